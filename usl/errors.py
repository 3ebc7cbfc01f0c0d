"""One exception type for bad data, so CLIs can print a single clear line instead of a traceback."""


class UslError(Exception):
    """Bad input or a broken dataset: the message names the file and what is wrong."""


def one_line(exc: BaseException) -> str:
    """An exception as one line of text (library messages often span several)."""
    text = " ".join(str(exc).split())
    return text if text else type(exc).__name__


def error_line(exc: BaseException) -> str:
    """A UslError's message for a CLI's one error line, also when a DataLoader worker re-raised it
    (torch then puts the worker's whole traceback into the message; its last line is ours)."""
    text = str(exc)
    if "Original Traceback" in text:
        last = text.strip().splitlines()[-1]
        text = last.split(": ", 1)[1] if last.startswith(("usl.", "UslError")) and ": " in last else last
    return text


class UslWarning(UserWarning):
    """Something the user should know but that stops nothing (a value assumed, a saved setting
    ignored): the CLIs print it as one ``COMMAND: warning: ...`` line."""
