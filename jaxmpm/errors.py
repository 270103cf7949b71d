"""Errors a user can act on.

`SceneError` is raised while a scene is read or checked, before anything is compiled: its
message is one sentence naming the offending key and value. `SimulationError` reports a run
that went wrong (a particle left the grid, a stress became non-finite), naming the step, body
and particle.
"""


class SceneError(ValueError):
    """A scene (or calibration) input is invalid; the message names the key and value."""


class SimulationError(RuntimeError):
    """A run stopped early; the message names the step, body and particle, and `result`
    holds what was computed before."""

    def __init__(self, message, result=None):
        super().__init__(message)
        self.result = result
