"""Poisson brackets of the affine-body phase space, eq. (87), in closed form and by autodiff.

Canonical bracket in the project's index placement (``pi[a, i]`` = pi^a_i, see ``state.py``):

    {F, G} = sum_K [ dF/dx_K . dG/dp_K - dF/dp_K . dG/dx_K
                     + Tr(dF/dphi_K @ dG/dpi_K) - Tr(dG/dphi_K @ dF/dpi_K) ],

so that ``{phi^i_a, pi^b_j} = delta^i_j delta^b_a`` and ``dF/dt = {F, H}`` (53), (87).

Closed forms (one body; different bodies commute), with Sigma = phi pi, Sigma_hat = pi phi (45):

    {Sigma^i_j, Sigma^k_l}             =  delta^i_l Sigma^k_j - delta^k_j Sigma^i_l,
    {Sigma_hat^A_B, Sigma_hat^C_D}     =  delta^C_B Sigma_hat^A_D - delta^A_D Sigma_hat^C_B,
    {Sigma^i_j, Sigma_hat^A_B}         =  0,

i.e. for the linear functions Sigma(Z) = Tr(Z Sigma), Sigma_hat(Z) = Tr(Z Sigma_hat), Z in gl(n):
``{Sigma(Z1), Sigma(Z2)} = Sigma([Z1, Z2])`` and ``{Sigma_hat(Z1), Sigma_hat(Z2)} =
-Sigma_hat([Z1, Z2])`` -- the structure constants of gl(n) (left and right regular translations
commute, hence the vanishing mixed bracket). With a configuration function F(phi), D = dF/dphi:

    {Sigma, F} = -phi D^T,   {Sigma_hat, F} = -D^T phi,   {p, f(x)} = -df/dx,

the first-order operators generating left and right regular translations in GL(n) (text after (87)).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from affinebody._checks import transpose
from affinebody.state import State


def canonical_bracket(F: Callable[[State], jax.Array], G: Callable[[State], jax.Array],
                      state: State) -> jax.Array:
    """{F, G} at ``state`` by autodiff; F, G may be array-valued: result shape F.shape + G.shape.

    ``state`` is one unbatched State ([N, n], [N, n, n], ...).
    """
    jf = jax.jacrev(F)(state)
    jg = jax.jacrev(G)(state)
    nf = len(jax.eval_shape(F, state).shape)
    ng = len(jax.eval_shape(G, state).shape)

    def pair(a, b):
        # contract the trailing (phase-space) axes of a with those of b
        k = a.ndim - nf
        return jnp.tensordot(a, b, axes=(list(range(nf, nf + k)), list(range(ng, ng + k))))

    return (pair(jf.x, jg.p) - pair(jf.p, jg.x)
            + pair(jf.phi, transpose(jg.pi)) - pair(jf.pi, transpose(jg.phi)))


def sigma_bracket(sigma: jax.Array) -> jax.Array:
    """{Sigma^i_j, Sigma^k_l} = delta^i_l Sigma^k_j - delta^k_j Sigma^i_l as T[..., i, j, k, l]."""
    eye = jnp.eye(sigma.shape[-1], dtype=sigma.dtype)
    return (jnp.einsum("il,...kj->...ijkl", eye, sigma)
            - jnp.einsum("kj,...il->...ijkl", eye, sigma))


def comoving_sigma_bracket(sigma_hat: jax.Array) -> jax.Array:
    """{Sh^A_B, Sh^C_D} = delta^C_B Sh^A_D - delta^A_D Sh^C_B as T[..., A, B, C, D]."""
    eye = jnp.eye(sigma_hat.shape[-1], dtype=sigma_hat.dtype)
    return (jnp.einsum("cb,...ad->...abcd", eye, sigma_hat)
            - jnp.einsum("ad,...cb->...abcd", eye, sigma_hat))


def sigma_linear_bracket(z1: jax.Array, z2: jax.Array, sigma: jax.Array) -> jax.Array:
    """{Tr(Z1 Sigma), Tr(Z2 Sigma)} = Tr([Z1, Z2] Sigma): left translations realise gl(n)."""
    return jnp.trace((z1 @ z2 - z2 @ z1) @ sigma, axis1=-2, axis2=-1)


def comoving_sigma_linear_bracket(z1: jax.Array, z2: jax.Array,
                                  sigma_hat: jax.Array) -> jax.Array:
    """{Tr(Z1 Sh), Tr(Z2 Sh)} = -Tr([Z1, Z2] Sh): right translations, an anti-homomorphism."""
    return -jnp.trace((z1 @ z2 - z2 @ z1) @ sigma_hat, axis1=-2, axis2=-1)


def sigma_config_bracket(phi: jax.Array, dF_dphi: jax.Array) -> jax.Array:
    """{Sigma^i_j, F(phi)} = -(phi D^T)^i_j, D = dF/dphi: generator of phi -> exp(Z) phi."""
    return -phi @ transpose(dF_dphi)


def comoving_sigma_config_bracket(phi: jax.Array, dF_dphi: jax.Array) -> jax.Array:
    """{Sigma_hat^A_B, F(phi)} = -(D^T phi)^A_B, D = dF/dphi: generator of phi -> phi exp(Z)."""
    return -transpose(dF_dphi) @ phi


def momentum_config_bracket(df_dx: jax.Array) -> jax.Array:
    """{p_a, f(x)} = -df/dx^a: the linear momentum generates translations."""
    return -df_dx


def affine_momentum_config_bracket(x: jax.Array, df_dx: jax.Array) -> jax.Array:
    """{Lambda^a_b, f(x)} = -x^a df/dx^b for the orbital affine momentum Lambda = x p^T (108)."""
    return -x[..., :, None] * df_dx[..., None, :]


__all__ = [
    "canonical_bracket", "sigma_bracket", "comoving_sigma_bracket", "sigma_linear_bracket",
    "comoving_sigma_linear_bracket", "sigma_config_bracket", "comoving_sigma_config_bracket",
    "momentum_config_bracket", "affine_momentum_config_bracket"
]
