"""Deformation tensors and invariants of one body: paper eqs. (11)-(19), (32)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import deformation as dfm
from strategies import SAMPLED_GROUPS, assert_close, dims, matrices, vectors

FAST = settings(max_examples=12, deadline=None)

_T = lambda a: np.swapaxes(np.asarray(a), -1, -2)
_inv = np.linalg.inv


def _eye(phi):
    return np.broadcast_to(np.eye(phi.shape[-1]), phi.shape)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_green_and_cauchy_tensors_and_their_inverses(group, data):
    """(11), (12): G = phi^T phi, C = phi^-T phi^-1, G~ = G^-1, C~ = C^-1, all SPD."""
    phi = data.draw(matrices(group))
    g, c = np.asarray(dfm.green_tensor(phi)), np.asarray(dfm.cauchy_tensor(phi))
    assert_close(g, _T(phi) @ phi, 1e-12)
    assert_close(c, _T(_inv(phi)) @ _inv(phi), 1e-10)
    assert_close(g, _T(g), 0.0)
    assert_close(c, _T(c), 1e-12)
    assert np.all(np.linalg.eigvalsh(g) > 0) and np.all(np.linalg.eigvalsh(c) > 0)
    assert_close(dfm.inverse_green_tensor(phi) @ g, _eye(phi), 1e-10)
    assert_close(dfm.inverse_cauchy_tensor(phi) @ c, _eye(phi), 1e-10)
    assert_close(dfm.inverse_cauchy_tensor(phi), phi @ _T(phi), 1e-12)


@FAST
@given(st.data())
def test_transformation_rules_14_15(data):
    n = data.draw(dims)
    phi = data.draw(matrices("GL", n))
    rot = data.draw(matrices("O", n))
    a = data.draw(matrices("GL", n))
    g, c = dfm.green_tensor(phi), dfm.cauchy_tensor(phi)
    # (14): A in O(n)
    assert_close(dfm.green_tensor(rot @ phi), g, 1e-10)
    assert_close(dfm.cauchy_tensor(phi @ rot), c, 1e-10)
    # (15): A in GL(n)
    assert_close(dfm.green_tensor(phi @ a), _T(a) @ g @ a, 1e-10)
    assert_close(dfm.cauchy_tensor(a @ phi), _T(_inv(a)) @ c @ _inv(a), 1e-9)


def _invariant_sets(phi):
    return (
        dfm.trace_invariants(phi),
        dfm.green_eigenvalues(phi),
        dfm.characteristic_invariants(phi),
    )


@FAST
@given(st.data())
def test_deformation_invariants_are_biorthogonally_invariant_16(data):
    n = data.draw(dims)
    phi = data.draw(matrices("GL", n))
    a, b = data.draw(matrices("O", n)), data.draw(matrices("O", n))
    for before, after in zip(_invariant_sets(phi), _invariant_sets(a @ phi @ b), strict=True):
        assert_close(after, before, 1e-9)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_invariants_17_18_19_against_numpy(group, data):
    phi = data.draw(matrices(group))
    n = phi.shape[-1]
    g = _T(phi) @ phi
    lam = np.linalg.eigvalsh(g)[..., ::-1]  # independent: symmetric eigensolver
    powers = np.stack([np.linalg.matrix_power(g, a) for a in range(1, n + 1)], axis=-3)
    K = np.trace(powers, axis1=-2, axis2=-1)
    assert_close(dfm.trace_invariants(phi), K, 1e-10)
    # (17): K_a = Tr(C^-a)
    c_inv = _inv(_T(_inv(phi)) @ _inv(phi))
    K_from_c = np.stack(
        [np.trace(np.linalg.matrix_power(c_inv, a), axis1=-2, axis2=-1) for a in range(1, n + 1)],
        axis=-1,
    )
    assert_close(K_from_c, K, 1e-8)
    assert_close(dfm.green_eigenvalues(phi), lam, 1e-10)  # (18), descending
    assert np.all(np.diff(np.asarray(dfm.green_eigenvalues(phi)), axis=-1) <= 0)
    I = np.asarray(dfm.characteristic_invariants(phi))
    coefficients = np.stack([np.poly(m) for m in g.reshape(-1, n, n)])
    coefficients = coefficients.reshape(g.shape[:-2] + (n + 1,))
    assert_close(I, coefficients[..., 1:] * (-1.0) ** np.arange(1, n + 1), 1e-9)
    assert_close(I[..., 0], np.trace(g, axis1=-2, axis2=-1), 1e-10)  # I_1 = Tr G
    assert_close(I[..., -1], np.linalg.det(g), 1e-9)  # I_n = det G
    # (19): det(G - lambda Id) = sum_k (-1)^k I_{n-k} lambda^k at a few lambda
    full = np.concatenate([np.ones(I.shape[:-1] + (1,)), I], axis=-1)  # I_0 .. I_n
    for x in (-1.3, 0.0, 0.7, 2.9):
        rhs = sum((-1) ** k * full[..., n - k] * x**k for k in range(n + 1))
        assert_close(np.linalg.det(g - x * np.eye(n)), rhs, 1e-9)


@FAST
@given(st.data())
def test_invariant_conversions_agree_both_ways(data):
    phi = data.draw(matrices("GL"))
    K, lam, I = (np.asarray(v) for v in _invariant_sets(phi))
    scale = float(np.max(lam))
    assert_close(dfm.traces_from_eigenvalues(lam), K, 1e-10)
    assert_close(dfm.characteristic_from_eigenvalues(lam), I, 1e-10)
    assert_close(dfm.characteristic_from_traces(K), I, 1e-9)
    assert_close(dfm.traces_from_characteristic(I), K, 1e-9)
    # Roots of a polynomial lose digits where roots (nearly) coincide: |dlambda| ~ eps^(1/k)
    # * scale for a k-fold root (sqrt(eps) ~ 1.5e-8 for a double one, eps^(1/3) ~ 6e-6 for
    # the triple one of n = 3); hypothesis does produce coincident singular values.
    tol = 3 * np.finfo(float).eps ** (1 / 3) * scale
    assert_close(dfm.eigenvalues_from_characteristic(I), lam, atol=tol)
    assert_close(dfm.eigenvalues_from_traces(K), lam, atol=tol)


@FAST
@given(st.data())
def test_closed_form_roots_on_well_separated_spectra(data):
    n = data.draw(dims)
    gaps = data.draw(vectors(n, batch=(3,), bound=1.0))
    lam = np.cumsum(1.5 + np.abs(gaps), axis=-1)[..., ::-1]  # separated by >= 1.5
    I = dfm.characteristic_from_eigenvalues(lam)
    assert_close(dfm.eigenvalues_from_characteristic(I), lam, 1e-9)
    assert_close(dfm.eigenvalues_from_traces(dfm.traces_from_eigenvalues(lam)), lam, 1e-9)


@pytest.mark.parametrize("n", [4, 5])
def test_newton_identities_for_general_n(n):
    rng = np.random.default_rng(n)
    lam = np.sort(rng.uniform(0.2, 3.0, size=(4, n)), axis=-1)[..., ::-1]
    expected_I = np.stack([np.poly(v)[1:] for v in lam]) * (-1.0) ** np.arange(1, n + 1)
    K = np.stack([np.sum(lam**a, axis=-1) for a in range(1, n + 1)], axis=-1)
    assert_close(dfm.characteristic_from_eigenvalues(lam), expected_I, 1e-11)
    assert_close(dfm.characteristic_from_traces(K), expected_I, 1e-10)
    assert_close(dfm.traces_from_characteristic(expected_I), K, 1e-10)
    assert_close(dfm.eigenvalues_from_characteristic(expected_I), lam, 1e-8)
    q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    phi = q @ np.diag(np.sqrt(lam[0]))
    assert_close(dfm.trace_invariants(phi), K[0], 1e-10)
    assert_close(dfm.characteristic_invariants(phi), expected_I[0], 1e-10)


def test_characteristic_invariants_are_accurate_for_strong_deformations():
    """I_p are the elementary symmetric polynomials of G's eigenvalues (19), I_n = det G.

    For stretches 1e3, 1, 1e-3 (det phi = 1) the exact values are I = (1e6 + 1 + 1e-6,
    1e6 + 1 + 1e-6, 1). They are well conditioned functions of phi (products of singular
    values), so float64 gives them to ~1e-15; Newton's identities from the power sums
    K_a ~ 1e18 cancel catastrophically (I_3 came out 0; see the report)."""
    stretches = np.array([1e3, 1.0, 1e-3])
    rotation = np.linalg.qr(np.random.default_rng(3).standard_normal((3, 3)))[0]
    for phi in (np.diag(stretches), rotation @ np.diag(stretches) @ rotation.T):
        lam = stretches**2
        exact = [lam.sum(), lam[0] * lam[1] + lam[0] * lam[2] + lam[1] * lam[2], lam.prod()]
        np.testing.assert_allclose(dfm.characteristic_invariants(phi), exact, rtol=1e-9)


def test_degenerate_spectra_give_finite_roots():
    for n in (1, 2, 3):
        for phi in (np.eye(n), 2.0 * np.eye(n), np.diag([2.0, 2.0, 0.5][:n])):
            lam = np.linalg.eigvalsh(phi.T @ phi)[::-1]
            roots = np.asarray(dfm.eigenvalues_from_traces(dfm.trace_invariants(phi)))
            assert np.all(np.isfinite(roots))
            assert_close(roots, lam, atol=1e-6)


@FAST
@given(st.sampled_from(("SO", "O")), st.data())
def test_strains_vanish_at_orthogonal_configurations(group, data):
    rot = data.draw(matrices(group))
    assert_close(dfm.lagrange_strain(rot), 0.0, atol=1e-12)
    assert_close(dfm.euler_strain(rot), 0.0, atol=1e-12)


@FAST
@given(st.data())
def test_strains_32(data):
    n = data.draw(dims)
    phi, rot = data.draw(matrices("GL", n)), data.draw(matrices("O", n))
    g = _T(phi) @ phi
    c = _T(_inv(phi)) @ _inv(phi)
    assert_close(dfm.lagrange_strain(phi), 0.5 * (g - np.eye(n)), 1e-12)
    assert_close(dfm.euler_strain(phi), 0.5 * (np.eye(n) - c), 1e-10)
    assert_close(dfm.lagrange_strain(rot @ phi), dfm.lagrange_strain(phi), 1e-10)
    assert_close(dfm.euler_strain(phi @ rot), dfm.euler_strain(phi), 1e-10)


def test_singular_phi_is_refused_by_cauchy_tensor():
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    for f in (dfm.cauchy_tensor, dfm.inverse_green_tensor, dfm.euler_strain):
        with pytest.raises(ValueError, match="phi is singular"):
            f(singular)
    with pytest.raises(ValueError, match=r"phi must have shape \[\.\.\., n, n\]"):
        dfm.green_tensor(np.ones((2, 3)))
