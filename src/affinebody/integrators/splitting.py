"""Explicit symplectic splittings of H = T + V (75a) into exact sub-flows.

- the kick K(h): exact flow of V (configuration fixed, momenta change), ``system.kick``;
- the drift D(h): flow of T, the palindromic composition of the kinetic terms' exact flows
  (``system.drift``; exact when T has one term or commuting terms).

The Strang step S(h) = K(h/2) D(h) K(h/2) is symplectic, time-reversible (S(-h) S(h) = id) and of
order 2. Symmetric compositions S(w_1 h) ... S(w_m h) raise the order (Yoshida 1990, Suzuki 1990):

- ``yoshida4``: triple jump w = (w1, w0, w1), w1 = 1/(2 - 2^(1/3)), w0 = 1 - 2 w1 (order 4);
- ``suzuki4``: fractal w = (p, p, 1 - 4p, p, p), p = 1/(4 - 4^(1/3)) (order 4, smaller error);
- ``yoshida6``: Yoshida's 7-stage solution A (order 6).

Adjacent half-kicks are merged, so a composition of m Strang steps costs m drifts and m + 1 kicks.
Every composition of exact flows is symplectic and keeps each momentum map that all sub-flows keep
(e.g. total linear momentum, affine momentum), so these are conserved to round-off.

On the subgroups SL, UL, SO, O, R+SO, R+O the kicks are projected and the drifts constrained
(``affinebody.constraints``: exact flows, Lie-group splittings, RATTLE), all symplectic and
symmetric on T*G, so the compositions keep their orders there as well.

Neighbour lists. :meth:`Splitting.advance` sums the pair forces over a neighbour list
(``affinebody.neighbors``) and updates the list after every drift, before the next kick (the only
sub-flow that moves the configuration is the drift), inside compiled code; ``simulate.run``
carries the list through its scan.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from affinebody import neighbors as nb
from affinebody.integrators.base import AbstractIntegrator
from affinebody.state import State
from affinebody.system import HamiltonianSystem


@dataclass(frozen=True)
class Splitting(AbstractIntegrator):
    """Symmetric composition S(w_1 h) ... S(w_m h) of Strang steps S = K(h/2) D(h) K(h/2)."""

    name: str
    order: int
    weights: tuple[float, ...]
    carries_forces: ClassVar[bool] = True
    uses_neighbor_lists: ClassVar[bool] = True

    def check(self, system: HamiltonianSystem) -> None:
        """Splittings ignore a rotationless (non-holonomic) constraint: refuse such systems."""
        refuse_nonholonomic(system, self.name)

    @property
    def drifts(self) -> tuple[float, ...]:
        """Drift coefficients d_1..d_m (= the weights)."""
        return self.weights

    @property
    def kicks(self) -> tuple[float, ...]:
        """Kick coefficients c_0..c_m after merging adjacent half-kicks."""
        w = self.weights
        inner = tuple(0.5 * (a + b) for a, b in zip(w[:-1], w[1:], strict=True))
        return (0.5 * w[0],) + inner + (0.5 * w[-1],)

    def step(self, system: HamiltonianSystem, state: State, h) -> State:
        """One step K(c_0 h) D(d_1 h) K(c_1 h) ... D(d_m h) K(c_m h) (pair terms over all
        pairs). The stages run in a ``lax.scan``, so compiling a 7-stage scheme costs about as
        much as compiling Strang."""
        return self.advance(system, state, system.forces(state), h)[0]

    def step_with_neighbors(self, system: HamiltonianSystem, state: State, h, spec,
                            neighbors) -> tuple[State, NeighborStep]:
        """The same step with the pair forces summed over a neighbour list.

        ``neighbors`` (a ``neighbors.NeighborList`` of the static ``spec``) must be valid for
        ``state``. It is updated (rebuilt where ``neighbors.needs_rebuild``) after every drift,
        before the kick that follows, so every kick sees a list that covers its configuration.
        Returns the new state and a :class:`NeighborStep`: the list, valid for the new state
        unless ``overflow`` is non-zero (then the step's forces may be wrong and the step must
        be discarded), and the number of rebuilds.
        """
        state, tracked, _ = self.advance(system, state, system.forces(state, neighbors), h,
                                         spec, neighbors)
        return state, tracked

    def advance(self, system: HamiltonianSystem, state: State, forces, h, spec=None,
                neighbors=None, middle=None, force_pass=None):
        """One step from ``state`` whose forces (``system.forces``) are ``forces``, returning
        (new state, :class:`NeighborStep` or None, forces at the new state).

        The last kick of a step and the first of the next act on the same configuration, so
        a run that carries the forces from step to step evaluates them once per stage, not
        twice ("first same as last"); the result is :meth:`step`'s to round-off. With
        ``spec`` and ``neighbors`` the pair forces are summed over the list, updated after
        every drift as in :meth:`step_with_neighbors`.

        middle: None, or a map of the momenta at fixed configuration (a thermostat's O step)
        done in the middle of the middle drift, D(d h/2) O D(d h/2): with Strang this is
        BAOAB, K(h/2) D(h/2) O(h) D(h/2) K(h/2) (Leimkuhler and Matthews 2013), and every
        composition stays symmetric.

        force_pass: None, or f(system, state, neighbors) -> (forces, extra) evaluating the
        forces in place of ``system.forces`` with more from the same pass (a barostat takes
        the virial, ``pressure.energy_forces_virial``); the step then returns (new state,
        NeighborStep or None, forces, extra), extra that of the last evaluation.
        """
        self.check(system)
        kicks = self.kicks
        state = system.kick(state, kicks[0] * h, forces=forces)
        tracked = None
        if spec is not None:
            zero = jnp.zeros((), dtype=jnp.int32)
            tracked = NeighborStep(neighbors, zero, zero, neighbors.count, neighbors.reach)
        evaluate = force_pass or (lambda system, s, nbrs: (system.forces(s, nbrs), ()))

        def stage(carry, coefficients, inner=None):
            s, tracked, _, _ = carry
            d, c = coefficients
            if inner is None:
                s = system.drift(s, d * h)
            else:
                s = system.drift(inner(system.drift(s, 0.5 * d * h)), 0.5 * d * h)
            current = None
            if spec is not None:
                tracked = update_neighbors(spec, tracked, s, system.cell)
                current = tracked.neighbors
            f, extra = evaluate(system, s, current)
            return (system.kick(s, c * h, forces=f), tracked, f, extra), None

        def stages(carry, first, last):
            if last - first == 1:
                return stage(carry, (self.drifts[first], kicks[first + 1]))[0]
            if last - first > 1:
                coefficients = (jnp.asarray(self.drifts[first:last]),
                                jnp.asarray(kicks[first + 1:last + 1]))
                return lax.scan(stage, carry, coefficients)[0]
            return carry

        extra = ()
        if force_pass is not None:  # its zero (a scan over stages carries it), by its shape
            extra = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(
                lambda: force_pass(system, state, None if spec is None else neighbors)[1]))
        carry = (state, tracked, forces, extra)
        m = len(self.drifts)
        if middle is None:
            carry = stages(carry, 0, m)
        else:
            mid = m // 2
            carry = stages(carry, 0, mid)
            carry = stage(carry, (self.drifts[mid], kicks[mid + 1]), middle)[0]
            carry = stages(carry, mid + 1, m)
        return carry if force_pass is not None else carry[:3]


class NeighborStep(NamedTuple):
    """A neighbour list after a step, with what the step's updates saw: rebuilds (count),
    overflow (OR of their ``NeighborList.overflow`` bits, see ``affinebody.neighbors``), and the
    largest pair count and reach of their lists (what a reallocation must hold)."""

    neighbors: nb.NeighborList
    rebuilds: jax.Array
    overflow: jax.Array
    most_pairs: jax.Array
    largest_reach: jax.Array


def update_neighbors(spec, tracked: NeighborStep, state: State, cell=None) -> NeighborStep:
    """``neighbors.update`` that also counts rebuilds and keeps every overflow flag; ``cell``:
    the current cell of a box that a barostat deforms, or None."""
    stale = nb.needs_rebuild(spec, tracked.neighbors, state.x, state.phi, cell)
    fresh = lax.cond(stale, lambda: nb.build(spec, state.x, state.phi, cell),
                     lambda: tracked.neighbors)
    return NeighborStep(fresh, tracked.rebuilds + stale.astype(jnp.int32),
                        tracked.overflow | fresh.overflow,
                        jnp.maximum(tracked.most_pairs, fresh.count),
                        jnp.maximum(tracked.largest_reach, fresh.reach))


_Y4 = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
_S4 = 1.0 / (4.0 - 4.0 ** (1.0 / 3.0))
# Yoshida (1990), Phys. Lett. A 150, 262, Table 1, solution A.
_Y6 = (0.784513610477560, 0.235573213359357, -1.17767998417887)
_Y6_0 = 1.0 - 2.0 * sum(_Y6)

STRANG = Splitting("strang", 2, (1.0,))
YOSHIDA4 = Splitting("yoshida4", 4, (_Y4, 1.0 - 2.0 * _Y4, _Y4))
SUZUKI4 = Splitting("suzuki4", 4, (_S4, _S4, 1.0 - 4.0 * _S4, _S4, _S4))
YOSHIDA6 = Splitting("yoshida6", 6, _Y6 + (_Y6_0,) + _Y6[::-1])


def refuse_nonholonomic(system, name: str) -> None:
    """ValueError when ``system`` has a rotationless constraint that integrator ``name``
    would ignore."""
    if getattr(system, "rotationless", None) is not None:
        raise ValueError(
            f"integrator {name!r} ignores the rotationless constraint "
            f"{system.rotationless!r}: use integrator = 'nonholonomic-rattle'"
        )


__all__ = [
    "Splitting", "NeighborStep", "update_neighbors", "STRANG", "YOSHIDA4", "SUZUKI4", "YOSHIDA6",
    "refuse_nonholonomic"
]
