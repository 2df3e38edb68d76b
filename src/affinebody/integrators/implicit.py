"""Implicit midpoint rule: z' = z + h f((z + z')/2) with the autodiff vector field f.

Solved by fixed-point iteration (a ``lax.while_loop``, jit-compatible) to a relative tolerance
with a bounded number of iterations; for kinetic models without an exact splitting. It is
symplectic and symmetric, of order 2, and defined on GL+, GL and L (not on the constrained
groups). A step that does not converge returns NaN, which the run driver reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
from jax import lax

from affinebody.integrators.base import AbstractIntegrator
from affinebody.integrators.splitting import refuse_nonholonomic
from affinebody.state import State
from affinebody.system import HamiltonianSystem


@dataclass(frozen=True)
class ImplicitMidpoint(AbstractIntegrator):
    """Implicit midpoint rule by fixed-point iteration (see the module docstring)."""

    tol: float = 1e-14
    max_iter: int = 60
    name: str = "implicit-midpoint"
    order: int = 2

    def check(self, system: HamiltonianSystem) -> None:
        """Defined on GL+, GL and L, without a rotationless constraint."""
        refuse_nonholonomic(system, self.name)
        if system.constrained:
            raise ValueError(
                f"integrator 'implicit-midpoint' works on GL+, GL and L, not on {system.group}: "
                f"use a splitting integrator (strang, yoshida4, suzuki4, yoshida6)"
            )

    def step(self, system: HamiltonianSystem, state: State, h) -> State:
        """z' solving z' = z + h f((z + z')/2); NaN where not converged in ``max_iter``."""
        self.check(system)
        f = system.vector_field

        def update(z):
            mid = jax.tree.map(lambda a, b: 0.5 * (a + b), state, z)
            return jax.tree.map(lambda a, v: a + h * v, state, f(mid))

        def change(z_new, z):
            diffs = jax.tree.map(lambda a, b: jnp.max(jnp.abs(a - b) / (1.0 + jnp.abs(b))),
                                 z_new, z)
            return jnp.max(jnp.stack(jax.tree.leaves(diffs)))

        def cond(carry):
            _, k, err = carry
            return (err > self.tol) & (k <= self.max_iter)

        def body(carry):
            z, k, _ = carry
            z_new = update(z)
            return z_new, k + 1, change(z_new, z)

        # from z = state, whose update is the first iterate: one copy of the vector field in
        # the compiled graph instead of two (half the time to trace and compile the step)
        z, _, err = lax.while_loop(cond, body, (state, 0, jnp.asarray(jnp.inf, state.x.dtype)))
        # round-off can stall the iteration a little above tol: accept 100 tol
        ok = err <= 100.0 * self.tol
        return jax.tree.map(lambda a: jnp.where(ok, a, jnp.nan), z)


IMPLICIT_MIDPOINT = ImplicitMidpoint()

__all__ = ["IMPLICIT_MIDPOINT", "ImplicitMidpoint"]
