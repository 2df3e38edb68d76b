"""Polar and two-polar decompositions and the measures of the quantized theory.

Paper, last section: phi = U A = B U = L D R^T, G = A^2 = R D^2 R^T, C = B^-2 = L D^-2 L^T;
Haar measure |det phi|^-n dphi (91) and its two-polar form (with the products over a < b,
docs/theory/paper-typos.md), checked through autodiff Jacobians of the parametrisations.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import polar
from strategies import (
    SAMPLED_GROUPS,
    assert_close,
    degenerate_matrices,
    dims,
    matrices,
    orthogonal,
    vectors,
)

FAST = settings(max_examples=12, deadline=None)
SLOW = settings(max_examples=6, deadline=None)

_T = lambda a: np.swapaxes(np.asarray(a), -1, -2)


def _is_rotation(m, tol=1e-10):
    m = np.asarray(m)
    n = m.shape[-1]
    assert_close(_T(m) @ m, np.broadcast_to(np.eye(n), m.shape), tol)
    assert_close(np.linalg.det(m), 1.0, tol)


def _is_spd(a, tol=1e-10):
    a = np.asarray(a)
    assert_close(a, _T(a), tol)
    assert np.all(np.linalg.eigvalsh(a) > 0)


def _sqrtm_spd(g):
    lam, w = np.linalg.eigh(g)
    return (w * np.sqrt(lam)[..., None, :]) @ _T(w)


def _check_polar(phi):
    n = phi.shape[-1]
    u, a = (np.asarray(m) for m in polar.polar(phi))
    b, u_left = (np.asarray(m) for m in polar.left_polar(phi))
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(a))
    assert_close(_T(u) @ u, np.broadcast_to(np.eye(n), u.shape), 1e-10)
    assert_close(np.linalg.det(u), np.sign(np.linalg.det(phi)), 1e-10)
    _is_spd(a)
    _is_spd(b)
    assert_close(u @ a, phi, 1e-10)
    assert_close(b @ u, phi, 1e-10)
    assert_close(u_left, u, 1e-10)
    assert_close(b, u @ a @ _T(u), 1e-10)
    g = _T(phi) @ phi
    assert_close(a @ a, g, 1e-10)  # G = A^2
    assert_close(a, _sqrtm_spd(g), 1e-9)  # A is *the* SPD square root of G (independent eigh)
    c = np.linalg.inv(phi @ _T(phi))
    assert_close(np.linalg.inv(b @ b), c, 1e-9)  # C = B^-2


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_polar_decomposition(group, data):
    _check_polar(data.draw(matrices(group)))


@FAST
@given(degenerate_matrices())
def test_polar_decomposition_at_coincident_singular_values(phi):
    _check_polar(phi)


def _check_two_polar(phi):
    tp = polar.two_polar(phi)
    L, q, R, sign = (np.asarray(t) for t in tp)
    for t in (L, q, R, sign):
        assert np.all(np.isfinite(t))
    _is_rotation(L)
    _is_rotation(R)
    assert np.all(np.diff(q, axis=-1) <= 0)  # q descending
    assert_close(sign, np.sign(np.linalg.det(phi)), 0.0)
    assert_close(np.exp(q), np.linalg.svd(phi, compute_uv=False), 1e-10)
    assert_close(polar.from_two_polar(L, q, R, sign), phi, 1e-10)  # round trip
    d2 = np.exp(2 * q)
    assert_close((R * d2[..., None, :]) @ _T(R), _T(phi) @ phi, 1e-10)  # G = R D^2 R^T
    c = np.linalg.inv(phi @ _T(phi))
    assert_close((L / d2[..., None, :]) @ _T(L), c, 1e-9)  # C = L D^-2 L^T
    Q = np.asarray(polar.signed_singular_values(phi))
    assert_close(np.abs(Q), np.exp(q), 1e-10)
    assert_close(np.prod(Q, axis=-1), np.linalg.det(phi), 1e-10)
    assert np.all(Q[..., :-1] > 0)
    # from_two_polar(L, q, R, sign) == L diag(Q) R^T
    assert_close((L * Q[..., None, :]) @ _T(R), phi, 1e-10)
    return tp


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_two_polar_round_trip(group, data):
    _check_two_polar(data.draw(matrices(group)))


@FAST
@given(degenerate_matrices())
def test_two_polar_round_trip_at_coincident_singular_values(phi):
    _check_two_polar(phi)


def test_two_polar_of_scaled_rotations_and_repeated_diagonals():
    rng = np.random.default_rng(0)
    for n in (1, 2, 3):
        for phi in (
            2.5 * orthogonal(rng, n, (2,), 1.0),
            0.4 * orthogonal(rng, n, (2,), -1.0),
            np.broadcast_to(np.diag([3.0, 3.0, 0.5][:n]), (2, n, n)),
            np.broadcast_to(np.diag([2.0, 0.5, 0.5][:n]), (2, n, n)),
            np.broadcast_to(np.eye(n), (2, n, n)),
        ):
            _check_two_polar(phi)
            _check_polar(phi)


def test_two_polar_refuses_singular_phi():
    """q = log of the singular values needs invertible phi (docstring of two_polar): a
    singular phi must raise a ValueError naming it, not return q = -36 or -inf."""
    with pytest.raises(ValueError, match="phi is singular"):
        polar.two_polar(np.array([[1.0, 2.0], [2.0, 4.0]]))
    with pytest.raises(ValueError, match="phi is singular"):
        polar.two_polar(np.zeros((3, 3)))


def test_signed_singular_values_of_singular_matrices():
    phi = np.array([[1.0, 2.0], [2.0, 4.0]])
    Q = np.asarray(polar.signed_singular_values(phi))
    assert np.all(np.isfinite(Q))
    assert_close(Q, [5.0, 0.0], 1e-12)


# ------------------------------------------------------------------------- derivatives

_polar_jvp = jax.jit(lambda phi, dphi: jax.jvp(polar.polar, (phi,), (dphi,)))
_polar = jax.jit(polar.polar)


def _polar_objective(phi):
    u, a = polar.polar(phi)
    n = phi.shape[-1]
    weights = jnp.arange(1.0, n * n + 1).reshape(n, n)
    return jnp.sum(weights * u) + jnp.sum(jnp.sin(a) * weights.T)


_grad_polar_objective = jax.jit(jax.grad(_polar_objective))
_grad_q = jax.jit(
    jax.grad(lambda phi: jnp.sum(polar.two_polar(phi).q * jnp.arange(1.0, 4.0)[: phi.shape[-1]]))
)
_grad_log_det = jax.jit(jax.grad(lambda phi: jnp.sum(polar.two_polar(phi).q)))


def _central_difference(phi, dphi, h=1e-6):
    plus, minus = _polar(phi + h * dphi), _polar(phi - h * dphi)
    return [(p - m) / (2 * h) for p, m in zip(plus, minus, strict=True)]


@FAST
@given(st.data())
def test_polar_derivative_matches_central_differences(data):
    n = data.draw(dims)
    phi = data.draw(st.one_of(matrices("GL", n, batch=()), degenerate_matrices(n, batch=())))
    dphi = data.draw(vectors(n * n, batch=(), bound=1.0)).reshape(n, n)
    (u, a), (du, da) = _polar_jvp(phi, dphi)
    fd_u, fd_a = _central_difference(phi, dphi)
    # Polar factors are analytic on GL(n) (A = sqrt(phi^T phi)), also where singular values
    # coincide; O(h^2) truncation + O(eps/h) rounding ~ 1e-9 here.
    assert_close(du, fd_u, 1e-6)
    assert_close(da, fd_a, 1e-6)
    # Tangent consistency: dphi = dU A + U dA, U^T dU skew, dA symmetric.
    assert_close(du @ a + u @ da, dphi, 1e-9)
    assert_close(_T(u) @ du, -_T(_T(u) @ du), 1e-9)
    assert_close(da, _T(da), 1e-9)


@FAST
@given(degenerate_matrices(batch=()))
def test_gradients_are_finite_at_coincident_singular_values(phi):
    assert np.all(np.isfinite(_grad_polar_objective(phi)))
    assert np.all(np.isfinite(_grad_q(phi)))
    # sum_a q_a = ln|det phi| has gradient phi^-T everywhere, degenerate or not.
    assert_close(_grad_log_det(phi), np.linalg.inv(phi).T, 1e-9)


# --------------------------------------------------------------------------------- Haar

_two_sided_jacobian = jax.jit(jax.jacfwd(lambda phi, a, b: a @ phi @ b))


def _flat_jacobian_det(phi, a, b):
    """|det d(A phi B)/dphi| from the autodiff Jacobian as an n^2 x n^2 matrix."""
    n = phi.shape[-1]
    jac = np.asarray(_two_sided_jacobian(phi, a, b)).reshape(n * n, n * n)
    return abs(float(np.linalg.det(jac)))


def _spatial_affine_map(z, a, shift):
    n = a.shape[-1]
    return jnp.concatenate([a @ z[:n] + shift, (a @ z[n:].reshape(n, n)).ravel()])


_spatial_affine_jacobian = jax.jit(jax.jacfwd(_spatial_affine_map))


@SLOW
@given(st.data())
def test_haar_density_is_left_and_right_invariant(data):
    n = data.draw(dims)
    phi, a, b = (data.draw(matrices(g, n, batch=())) for g in ("GL", "GL", "GL"))
    jac = _flat_jacobian_det(phi, a, b)
    assert_close(jac, abs(np.linalg.det(a) * np.linalg.det(b)) ** n, 1e-9)  # |det A det B|^n
    moved = a @ phi @ b
    assert_close(polar.haar_density(moved) * jac, polar.haar_density(phi), 1e-9)
    assert_close(polar.haar_density(phi), abs(np.linalg.det(phi)) ** (-n), 1e-10)


@SLOW
@given(st.data())
def test_affine_haar_density_is_spatially_but_not_materially_invariant(data):
    """(89): |det phi|^-(n+1) dx dphi under (x, phi) -> (A x + b, A phi) and phi -> phi B."""
    n = data.draw(dims)
    phi, a, b = (data.draw(matrices(g, n, batch=())) for g in ("GL", "GL", "GL"))
    shift = data.draw(vectors(n, batch=()))
    x = data.draw(vectors(n, batch=()))
    z = np.concatenate([x, phi.ravel()])
    jac = abs(np.linalg.det(_spatial_affine_jacobian(z, a, shift)))
    density = polar.haar_density_with_translations
    assert_close(density(a @ phi) * jac, density(phi), 1e-9)
    material_jac = _flat_jacobian_det(phi, np.eye(n), b)
    # The affine group is not unimodular: the density changes by exactly |det B|^-1.
    assert_close(density(phi @ b) * material_jac / density(phi), 1 / abs(np.linalg.det(b)), 1e-9)


# ------------------------------------------------------------------ two-polar measures

def _so_basis(n):
    """E_ab = e_a e_b^T - e_b e_a^T, a < b: orthonormal for <X, Y> = Tr(X^T Y)/2."""
    basis = np.zeros((n * (n - 1) // 2, n, n))
    for k, (a, b) in enumerate(itertools.combinations(range(n), 2)):
        basis[k, a, b], basis[k, b, a] = 1.0, -1.0
    return jnp.asarray(basis)


def _cayley(x):
    ident = jnp.eye(x.shape[-1])
    return jnp.linalg.solve(ident - 0.5 * x, ident + 0.5 * x)


def _two_polar_chart(z, L0, R0, sign, log_coordinates):
    """(Q or q, alpha, beta) -> L0 cay(alpha.E) diag(Q) cay(-beta.E) R0^T, flattened.

    cay(X) = (Id - X/2)^-1 (Id + X/2) is a chart of SO(n) with the derivative of expm at 0
    (both are X to first order), so the Jacobian at alpha = beta = 0 is that of the expm chart
    and cheaper to compile.
    """
    n = L0.shape[-1]
    basis = _so_basis(n)
    m = basis.shape[0]
    d = jnp.exp(z[:n]) if log_coordinates else z[:n]
    d = d * jnp.ones(n).at[-1].set(sign)
    left, right = jnp.eye(n), jnp.eye(n)
    if m:
        left = _cayley(jnp.tensordot(z[n : n + m], basis, 1))
        right = _cayley(-jnp.tensordot(z[n + m :], basis, 1))
    return (L0 @ left @ (d[:, None] * right) @ R0.T).ravel()


@jax.jit
def _charts_and_jacobians(z_Q, z_q, L0, R0, sign):
    """Both charts at their base points and |det| of their autodiff Jacobians (n^2 x n^2)."""
    jac_Q = jax.jacfwd(_two_polar_chart)(z_Q, L0, R0, 1.0, False)
    jac_q = jax.jacfwd(_two_polar_chart)(z_q, L0, R0, sign, True)
    return (_two_polar_chart(z_Q, L0, R0, 1.0, False), jnp.abs(jnp.linalg.det(jac_Q)),
            _two_polar_chart(z_q, L0, R0, sign, True), jnp.abs(jnp.linalg.det(jac_q)))


@SLOW
@given(st.sampled_from(("GL+", "GL-")), st.data())
def test_two_polar_lebesgue_and_haar_densities_from_autodiff_jacobian(group, data):
    n = data.draw(dims)
    phi = data.draw(matrices(group, n, batch=()))
    L0, q, R0, sign = (np.asarray(t) for t in polar.two_polar(phi))
    Q = np.asarray(polar.signed_singular_values(phi))
    zeros = np.zeros(n * (n - 1))

    phi_Q, jac_Q, phi_q, jac_q = _charts_and_jacobians(
        np.concatenate([Q, zeros]), np.concatenate([q, zeros]), L0, R0, sign
    )
    assert_close(phi_Q, phi.ravel(), 1e-10)
    # dphi = prod_{a<b} |Q_a^2 - Q_b^2| dQ dmu(L) dmu(R), constant exactly 1 in this basis.
    assert_close(jac_Q, polar.two_polar_lebesgue_density(Q), 1e-9)
    expected_lebesgue = np.prod([abs(Q[a] ** 2 - Q[b] ** 2)
                                 for a, b in itertools.combinations(range(n), 2)])
    assert_close(polar.two_polar_lebesgue_density(Q), expected_lebesgue, 1e-10)

    assert_close(phi_q, phi.ravel(), 1e-10)
    # |det phi|^-n dphi = 2^(n(n-1)/2) prod_{a<b} |sinh(q_a - q_b)| dq dmu(L) dmu(R).
    haar_in_q = polar.haar_density(phi) * jac_q
    assert_close(haar_in_q, 2.0 ** (n * (n - 1) / 2) * polar.two_polar_haar_density(q), 1e-9)
    expected_haar = np.prod([abs(np.sinh(q[a] - q[b]))
                             for a, b in itertools.combinations(range(n), 2)])
    assert_close(polar.two_polar_haar_density(q), expected_haar, 1e-10)


def test_two_polar_densities_vanish_at_coincident_singular_values():
    assert_close(polar.two_polar_haar_density(np.array([0.3, 0.3, -1.0])), 0.0, 1e-15)
    assert_close(polar.two_polar_lebesgue_density(np.array([2.0, 1.0, -1.0])), 0.0, 1e-15)
    assert_close(polar.two_polar_haar_density(np.array([[0.5], [1.0]])), [1.0, 1.0], 0.0)
