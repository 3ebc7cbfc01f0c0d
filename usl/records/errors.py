"""One exception type for bad data, so CLIs can print a single clear line instead of a traceback."""


class UslError(Exception):
    """Bad input or a broken dataset: the message names the file and what is wrong."""
