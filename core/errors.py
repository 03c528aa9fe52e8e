"""Exception types shared by every stage (three only, as meshio does)."""


class ChipstackError(Exception):
    """Base of every error this project raises on purpose."""


class InputError(ChipstackError, ValueError):
    """Bad user input: a scenario key, a file, a flag. The message names it."""


class SimulationError(ChipstackError, RuntimeError):
    """The physics went wrong (NaN poses, runaway energy, ...)."""


def printable(text: object) -> str:
    """``text`` as is when it prints on one line, else its repr (messages stay one line)."""
    text = str(text)
    return text if text.isprintable() else repr(text)
