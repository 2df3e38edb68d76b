"""Wall-clock phases of a command, with JAX's compilation time told apart.

``affinebody run --verbose`` prints where the time of a run went (set-up stages, compilation,
integration, output), so a slow set-up is visible and the integration rate excludes compiling.
Compilation is measured from JAX's own monitoring events (tracing, lowering and XLA compile
spans): :class:`CompileClock` merges their time spans, so nested events count once.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

#: JAX monitoring events whose spans make up "compiling".
COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)


class CompileClock:
    """Seconds JAX spent compiling while the clock was installed (union of event spans)."""

    def __init__(self) -> None:
        self._spans: list[tuple[float, float]] = []

    def _listener(self, event: str, start: float, end: float, **_kwargs) -> None:
        if event in COMPILE_EVENTS:
            self._spans.append((start, end))

    @contextmanager
    def installed(self) -> Iterator[CompileClock]:
        from jax import monitoring

        monitoring.register_event_time_span_listener(self._listener)
        try:
            yield self
        finally:
            monitoring.unregister_event_time_span_listener(self._listener)

    @property
    def seconds(self) -> float:
        total, reach = 0.0, -float("inf")
        for start, end in sorted(self._spans):
            if end <= reach:
                continue
            total += end - max(start, reach)
            reach = end
        return total


class Phases:
    """Named wall-clock phases, accumulated (``with phases("output"): ...``)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - start)

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds
