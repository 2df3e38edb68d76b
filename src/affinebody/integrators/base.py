"""The integrator interface: what the run driver (``affinebody.simulate``) needs of a stepper.

An integrator is a small frozen dataclass (hashable: the driver passes it to ``jax.jit`` as a
static argument) with a ``name`` (the config's ``run.integrator``), its ``order``, and

- :meth:`~AbstractIntegrator.check` (system): a ``ValueError`` with a one-line reason when the
  integrator cannot integrate that system (e.g. implicit midpoint on a constrained group), so
  refusals come before any compilation;
- :meth:`~AbstractIntegrator.step` (system, state, h): one step, jit-compatible; a step that
  cannot be completed (no convergence) returns NaN, which the driver reports;
- ``carries_forces``: True when the integrator exposes ``advance(system, state, forces, h, spec,
  neighbors) -> (state, NeighborStep | None, forces)`` and reuses the forces of the last kick
  of a step as the first kick of the next (the splittings: "first same as last");
- ``uses_neighbor_lists``: True when ``advance`` can sum the pair forces over a neighbour
  list; the others sum over all pairs.
"""

from __future__ import annotations

import abc
from typing import ClassVar

from affinebody.state import State


class AbstractIntegrator(abc.ABC):
    """Base of every time stepper (see the module docstring)."""

    name: str
    order: int
    carries_forces: ClassVar[bool] = False
    uses_neighbor_lists: ClassVar[bool] = False

    def check(self, system) -> None:  # noqa: B027 - most integrators accept every system
        """Raise ``ValueError`` (one line, with the fix) when ``system`` cannot be integrated."""

    @abc.abstractmethod
    def step(self, system, state: State, h) -> State:
        """One step of size ``h`` (jit-compatible)."""


__all__ = ["AbstractIntegrator"]
