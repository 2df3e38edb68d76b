"""Deformation tensors and deformation invariants of one affine body (eqs. (11)-(19), (32)).

Green G = phi^T phi and Cauchy C = phi^-T phi^-1 (11), their contravariant inverses (12),
Lagrange and Euler strains (32), and three equivalent sets of deformation invariants
(functions on O(n) \\ GL(n) / O(n), eq. (16)):

- K_a = Tr(G^a), a = 1..n (17);
- the eigenvalues lambda_1 >= ... >= lambda_n of G (18) (squared singular values of phi);
- the coefficients I_p of det(G - lambda Id) = sum_k (-1)^k I_{n-k} lambda^k (19), i.e. the
  elementary symmetric polynomials of the lambdas: I_1 = Tr G, ..., I_n = det G, I_0 = 1.

Conversions between the sets use Newton's identities (general n) and, for eigenvalues from
power sums or coefficients, the closed-form roots for n <= 3 (traceable) with a NumPy
fallback for n > 3.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg as linalg
from affinebody._checks import as_matrix, as_vector, check_invertible, eye_like, trace, transpose


def green_tensor(phi) -> jax.Array:
    """G[phi] = phi^T phi, eq. (11)."""
    phi = as_matrix(phi)
    return transpose(phi) @ phi


def cauchy_tensor(phi) -> jax.Array:
    """C[phi] = phi^-T phi^-1, eq. (11)."""
    phi = as_matrix(phi)
    check_invertible(phi)
    inv = linalg.inv(phi)
    return transpose(inv) @ inv


def inverse_green_tensor(phi) -> jax.Array:
    """Contravariant inverse G~[phi] = phi^-1 phi^-T = G^-1, eq. (12)."""
    phi = as_matrix(phi)
    check_invertible(phi)
    inv = linalg.inv(phi)
    return inv @ transpose(inv)


def inverse_cauchy_tensor(phi) -> jax.Array:
    """Contravariant inverse C~[phi] = phi phi^T = C^-1, eq. (12)."""
    phi = as_matrix(phi)
    return phi @ transpose(phi)


def lagrange_strain(phi) -> jax.Array:
    """Lagrange strain E[phi] = (G[phi] - Id)/2, eq. (32)."""
    g = green_tensor(phi)
    return 0.5 * (g - eye_like(g))


def euler_strain(phi) -> jax.Array:
    """Euler strain e[phi] = (Id - C[phi])/2, eq. (32)."""
    c = cauchy_tensor(phi)
    return 0.5 * (eye_like(c) - c)


def matrix_power_traces(m: jax.Array, count: int) -> jax.Array:
    """[..., count]: Tr(m^a) for a = 1..count (the K-type invariants of (17), (28), (30))."""
    powers = [m]
    for _ in range(count - 1):
        powers.append(powers[-1] @ m)
    return jnp.stack([trace(p) for p in powers], axis=-1)


def trace_invariants(phi) -> jax.Array:
    """K_a[phi] = Tr(G^a) = Tr(C^-a), a = 1..n, eq. (17); shape [..., n]."""
    g = green_tensor(phi)
    return matrix_power_traces(g, g.shape[-1])


def green_eigenvalues(phi) -> jax.Array:
    """Eigenvalues lambda_1 >= ... >= lambda_n of G[phi], eq. (18): squared singular values."""
    phi = as_matrix(phi)
    return jnp.linalg.svd(phi, compute_uv=False) ** 2


def characteristic_invariants(phi) -> jax.Array:
    """I_1, ..., I_n of eq. (19) (I_0 = 1): elementary symmetric polynomials of G's eigenvalues.

    I_1 = Tr G and I_n = det G. Computed from the squared singular values of phi: going through
    the power traces K_a (Newton's identities) cancels catastrophically for strong deformations
    (phi = diag(1e3, 1, 1e-3) would give I_3 = 0 instead of 1).
    """
    return characteristic_from_eigenvalues(green_eigenvalues(phi))


def traces_from_eigenvalues(lam) -> jax.Array:
    """K_a = sum_i lambda_i^a, a = 1..n."""
    lam = as_vector(lam, "lambda")
    n = lam.shape[-1]
    return jnp.stack([jnp.sum(lam**a, axis=-1) for a in range(1, n + 1)], axis=-1)


def characteristic_from_eigenvalues(lam) -> jax.Array:
    """I_p = e_p(lambda), p = 1..n (elementary symmetric polynomials)."""
    lam = as_vector(lam, "lambda")
    n = lam.shape[-1]
    e = [jnp.ones(lam.shape[:-1])] + [jnp.zeros(lam.shape[:-1])] * n
    for i in range(n):
        for p in range(i + 1, 0, -1):
            e[p] = e[p] + lam[..., i] * e[p - 1]
    return jnp.stack(e[1:], axis=-1)


def characteristic_from_traces(K) -> jax.Array:
    """Newton's identities: p I_p = sum_{i=1}^p (-1)^(i-1) I_{p-i} K_i, p = 1..n."""
    K = as_vector(K, "K")
    n = K.shape[-1]
    e = [jnp.ones(K.shape[:-1])]
    for p in range(1, n + 1):
        acc = sum((-1) ** (i - 1) * e[p - i] * K[..., i - 1] for i in range(1, p + 1))
        e.append(acc / p)
    return jnp.stack(e[1:], axis=-1)


def traces_from_characteristic(I) -> jax.Array:
    """Newton's identities: K_p = sum_{i=1}^{p-1} (-1)^(i-1) I_i K_{p-i} + (-1)^(p-1) p I_p."""
    I = as_vector(I, "I")
    n = I.shape[-1]
    k: list[jax.Array] = []
    for p in range(1, n + 1):
        acc = (-1) ** (p - 1) * p * I[..., p - 1]
        for i in range(1, p):
            acc = acc + (-1) ** (i - 1) * I[..., i - 1] * k[p - i - 1]
        k.append(acc)
    return jnp.stack(k, axis=-1)


def _safe_sqrt(x: jax.Array) -> jax.Array:
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def eigenvalues_from_characteristic(I) -> jax.Array:
    """Roots lambda_1 >= ... >= lambda_n of lambda^n - I_1 lambda^(n-1) + ... + (-1)^n I_n.

    Assumes real roots (true for Green tensors). Closed forms for n <= 3 (the trigonometric
    solution of the cubic); NumPy's polynomial roots for n > 3 (not traceable).
    """
    I = as_vector(I, "I")
    n = I.shape[-1]
    if n == 1:
        return I
    if n == 2:
        half = 0.5 * I[..., 0]
        disc = _safe_sqrt(half**2 - I[..., 1])
        return jnp.stack([half + disc, half - disc], axis=-1)
    if n == 3:
        a, b, c = I[..., 0], I[..., 1], I[..., 2]
        p = b - a**2 / 3.0  # depressed cubic t^3 + p t + q, lambda = t + a/3
        q = -2.0 * a**3 / 27.0 + a * b / 3.0 - c
        m = _safe_sqrt(-p / 3.0)
        safe_m = jnp.where(m > 0, m, 1.0)
        # cos(3 theta) = (3 q / 2 p) sqrt(-3 / p) = -q / (2 m^3), with p = -3 m^2
        arg = jnp.clip(jnp.where(m > 0, -q / (2.0 * safe_m**3), 0.0), -1.0, 1.0)
        theta = jnp.arccos(arg) / 3.0
        roots = [2.0 * m * jnp.cos(theta - 2.0 * jnp.pi * k / 3.0) + a / 3.0 for k in range(3)]
        return -jnp.sort(-jnp.stack(roots, axis=-1), axis=-1)
    coeffs = np.concatenate(
        [np.ones(I.shape[:-1] + (1,)), np.asarray(I) * (-1.0) ** np.arange(1, n + 1)], axis=-1
    )
    flat = coeffs.reshape(-1, n + 1)
    roots = np.stack([np.sort(np.real(np.roots(c)))[::-1] for c in flat])
    return jnp.asarray(roots.reshape(I.shape))


def eigenvalues_from_traces(K) -> jax.Array:
    """Eigenvalues of G from K_a = Tr(G^a), via the characteristic coefficients."""
    return eigenvalues_from_characteristic(characteristic_from_traces(K))


__all__ = [
    "green_tensor", "cauchy_tensor", "inverse_green_tensor", "inverse_cauchy_tensor",
    "lagrange_strain", "euler_strain", "matrix_power_traces", "trace_invariants",
    "green_eigenvalues", "characteristic_invariants", "traces_from_eigenvalues",
    "characteristic_from_eigenvalues", "characteristic_from_traces", "traces_from_characteristic",
    "eigenvalues_from_characteristic", "eigenvalues_from_traces"
]
