"""Configuration groups of an affinely-rigid body (paper §1) and their Lie algebras.

The internal configuration phi lives in one of (paper §1, text around eqs. (2)-(4)):

=========  ==========================================  ============================
group      definition                                   Lie algebra
=========  ==========================================  ============================
``L``      all n x n matrices L(n, R) (not a group)     gl(n)
``GL``     det phi != 0                                 gl(n)
``GL+``    det phi > 0                                  gl(n)
``SL``     det phi = 1 (incompressible body)            sl(n): Tr X = 0
``UL``     |det phi| = 1 (unimodular)                   sl(n)
``SO``     phi^T phi = Id, det phi = 1 (rigid body)     so(n): X^T = -X
``O``      phi^T phi = Id                               so(n)
``R+SO``   phi = s U, s > 0, U in SO(n)                 R Id + so(n)
``R+O``    phi = s U, s > 0, U in O(n)                  R Id + so(n)
=========  ==========================================  ============================

All functions are batched over leading axes ``[..., n, n]`` and JAX-traceable.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax

from affinebody import _linalg as linalg
from affinebody._checks import (
    as_matrix,
    eye_like,
    is_concrete,
    is_invertible,
    skew,
    trace,
    transpose,
)

GROUPS = ("GL", "GL+", "SL", "UL", "SO", "O", "R+SO", "R+O")
#: Groups plus the linear space L(n, R) that d'Alembert motion may use (paper §1).
CONFIGURATION_SPACES = ("L",) + GROUPS

_ALGEBRA = {
    "L": "gl",
    "GL": "gl",
    "GL+": "gl",
    "SL": "sl",
    "UL": "sl",
    "SO": "so",
    "O": "so",
    "R+SO": "R+so",
    "R+O": "R+so",
}


def _check_group(group: str) -> str:
    if group not in _ALGEBRA:
        raise ValueError(
            f"unknown configuration group {group!r} "
            f"(choose one of {', '.join(CONFIGURATION_SPACES)})"
        )
    return group


def lie_algebra(group: str) -> str:
    """Name of the Lie algebra of ``group``: 'gl', 'sl', 'so' or 'R+so'."""
    return _ALGEBRA[_check_group(group)]


def is_member(phi, group: str, tol: float = 1e-10) -> jax.Array:
    """Boolean [...]: whether each phi lies in ``group`` to relative tolerance ``tol``.

    Metric conditions are tested on the Green tensor G = phi^T phi (11): ``|G - Id| <= tol``
    for SO/O and ``|G - s^2 Id| <= tol s^2`` with s^2 = Tr G / n for R+SO/R+O; determinant
    conditions as ``|det phi - 1| <= tol`` (SL) or ``||det phi| - 1| <= tol`` (UL). GL and GL+
    test membership, not conditioning: phi is invertible when its reciprocal condition number
    exceeds what float64 resolves (``_checks.is_invertible``, ``_checks.SINGULAR_RTOL``,
    whatever ``tol``), and in GL+ when det phi > 0 besides; a strongly sheared phi with det 1 is
    in GL+ up to condition numbers of order 1e13.
    """
    _check_group(group)
    phi = as_matrix(phi, "phi")
    n = phi.shape[-1]
    det = linalg.det(phi)
    invertible = is_invertible(phi)
    if group == "L":
        return jnp.all(jnp.isfinite(phi), axis=(-2, -1))
    if group == "GL":
        return invertible
    if group == "GL+":
        return invertible & (det > 0)
    if group == "SL":
        return jnp.abs(det - 1.0) <= tol
    if group == "UL":
        return jnp.abs(jnp.abs(det) - 1.0) <= tol
    g = transpose(phi) @ phi
    if group in ("SO", "O"):
        metric_ok = jnp.max(jnp.abs(g - eye_like(g)), axis=(-2, -1)) <= tol
    else:
        s2 = trace(g) / n
        metric_ok = (jnp.max(jnp.abs(g - s2[..., None, None] * eye_like(g)), axis=(-2, -1))
                     <= tol * s2) & (s2 > 0)
    if group in ("SO", "R+SO"):
        return metric_ok & (det > 0)
    return metric_ok


#: :func:`is_member` compiled as one program (``group`` and ``tol`` static): what eager checks
#: of whole states call (``HamiltonianSystem.check``). Op by op, each of its few dozen array
#: operations is compiled and dispatched on its own: 1.6 s against 0.7 s in a new process at
#: 4096 bodies.
is_member_jit = jax.jit(is_member, static_argnames=("group", "tol"))


def project(phi, group: str) -> jax.Array:
    """Project phi onto ``group``.

    - SO / O: the nearest element in the Frobenius norm, from the polar decomposition
      (Kabsch: L R^T of the two-polar decomposition for SO, the polar factor U for O);
    - R+SO / R+O: the nearest scaled rotation s U, s = Tr(U^T phi) / n;
    - SL / UL: determinant normalisation phi |det phi|^(-1/n) (for SL with det phi < 0 and n
      odd the sign is flipped as well; for n even no scalar multiple of such phi is in SL);
    - GL, GL+, L: open sets, phi itself.

    Where no element of the group is reachable this way (GL+ with det phi <= 0, SL with
    det phi < 0 and n even, R+SO/R+O with Tr(U^T phi) <= 0, GL with singular phi) a concrete
    input raises ValueError; traced inputs are not checked.
    """
    from affinebody.polar import two_polar

    _check_group(group)
    phi = as_matrix(phi, "phi")
    n = phi.shape[-1]
    det = linalg.det(phi)
    if group in ("GL", "SL", "UL"):
        singular = ~is_invertible(phi)
        _refuse_if(singular, f"phi is singular: it has no projection onto {group}(n)")
    if group == "GL+" or (group == "SL" and n % 2 == 0):
        _refuse_if(det <= 0, f"det phi <= 0: phi has no projection onto {group}(n) "
                             f"(the sign of det phi cannot change continuously)")
    if group in ("L", "GL", "GL+"):
        return phi
    if group in ("SL", "UL"):
        scaled = phi * (jnp.abs(det) ** (-1.0 / n))[..., None, None]
        if group == "SL" and n % 2 == 1:
            scaled = scaled * jnp.sign(det)[..., None, None]
        return scaled
    tp = two_polar(phi)
    rotation = tp.L @ transpose(tp.R)  # Kabsch: nearest element of SO(n)
    signs = jnp.ones(tp.q.shape).at[..., -1].set(tp.sign)
    orthogonal = (tp.L * signs[..., None, :]) @ transpose(tp.R)  # polar factor, in O(n)
    u = rotation if group in ("SO", "R+SO") else orthogonal
    if group in ("SO", "O"):
        return u
    scale = trace(transpose(u) @ phi) / n
    _refuse_if(scale <= 0, f"phi has no nearest element of {group}(n): Tr(U^T phi) <= 0 for its "
                           f"nearest rotation U")
    return scale[..., None, None] * u


def _refuse_if(condition: jax.Array, message: str) -> None:
    if is_concrete(condition) and bool(jnp.any(condition)):
        raise ValueError(message)


def project_algebra(x, group: str) -> jax.Array:
    """Orthogonal (Frobenius) projection of a matrix onto the Lie algebra of ``group``.

    gl: X; sl: X - (Tr X / n) Id; so: (X - X^T)/2; R+so: (X - X^T)/2 + (Tr X / n) Id.
    """
    algebra = lie_algebra(group)
    x = as_matrix(x, "X")
    n = x.shape[-1]
    if algebra == "gl":
        return x
    mean_trace = (trace(x) / n)[..., None, None] * eye_like(x)
    if algebra == "sl":
        return x - mean_trace
    if algebra == "so":
        return skew(x)
    return skew(x) + mean_trace


def expm(x) -> jax.Array:
    """Matrix exponential (one-parameter subgroups t -> expm(t X)), batched; Pade [13/13] with
    scaling and squaring and no LAPACK call for n <= 3 (:func:`affinebody._linalg.expm`)."""
    x = as_matrix(x, "X")
    return linalg.expm(x)


def _sqrtm_denman_beavers(a: jax.Array, iterations: int) -> jax.Array:
    """Principal square root by the Denman-Beavers iteration (quadratic convergence)."""

    def body(_, yz):
        y, z = yz
        return 0.5 * (y + linalg.inv(z)), 0.5 * (z + linalg.inv(y))

    y, _ = lax.fori_loop(0, iterations, body, (a, jnp.broadcast_to(eye_like(a), a.shape)))
    return y


def logm(phi, max_square_roots: int = 40) -> jax.Array:
    """Principal matrix logarithm of phi (no eigenvalues on the closed negative real axis).

    Inverse scaling and squaring: take k square roots until ``|A - Id| < 1/4`` (k <= 40, chosen
    at run time for the whole batch), then ``log A = 2 atanh(Z) = 2 sum Z^(2j+1)/(2j+1)`` with
    ``Z = (A - Id)(A + Id)^-1``, and multiply by 2^k. For analysis and tests: the run-time
    loop is not reverse-mode differentiable.
    """
    return _logm(as_matrix(phi, "phi"), max_square_roots)


@partial(jax.jit, static_argnums=1)
def _logm(a: jax.Array, max_square_roots: int) -> jax.Array:
    ident = eye_like(a)

    def far(state):
        m, k = state
        return (jnp.max(jnp.sum(jnp.abs(m - ident), axis=-2)) >= 0.25) & (k < max_square_roots)

    def root(state):
        m, k = state
        return _sqrtm_denman_beavers(m, 12), k + 1

    a, k = lax.while_loop(far, root, (a, 0))
    z = (a - ident) @ linalg.inv(a + ident)
    z2 = z @ z
    term, series = z, z
    for j in range(1, 14):
        term = term @ z2
        series = series + term / (2 * j + 1)
    return (2.0 * 2.0**k) * series


__all__ = [
    "GROUPS", "CONFIGURATION_SPACES", "lie_algebra", "is_member", "project", "project_algebra",
    "expm", "logm"
]
