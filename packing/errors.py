"""Exception types shared by every stage (three only, as meshio does)."""


class ChipstackError(Exception):
    """Base of every error this project raises on purpose."""


class InputError(ChipstackError, ValueError):
    """Bad user input: a scenario key, a file, a flag. The message names it."""


class SimulationError(ChipstackError, RuntimeError):
    """The physics went wrong (NaN poses, runaway energy, ...)."""
