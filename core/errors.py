"""Exception types shared by every stage (three only, as meshio does)."""


class ChipstackError(Exception):
    """Base of every error this project raises on purpose."""


class InputError(ChipstackError, ValueError):
    """Bad user input: a scenario key, a file, a flag. The message names it."""


class StoppedEarly(ChipstackError, RuntimeError):
    """Work stopped on purpose before its end (a time limit), its finished parts kept:
    the same command resumes it. The message says where it stopped."""


class SimulationError(ChipstackError, RuntimeError):
    """The physics went wrong (NaN poses, runaway energy, ...)."""


MAX_QUOTED = 200  # characters of a user's value an error message quotes


def printable(text: object) -> str:
    """``text`` as is when it prints on one line, else its repr (messages stay one line),
    cut to its first ``MAX_QUOTED`` characters (a 5 MB value stays a short line)."""
    text = str(text)
    shown = text if text.isprintable() else repr(text)
    return _bounded(shown)


def brief(value: object) -> str:
    """The repr of ``value`` for an error message: one line, at most ``MAX_QUOTED``
    characters and a count of the rest."""
    return _bounded(repr(value))


def _bounded(shown: str) -> str:
    if len(shown) <= MAX_QUOTED:
        return shown
    return f"{shown[:MAX_QUOTED]}... ({len(shown):,} characters)"
