"""The errors a user can cause, each reported by the CLI as one line (`mls-mpm: error: ...`, exit 2).

Every module raises a subclass of UserError for bad input (a scene key, an image, a folder, a result file),
so the CLI catches one class; SimulationError (exit 1) is a simulation that went wrong, not bad input.
Nothing here imports Taichi, so light modules (scene, optimize) can use these names.
"""


class UserError(ValueError):
    """Bad input; the message is one line naming the file, key or value and what is expected."""


class SimulationError(RuntimeError):
    """The simulation left the grid or went non-finite; the message names the step and the particle."""


class Interrupted(Exception):
    """SIGINT or SIGTERM asked a long job (rendering) to stop; what it had finished is kept."""
