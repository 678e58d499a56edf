"""Error types. Anything a user can cause raises a subclass of :class:`HandFEError`;
the CLI prints its message and exits non-zero instead of showing a traceback."""


class HandFEError(Exception):
    """Base class for errors with a message meant for the user."""


class InputError(HandFEError, ValueError):
    """Bad input: a parameter, file, key or value out of range. The message names it."""


class ConfigError(InputError):
    """A configuration file has an unknown key, a wrong type or an out-of-range value."""


class SolverError(HandFEError, RuntimeError):
    """A solve failed; the message says which load step and why."""

    def __init__(self, message: str, *, load_step: int | None = None,
                 load_factor: float | None = None, residual: float | None = None):
        super().__init__(message)
        self.load_step = load_step
        self.load_factor = load_factor
        self.residual = residual
