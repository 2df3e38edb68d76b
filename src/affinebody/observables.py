"""Observables of N affine bodies as pure functions of a ``State`` (batched over leading axes).

Momentum maps of the symmetries of section "General quantization ideas", eqs. (103), (108), (109):

- total linear momentum            p = sum_K p_K                        (translations),
- total affine spin (spatial)      Sigma = sum_K phi_K pi_K             (phi_K -> A phi_K),
- total affine spin (co-moving)    Sigma_hat = sum_K pi_K phi_K         (phi_K -> phi_K B),
- orbital affine momentum          Lambda = sum_K x_K p_K^T             (x_K -> A x_K),
- total affine momentum            J = Lambda + Sigma             (x_K, phi_K -> A x_K, A phi_K),
- angular momentum                 J - J^T = (Lambda - Lambda^T) + S    (spatial rotations; doubled
                                   skew part, the convention of (49): S = Sigma - Sigma^T),
- vorticity                        Sigma_hat - Sigma_hat^T              (material rotations, (49)).

Each is conserved exactly when the Hamiltonian is invariant under its group (Noether):
Tr(Z J) generates (x, phi) -> (exp(sZ) x, exp(sZ) phi); Tr(Z Sigma_hat) generates
phi -> phi exp(sZ).

Volumes: det phi_K and the relative volumes det Gamma[phi_K, phi_L] = det phi_L / det phi_K (79).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody import momenta
from affinebody._checks import transpose
from affinebody.state import State


def linear_momentum(state: State) -> jax.Array:
    """Total linear momentum sum_K p_K, shape [..., n] (103)."""
    return jnp.sum(state.p, axis=-2)


def affine_spins(state: State) -> jax.Array:
    """Per-body spatial affine spins Sigma_K = phi_K pi_K, shape [..., N, n, n] (45)."""
    return momenta.affine_spin(state.phi, state.pi)


def comoving_affine_spins(state: State) -> jax.Array:
    """Per-body co-moving affine spins Sigma_hat_K = pi_K phi_K, shape [..., N, n, n] (45)."""
    return momenta.comoving_affine_spin(state.phi, state.pi)


def affine_spin(state: State) -> jax.Array:
    """Total spatial affine spin sum_K phi_K pi_K, shape [..., n, n] (103)."""
    return jnp.sum(affine_spins(state), axis=-3)


def comoving_affine_spin(state: State) -> jax.Array:
    """Total co-moving affine spin sum_K pi_K phi_K, shape [..., n, n] (103)."""
    return jnp.sum(comoving_affine_spins(state), axis=-3)


def orbital_affine_momentum(state: State) -> jax.Array:
    """Orbital affine momentum Lambda^a_b = sum_K x_K^a p_Kb, shape [..., n, n] (108)."""
    return jnp.sum(state.x[..., :, None] * state.p[..., None, :], axis=-3)


def affine_momentum(state: State) -> jax.Array:
    """Total affine momentum J = Lambda + Sigma, shape [..., n, n] (108), (109)."""
    return orbital_affine_momentum(state) + affine_spin(state)


def angular_momentum(state: State) -> jax.Array:
    """Total angular momentum J - J^T (doubled skew part, convention of (49)), [..., n, n]."""
    j = affine_momentum(state)
    return j - transpose(j)


def spin(state: State) -> jax.Array:
    """Total internal spin S = Sigma - Sigma^T (49), shape [..., n, n]."""
    s = affine_spin(state)
    return s - transpose(s)


def vorticity(state: State) -> jax.Array:
    """Total vorticity V = Sigma_hat - Sigma_hat^T (49), shape [..., n, n]."""
    s = comoving_affine_spin(state)
    return s - transpose(s)


def dilatation_momentum(state: State) -> jax.Array:
    """Tr Sigma = sum_K Tr(phi_K pi_K), generator of the global scaling phi_K -> e^s phi_K."""
    return jnp.trace(affine_spin(state), axis1=-2, axis2=-1)


def volumes(state: State) -> jax.Array:
    """Volumes det phi_K, shape [..., N]."""
    return linalg.det(state.phi)


def relative_volumes(state: State) -> jax.Array:
    """Relative volumes det Gamma[phi_K, phi_L] = det(phi_K^-1 phi_L), shape [..., N, N] (79)."""
    det = volumes(state)
    return det[..., None, :] / det[..., :, None]


__all__ = [
    "linear_momentum", "affine_spins", "comoving_affine_spins", "affine_spin",
    "comoving_affine_spin", "orbital_affine_momentum", "affine_momentum", "angular_momentum",
    "spin", "vorticity", "dilatation_momentum", "volumes", "relative_volumes"
]
