"""How long JAX spends compiling: tracing, lowering and XLA's compile (or loading the program
from the persistent compilation cache), summed from the durations JAX reports through
`jax.monitoring` while a `CompileClock` is open.

    with CompileClock() as timing:
        ...
    timing.seconds, timing.elapsed      # compiling, and wall time since it opened

Only top-level traces are reported by JAX, so nested programs are not counted twice. The
clock hears every thread of the process: a compile elsewhere at the same time counts too.
"""

import time

import jax

COMPILE_EVENTS = frozenset((
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
))


class CompileClock:
    """A context manager summing the seconds JAX reports compiling while it is open."""

    def __init__(self):
        self.seconds = 0.0
        self.open = False
        self.opened_at = time.monotonic()

    @property
    def elapsed(self) -> float:
        """Wall time since the clock opened [s]."""
        return time.monotonic() - self.opened_at

    def record(self, event, duration, **_):
        if self.open and event in COMPILE_EVENTS:
            self.seconds += float(duration)

    def __enter__(self):
        self.open, self.opened_at = True, time.monotonic()
        jax.monitoring.register_event_duration_secs_listener(self.record)
        return self

    def __exit__(self, *_):
        self.open = False             # inert from here even where JAX cannot unregister it
        unregister = getattr(jax.monitoring, "unregister_event_duration_listener", None)
        if unregister is not None:
            unregister(self.record)
