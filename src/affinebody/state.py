"""Phase-space state of N affine bodies, eq. (5) and the canonical momenta (42), (50).

``State`` is a JAX pytree (a NamedTuple) with leading body axis N (and optionally more
leading batch axes in front, e.g. for ensembles):

- ``x``   [..., N, n]     centres of mass (spatial),
- ``phi`` [..., N, n, n]  internal configurations, phi[i, a] = phi^i_a
                          (row index spatial, column index material),
- ``p``   [..., N, n]     linear momenta p_i,
- ``pi``  [..., N, n, n]  momenta conjugate to phi in the paper's index placement
                          pi[a, i] = pi^a_i, paired as Tr(pi @ xi) (42); so the affine spins
                          are Sigma = phi @ pi and Sigma_hat = pi @ phi (45).

Hamilton's equations in this placement (docs/theory/conventions.md): dphi/dt = (dH/dpi)^T,
dpi/dt = -(dH/dphi)^T, where dH/dM is the array of partials with the shape of M.
"""

from __future__ import annotations

from typing import NamedTuple

import jax


class State(NamedTuple):
    """Canonical state (x, phi, p, pi) of N affine bodies; see the module docstring."""

    x: jax.Array
    phi: jax.Array
    p: jax.Array
    pi: jax.Array

    @property
    def n(self) -> int:
        """Spatial dimension n."""
        return self.phi.shape[-1]

    @property
    def bodies(self) -> int:
        """Number of bodies N."""
        return self.phi.shape[-3]


class VelocityState(NamedTuple):
    """Lagrangian state (x, phi, v, xi) with v = dx/dt, xi = dphi/dt (7)."""

    x: jax.Array
    phi: jax.Array
    v: jax.Array
    xi: jax.Array


__all__ = [
    "State", "VelocityState"
]
