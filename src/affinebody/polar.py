"""Polar and two-polar decompositions, and the measures of the quantized theory.

Paper, last section: phi = U A = B U = L D R^T with U, L, R orthogonal, A, B = U A U^T
symmetric positive definite and D = diag(Q), Q_a = exp(q_a). Then G = A^2 = R D^2 R^T and
C = B^-2 = L D^-2 L^T (11).

Sign convention (also for GL^-): L, R are in SO(n), q_1 >= ... >= q_n, and

    phi = L diag(exp q) diag(1, ..., 1, s) R^T,      s = sign(det phi),

i.e. the signed singular values are Q = (exp q_1, ..., exp q_{n-1}, s exp q_n). For the
d'Alembert models on all of L(n, R) the last Q passes through 0 when det phi changes sign
(docs/theory/two-polar.md: Q_1 > ... > |Q_n|).

Measures (docs/theory/paper-typos.md: the printed i != j products run over pairs i < j):
- Haar on GL(n): |det phi|^-n dphi (91); on R^n x GL(n): |det phi|^(-n-1) dx dphi (89);
- in two-polar coordinates: |det phi|^-n dphi = 2^(n(n-1)/2) prod_{a<b} |sinh(q_a - q_b)|
  dq dmu(L) dmu(R), and dphi = prod_{a<b} |Q_a^2 - Q_b^2| dQ dmu(L) dmu(R).

Degenerate singular values (e.g. phi = Id) give finite values everywhere; the polar factors
have a custom derivative (a Sylvester equation with denominators s_i + s_j > 0) so that
their gradients are finite there too.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody._checks import as_matrix, as_vector, check_invertible, transpose


class TwoPolar(NamedTuple):
    """phi = L diag(exp q) diag(1, ..., 1, sign) R^T with L, R in SO(n), q descending."""

    L: jax.Array
    q: jax.Array
    R: jax.Array
    sign: jax.Array


def _last_entry(value: jax.Array, n: int) -> jax.Array:
    """Vector (1, ..., 1, value) of length n, batched over value's shape."""
    return jnp.ones(value.shape + (n,), value.dtype).at[..., -1].set(value)


def _svd_rotations(phi: jax.Array):
    """SVD phi = L diag(s) diag(1..1, sign) R^T with L, R turned into rotations."""
    n = phi.shape[-1]
    u, s, vt = jnp.linalg.svd(phi)
    v = transpose(vt)
    det_u = jnp.sign(linalg.det(u))
    det_v = jnp.sign(linalg.det(v))
    rot_l = u * _last_entry(det_u, n)[..., None, :]
    rot_r = v * _last_entry(det_v, n)[..., None, :]
    return rot_l, s, rot_r, det_u * det_v


def two_polar(phi) -> TwoPolar:
    """Two-polar decomposition phi = L diag(exp q) diag(1, ..., sign) R^T (paper, last section).

    Requires invertible phi (q = log of the singular values). L and R are not unique where
    singular values coincide; q always is.
    """
    phi = as_matrix(phi, "phi")
    check_invertible(phi)
    rot_l, s, rot_r, sign = _svd_rotations(phi)
    return TwoPolar(rot_l, jnp.log(s), rot_r, sign)


def from_two_polar(L, q, R, sign=1.0) -> jax.Array:
    """Inverse of :func:`two_polar`: L diag(exp q) diag(1, ..., sign) R^T."""
    L = as_matrix(L, "L")
    R = as_matrix(R, "R")
    q = as_vector(q, "q", L.shape[-1])
    Q = jnp.exp(q) * _last_entry(jnp.asarray(sign, q.dtype) * jnp.ones(q.shape[:-1]), q.shape[-1])
    return (L * Q[..., None, :]) @ transpose(R)


def signed_singular_values(phi) -> jax.Array:
    """Q = (s_1, ..., s_{n-1}, sign(det phi) s_n), s descending; defined for singular phi too."""
    phi = as_matrix(phi, "phi")
    s = jnp.linalg.svd(phi, compute_uv=False)
    sign = jnp.sign(linalg.det(phi))
    sign = jnp.where(sign == 0, 1.0, sign)
    return s * _last_entry(sign, phi.shape[-1])


@jax.custom_jvp
def _polar(phi):
    u, s, vt = jnp.linalg.svd(phi)
    v = transpose(vt)
    return u @ vt, (v * s[..., None, :]) @ vt


@_polar.defjvp
def _polar_jvp(primals, tangents):
    (phi,), (dphi,) = primals, tangents
    u, a = _polar(phi)
    s, w = jnp.linalg.eigh(a)
    k = transpose(u) @ dphi
    rhs = transpose(w) @ (k - transpose(k)) @ w
    denom = s[..., :, None] + s[..., None, :]
    off_diagonal = ~jnp.eye(phi.shape[-1], dtype=bool)
    safe = jnp.where(off_diagonal, denom, 1.0)
    omega = w @ jnp.where(off_diagonal, rhs / safe, 0.0) @ transpose(w)
    return (u, a), (u @ omega, k - omega @ a)


def polar(phi) -> tuple[jax.Array, jax.Array]:
    """Right polar decomposition phi = U A: U orthogonal (det U = sign det phi), A = sqrt(G) SPD.

    G = A^2 (paper, last section). Differentiable also where singular values coincide.
    """
    return _polar(as_matrix(phi, "phi"))


def left_polar(phi) -> tuple[jax.Array, jax.Array]:
    """Left polar decomposition phi = B U with B = U A U^T = sqrt(phi phi^T); returns (B, U)."""
    u, a = polar(phi)
    return u @ a @ transpose(u), u


def haar_density(phi) -> jax.Array:
    """Density of the Haar measure on GL(n) w.r.t. Lebesgue measure: |det phi|^-n, eq. (91)."""
    phi = as_matrix(phi, "phi")
    return jnp.abs(linalg.det(phi)) ** (-phi.shape[-1])


def haar_density_with_translations(phi) -> jax.Array:
    """Density |det phi|^(-n-1) of the measure alpha on R^n x GL(n), eq. (89).

    Invariant under the spatial affine action (x, phi) -> (A x + b, A phi) but not under
    phi -> phi B (the affine group is not unimodular; docs/theory/paper-typos.md).
    """
    phi = as_matrix(phi, "phi")
    return jnp.abs(linalg.det(phi)) ** (-phi.shape[-1] - 1)


def _pairwise(values: jax.Array):
    n = values.shape[-1]
    a, b = jnp.triu_indices(n, k=1)
    return values[..., a], values[..., b]


def two_polar_haar_density(q) -> jax.Array:
    """prod_{a<b} |sinh(q_a - q_b)|: Haar measure in two-polar coordinates (up to 2^(n(n-1)/2))."""
    q = as_vector(q, "q")
    qa, qb = _pairwise(q)
    return jnp.prod(jnp.abs(jnp.sinh(qa - qb)), axis=-1)


def two_polar_lebesgue_density(Q) -> jax.Array:
    """prod_{a<b} |Q_a^2 - Q_b^2|: Lebesgue measure dphi in two-polar coordinates."""
    Q = as_vector(Q, "Q")
    qa, qb = _pairwise(Q)
    return jnp.prod(jnp.abs(qa**2 - qb**2), axis=-1)


__all__ = [
    "TwoPolar", "two_polar", "from_two_polar", "signed_singular_values", "polar", "left_polar",
    "haar_density", "haar_density_with_translations", "two_polar_haar_density",
    "two_polar_lebesgue_density"
]
