"""One exception type for bad data, so CLIs can print a single clear line instead of a traceback."""


class UslError(Exception):
    """Bad input or a broken dataset: the message names the file and what is wrong."""


def one_line(exc: BaseException) -> str:
    """An exception as one line of text (library messages often span several)."""
    text = " ".join(str(exc).split())
    return text if text else type(exc).__name__
