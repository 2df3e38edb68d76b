"""Nonholonomic RATTLE: the discrete Lagrange-d'Alembert step with velocity projection, the
integrator of rotationless (non-holonomic) systems (40), (41); the constraint itself is in
:mod:`affinebody.nonholonomic` and in docs/constrained_motion.md.

With the discrete Lagrangian L_d(q0, q1) = h/2 [L(q0, (q1 - q0)/h) + L(q1, (q1 - q0)/h)] the
step solves -D1 L_d(q0, q1) = p0 + C^T lambda together with the constraint at the midpoint for
the discrete velocity (and ln|det phi1| = 0 on SL, UL), by a blockwise Newton iteration; the
momentum at q1 is D2 L_d projected onto the admissible ones (the kinetic-metric projection).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody._checks import transpose
from affinebody.constraints import newton_blockwise
from affinebody.groups import lie_algebra
from affinebody.integrators.base import AbstractIntegrator
from affinebody.nonholonomic import (
    admissible_momentum,
    constraint_count,
    constraint_impulse,
    velocity_constraint,
)
from affinebody.state import State, VelocityState


def _discrete_constraint(phi0, phi1, h, rotationless: str, group: str) -> jax.Array:
    """C at the midpoint for the discrete velocity (phi1 - phi0)/h; ln|det phi1| on SL/UL."""
    mid = 0.5 * (phi0 + phi1)
    c = velocity_constraint(mid, (phi1 - phi0) / h, rotationless, "GL+")
    if lie_algebra(group) == "sl":
        c = jnp.concatenate([c, linalg.slogdet(phi1)[1][..., None]], axis=-1)
    return c


def _potential_gradient(system, x, phi):
    if system.potential is None:
        return jnp.zeros_like(x), jnp.zeros_like(phi)
    return jax.grad(lambda a, b: jnp.sum(system.potential.energy(a, b)), argnums=(0, 1))(x, phi)


def _pack(x, phi, lam):
    return jnp.concatenate([x, phi.reshape(phi.shape[:-2] + (-1,)), lam], axis=-1)


def _unpack(z, n: int):
    x = z[..., :n]
    phi = z[..., n:n + n * n].reshape(z.shape[:-1] + (n, n))
    return x, phi, z[..., n + n * n:]


@dataclass(frozen=True)
class NonholonomicRattle(AbstractIntegrator):
    """Discrete Lagrange-d'Alembert step with velocity projection (module docstring).

    Needs a system with ``rotationless`` set. A step whose Newton iteration does not converge
    returns NaN, which the run driver reports.
    """

    tol: float = 1e-13
    max_iter: int = 30
    name: str = "nonholonomic-rattle"
    order: int = 2

    def check(self, system) -> None:
        """Only for systems with a rotationless constraint."""
        if system.rotationless is None:
            raise ValueError(
                "integrator 'nonholonomic-rattle' integrates rotationless motion: set "
                "constraints.rotationless = 'spatial' or 'material' (or use a splitting integrator)"
            )

    def step(self, system, state: State, h) -> State:
        """One step of size h from a state with admissible velocity."""
        self.check(system)
        kind, group, kinetic = system.rotationless, system.group, system.kinetic
        n = state.phi.shape[-1]
        m = constraint_count(n, group)

        def t_grads(x, phi, v, xi):
            return jax.grad(lambda *a: jnp.sum(kinetic.lagrangian(VelocityState(*a))),
                            argnums=(0, 1, 2, 3))(x, phi, v, xi)

        x0, phi0 = state.x, state.phi
        dvx0, dvphi0 = _potential_gradient(system, x0, phi0)

        def momenta(x1, phi1, at_end: bool):
            """(-D1 L_d) or (D2 L_d): the discrete momenta at q0 or q1 (kinetic + V parts)."""
            v, xi = (x1 - x0) / h, (phi1 - phi0) / h
            gx0, gphi0, gv0, gxi0 = t_grads(x0, phi0, v, xi)
            gx1, gphi1, gv1, gxi1 = t_grads(x1, phi1, v, xi)
            if not at_end:
                return (0.5 * (gv0 + gv1) - 0.5 * h * (gx0 - dvx0),
                        0.5 * (gxi0 + gxi1) - 0.5 * h * (gphi0 - dvphi0))
            dvx1, dvphi1 = _potential_gradient(system, x1, phi1)
            return (0.5 * (gv0 + gv1) + 0.5 * h * (gx1 - dvx1),
                    0.5 * (gxi0 + gxi1) + 0.5 * h * (gphi1 - dvphi1))

        def residual(z):
            x1, phi1, lam = _unpack(z, n)
            px, pphi = momenta(x1, phi1, at_end=False)
            impulse = transpose(constraint_impulse(phi0, lam, kind, group))
            return _pack(px - state.p, pphi - transpose(state.pi) - impulse,
                         _discrete_constraint(phi0, phi1, h, kind, group))

        start = kinetic.inverse_legendre(state)
        z0 = _pack(x0 + h * start.v, phi0 + h * start.xi,
                   jnp.zeros(phi0.shape[:-2] + (m,), phi0.dtype))
        z, converged = newton_blockwise(residual, z0, self.tol, self.max_iter)
        x1, phi1, _ = _unpack(z, n)
        p1, pphi1 = momenta(x1, phi1, at_end=True)
        out = admissible_momentum(kinetic, State(x1, phi1, p1, transpose(pphi1)), kind, group)
        return jax.tree.map(lambda a: jnp.where(converged, a, jnp.nan), out)


NONHOLONOMIC_RATTLE = NonholonomicRattle()

__all__ = ["NONHOLONOMIC_RATTLE", "NonholonomicRattle"]
