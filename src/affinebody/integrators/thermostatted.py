"""An integrator with a thermostat's O step composed in.

Where the O step goes is the thermostat's ``splitting`` (``thermostats.SPLITTINGS``):

- ``"obabo"`` (the default): after the whole step of the integrator ``I``, I(h) O(h). Repeated,
  this is OBABO, O(h/2) K(h/2) D(h) K(h/2) O(h/2) for Strang, with the half O steps of
  consecutive steps merged into one O(h) (exact in law: the Ornstein-Uhlenbeck flow and
  Bussi's process for K are semigroups): one drift and one noise draw per step, the
  geometric Langevin algorithm of Bou-Rabee and Owhadi (2010). The frames see the
  configuration of OBABO; their momenta have had one more O(h/2).
- ``"baoab"``: in the middle of the middle drift of a splitting ``S``, K D(h/2) O(h) D(h/2) K
  (BAOAB for Strang, Leimkuhler and Matthews 2013; every composition stays symmetric); with
  any other integrator (the nonholonomic RATTLE of rotationless motion, implicit midpoint)
  the symmetric O(h/2) I(h) O(h/2).

Either way the exact drifts and kicks, the neighbour lists and the forces carried from step to
step ("first same as last") are those of the integrator (O changes only the momenta). What
it carries instead of the forces is a ``thermostats.ThermostatCarry``: the forces, the global
index of the last step (the step k draws its noise from ``fold_in(PRNGKey(seed), k)``), the
heat put in so far, and the constant noise factors of the momentum coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp

from affinebody import thermostats as th
from affinebody.integrators.base import AbstractIntegrator
from affinebody.integrators.splitting import Splitting
from affinebody.state import State


@dataclass(frozen=True)
class Thermostatted(AbstractIntegrator):
    """``splitting`` (any integrator, module docstring) with ``thermostat`` (a
    ``thermostats.Langevin`` or ``Bussi``)."""

    splitting: AbstractIntegrator
    thermostat: object
    carries_forces: ClassVar[bool] = True

    @property
    def uses_neighbor_lists(self) -> bool:  # type: ignore[override]
        return self.splitting.uses_neighbor_lists

    @property
    def name(self) -> str:
        return self.splitting.name

    @property
    def order(self) -> int:
        return min(self.splitting.order, 2)

    def check(self, system) -> None:
        """The splitting's refusals (the thermostat's own, a positive definite T, need n:
        ``thermostats.check``, which ``simulate.run`` calls)."""
        self.splitting.check(system)

    def initial_carry(self, system, state: State, forces, first_step=0,
                      heat=0.0) -> th.ThermostatCarry:
        """The carry at ``state`` (global step index ``first_step``, heat so far ``heat``)."""
        return th.ThermostatCarry(forces, jnp.asarray(first_step, dtype=jnp.int64),
                                  jnp.asarray(heat, dtype=state.x.dtype),
                                  th.factors(system, state))

    def advance(self, system, state: State, carry: th.ThermostatCarry, h, spec=None,
                neighbors=None):
        """One thermostatted step; returns (state, NeighborStep or None, new carry)."""
        step = carry.step + 1
        key = th.step_key(self.thermostat, step)

        def o_step(s, length, key):
            return th.thermostat_step(system, self.thermostat, s, length, key, carry.factors)

        if self.thermostat.splitting == "obabo":
            if isinstance(self.splitting, Splitting):
                state, tracked, forces = self.splitting.advance(system, state, carry.forces, h,
                                                                spec, neighbors)
            else:
                state, tracked, forces = self.splitting.step(system, state, h), None, carry.forces
            state, heat = o_step(state, h, key)
            return state, tracked, carry._replace(forces=forces, step=step,
                                                  heat=carry.heat + heat)
        exchanged = []

        def middle(s):
            new, heat = o_step(s, h, key)
            exchanged.append(heat)
            return new

        if isinstance(self.splitting, Splitting):
            state, tracked, forces = self.splitting.advance(system, state, carry.forces, h,
                                                            spec, neighbors, middle=middle)
            return state, tracked, carry._replace(forces=forces, step=step,
                                                  heat=carry.heat + exchanged[0])
        first, last = (jax.random.fold_in(key, k) for k in (0, 1))
        state, heat_1 = o_step(state, 0.5 * h, first)
        state = self.splitting.step(system, state, h)
        state, heat_2 = o_step(state, 0.5 * h, last)
        return state, None, carry._replace(step=step, heat=carry.heat + heat_1 + heat_2)

    def step_with_neighbors(self, system, state: State, h, spec, neighbors):
        """The splitting's step over a neighbour list, without the thermostat (what the
        driver's diagnosis of a blow-up integrates with dt/10)."""
        return self.splitting.step_with_neighbors(system, state, h, spec, neighbors)

    def step(self, system, state: State, h) -> State:
        """One step from step index 0 (the driver uses :meth:`advance` and carries it)."""
        carry = self.initial_carry(system, state, system.forces(state))
        return self.advance(system, state, carry, h)[0]


__all__ = ["Thermostatted"]
