"""Instantaneous pressure tensor and volume of N affine bodies in a periodic box
(docs/pressure.md).

For a strain eps [n, n] acting on the centres and on the box as x -> (Id + eps)^T x,
H -> (Id + eps)^T H, with conjugate momenta p -> (Id + eps)^-1 p (a canonical point
transformation) and the internal configurations phi_K (and pi_K) left alone,

    P_ab = -(1/V) dH/d(eps_ab) at eps = 0
         = (1/V) [ sum_K v_Ka p_Kb  +  W_ab ],       W = -dV/d(eps)   (the virial),

with V = det H, v_K = dT/dp_K the velocity of the centre given by the model's Legendre map
(any translational model, d'Alembert or the phi-dependent af-is one (64)), and for pair terms

    W_ab = sum_{pairs} u_a F_b,   u = x_K - x_L (minimum image),  F = -dV_KL/du,

where dV_KL/du collects the dependence through r and through the affine distance D (75) (whose
metric (C[phi_K] + C[phi_L])/2 is held fixed with phi). One-body terms of the centres contribute
-sum_K x_K (dV/dx_K)^T. The body shapes phi are not strained with the box: they are internal
degrees of freedom the ensemble integrates over at every volume, as molecular orientations are
(docs/pressure.md gives the argument). The isotropic pressure is Tr P / n.

The virial of pair terms is computed by :func:`affinebody.pair_kernels.pair_virial` from the
same per-pair gradient dV_KL/du that the forces of a neighbour-list run use, over the run's
neighbour list (O(N)) or over all pairs; :func:`energy_forces_virial` gives it with the energy
and the forces from one pass over a list (an NPT step's force evaluation before a move).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg as linalg
from affinebody import pair_kernels
from affinebody.potentials import PairTerm, terms_of
from affinebody.space import Space, as_space


def volume(space: Space, cell=None):
    """V = det H of a periodic box (ValueError in free space: no volume, no pressure);
    ``cell``: the current cell matrix of a box that a barostat deforms (``space`` is then its
    reference), or None."""
    space = as_space(space)
    if not space.periodic:
        raise ValueError("pressure and volume need a periodic box: set system.box")
    return space.volume if cell is None else linalg.det(jnp.asarray(cell))


def kinetic_tensor(system, state) -> jax.Array:
    """sum_K v_K p_K^T [..., n, n] with v_K = dT/dp_K (the model's Legendre map)."""
    velocity = jax.grad(lambda p: jnp.sum(system.kinetic_energy(state._replace(p=p))))(state.p)
    return jnp.einsum("...ka,...kb->...ab", velocity, state.p)


def check_space(system, space: Space) -> Space:
    """``space`` as a periodic Space that every pair term of ``system`` lives in (ValueError
    otherwise: the virial of a term in another box would not be this box's)."""
    space = as_space(space)
    volume(space)
    for term in terms_of(system.potential):
        if isinstance(term, PairTerm) and term.space != space:
            raise ValueError(
                f"pressure: the pair term {type(term).__name__} lives in {term.space}, not in "
                f"the box {space} of the pressure (give the pair terms the system's box)")
    return space


def _pairs(x, neighbors):
    """(i, j, count) of a list, or of all N(N-1)/2 pairs without one."""
    if neighbors is None:
        i, j = (jnp.asarray(a, dtype=jnp.int32) for a in np.triu_indices(x.shape[0], 1))
        return i, j, i.shape[0]
    return neighbors.i, neighbors.j, jnp.minimum(neighbors.count, neighbors.i.shape[0])


def _one_body(term, x, phi, forces: bool):
    """(V, dV/dx, dV/dphi or None) of a term that is not a pair term (one-body terms and any
    other energy of x, phi)."""
    if forces:
        e, (gx, gphi) = jax.value_and_grad(lambda y, f: jnp.sum(term.energy(y, f)),
                                           argnums=(0, 1))(x, phi)
        return e, gx, gphi
    e, gx = jax.value_and_grad(lambda y: jnp.sum(term.energy(y, phi)))(x)
    return e, gx, None


def virial(system, state, space: Space, neighbors=None, energy: bool = False):
    """W = -dV/d(eps) [n, n] of one system (x [N, n]); see the module docstring. With
    ``energy``: (V, W), the potential energy from the same pass over the pairs.

    neighbors: None (pair terms over all pairs, O(N^2)) or a ``neighbors.NeighborList`` valid
    for ``state`` that covers the pair cut-off (O(N)), as in a neighbour-list run.
    With ``system.cell`` set (a barostat), the minimum images are those of that cell.
    """
    space = check_space(system, space)
    x, phi = state.x, state.phi
    n = x.shape[-1]
    total = jnp.zeros((n, n), dtype=x.dtype)
    potential = jnp.zeros((), dtype=x.dtype)
    for term in terms_of(system.potential):
        if isinstance(term, PairTerm):
            if x.shape[0] > 1:
                e, w = pair_kernels.pair_virial(term, space, x, phi, *_pairs(x, neighbors),
                                                system.cell, energy=True)
                total, potential = total + w, potential + e
        else:  # one-body terms (and any other energy of x): W = -sum_K x_K (dV/dx_K)^T
            e, g, _ = _one_body(term, x, phi, forces=False)
            total, potential = total - jnp.einsum("ka,kb->ab", x, g), potential + e
    return (potential, total) if energy else total


def energy_forces_virial(system, state, space: Space, neighbors):
    """(V, (dV/dx, dV/dphi), W) of one system from one pass over the list's pairs
    (``pair_kernels.pair_sum`` with ``virial``): the forces of ``system.energy_and_forces`` and
    the W of :func:`virial`, so that a barostat move right after a step's force evaluation
    needs no pass of its own. ``neighbors``: a list valid for ``state`` (in ``system.cell``
    when set) that covers the pair cut-off."""
    space = check_space(system, space)
    x, phi = state.x, state.phi
    n = x.shape[-1]
    potential = jnp.zeros((), dtype=x.dtype)
    gx, gphi = jnp.zeros_like(x), jnp.zeros_like(phi)
    total = jnp.zeros((n, n), dtype=x.dtype)
    for term in terms_of(system.potential):
        if isinstance(term, PairTerm):
            if x.shape[0] < 2:
                continue
            e, tx, tphi, w = pair_kernels.pair_sum(term, space, x, phi, *_pairs(x, neighbors),
                                                   system.cell, virial=True)
        else:
            e, tx, tphi = _one_body(term, x, phi, forces=True)
            w = -jnp.einsum("ka,kb->ab", x, tx)
        potential, gx, gphi, total = potential + e, gx + tx, gphi + tphi, total + w
    return potential, (gx, gphi), total


def pressure_tensor(system, state, space: Space, neighbors=None, energy: bool = False,
                    measured=None):
    """P = (sum_K v_K p_K^T + W) / V [n, n] (module docstring); ``neighbors`` as in
    :func:`virial`; with ``energy``: (V, P), the potential energy from the same pass.
    ``measured``: None, or (V, W) of ``state`` already known (:func:`energy_forces_virial`
    in a step's last force evaluation): then no pass over the pairs here."""
    v = volume(space, system.cell)
    potential, w = (virial(system, state, space, neighbors, energy=True) if measured is None
                    else measured)
    p = (kinetic_tensor(system, state) + w) / v
    return (potential, p) if energy else p


@dataclass(frozen=True)
class Observer:
    """An observer of the run driver (``simulate.run(..., observers={name: Observer(...)})``):
    ``quantity`` "pressure" (the tensor) or "volume" in the periodic box ``space``, evaluated
    with the run's system and, in a neighbour-list run, its list (O(N))."""

    quantity: str
    space: Space

    #: the driver calls it as f(system, state, neighbors) rather than f(state)
    takes_system = True

    def __call__(self, system, state, neighbors=None):
        if self.quantity == "volume":
            return jnp.asarray(volume(self.space, system.cell), dtype=state.x.dtype)
        return pressure_tensor(system, state, self.space, neighbors)


def scalar_pressure(tensor: jax.Array) -> jax.Array:
    """The isotropic pressure Tr P / n."""
    return jnp.trace(tensor, axis1=-2, axis2=-1) / tensor.shape[-1]


__all__ = [
    "Observer", "check_space", "energy_forces_virial", "kinetic_tensor", "pressure_tensor",
    "scalar_pressure", "virial", "volume",
]
