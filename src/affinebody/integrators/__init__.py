"""Time steppers for a ``HamiltonianSystem``, one file per family, and their registry.

- :mod:`.splitting`: explicit symplectic splittings of exact flows (``strang``, ``yoshida4``,
  ``suzuki4``, ``yoshida6``), with neighbour lists and forces carried from step to step;
- :mod:`.implicit`: ``implicit-midpoint`` for kinetic models without an exact splitting;
- :mod:`.rattle`: ``nonholonomic-rattle``, the only integrator of rotationless systems (40), (41).

Each is an :class:`~.base.AbstractIntegrator`; :data:`INTEGRATORS` (name -> integrator) is the
one list of names: config validation, the CLI's messages and the driver all read it.
"""

from __future__ import annotations

from collections.abc import Callable

import jax

from affinebody.integrators.base import AbstractIntegrator
from affinebody.integrators.implicit import IMPLICIT_MIDPOINT, ImplicitMidpoint
from affinebody.integrators.rattle import NONHOLONOMIC_RATTLE, NonholonomicRattle
from affinebody.integrators.splitting import (
    STRANG,
    SUZUKI4,
    YOSHIDA4,
    YOSHIDA6,
    NeighborStep,
    Splitting,
)
from affinebody.integrators.thermostatted import Thermostatted
from affinebody.state import State

Step = Callable[[State, jax.Array], State]

#: Integrators by name (the names configs use).
INTEGRATORS: dict[str, AbstractIntegrator] = {
    s.name: s for s in (STRANG, YOSHIDA4, SUZUKI4, YOSHIDA6, IMPLICIT_MIDPOINT,
                        NONHOLONOMIC_RATTLE)
}
#: Names of the integrators that can sum pair forces over a neighbour list.
NEIGHBOR_LIST_INTEGRATORS = tuple(k for k, v in INTEGRATORS.items() if v.uses_neighbor_lists)


def get_integrator(integrator) -> AbstractIntegrator:
    """An integrator object from a name in INTEGRATORS (or the object itself)."""
    if isinstance(integrator, str):
        if integrator not in INTEGRATORS:
            raise ValueError(
                f"unknown integrator {integrator!r} (choose one of {', '.join(INTEGRATORS)})"
            )
        return INTEGRATORS[integrator]
    if not isinstance(integrator, AbstractIntegrator):
        raise ValueError(f"integrator must be a name or an AbstractIntegrator (got {integrator!r})")
    return integrator


def step_function(system, integrator="strang") -> Step:
    """``step(state, h) -> state`` for ``system`` with the chosen integrator (not jitted);
    refuses, with the integrator's one-line reason, a system it cannot integrate."""
    method = get_integrator(integrator)
    method.check(system)
    return lambda state, h: method.step(system, state, h)


__all__ = [
    "AbstractIntegrator", "IMPLICIT_MIDPOINT", "INTEGRATORS", "ImplicitMidpoint",
    "NEIGHBOR_LIST_INTEGRATORS", "NONHOLONOMIC_RATTLE", "NeighborStep", "NonholonomicRattle",
    "STRANG", "SUZUKI4", "Splitting", "Step", "Thermostatted", "YOSHIDA4", "YOSHIDA6",
    "get_integrator",
    "step_function",
]
