"""Mutual tensors and invariants of pairs of bodies: paper eqs. (20)-(33a), (75)-(79)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import deformation as dfm
from affinebody import mutual as mu
from strategies import SAMPLED_GROUPS, assert_close, dims, matrices, vectors

FAST = settings(max_examples=12, deadline=None)

_T = lambda a: np.swapaxes(np.asarray(a), -1, -2)
_inv = np.linalg.inv


def _powers_traces(m):
    m = np.asarray(m)
    n = m.shape[-1]
    return np.stack(
        [np.trace(np.linalg.matrix_power(m, a), axis1=-2, axis2=-1) for a in range(1, n + 1)],
        axis=-1,
    )


@FAST
@given(st.data())
def test_definitions_20_21_and_reduction_to_single_body(data):
    n = data.draw(dims)
    psi, phi = data.draw(matrices("GL", n)), data.draw(matrices("GL", n))
    assert_close(mu.mutual_green(psi, phi), _T(psi) @ phi, 1e-12)
    assert_close(mu.mutual_cauchy(psi, phi), _T(_inv(phi)) @ _inv(psi), 1e-10)
    assert_close(mu.mutual_gamma(psi, phi), _inv(psi) @ phi, 1e-10)
    assert_close(mu.mutual_sigma(psi, phi), phi @ _inv(psi), 1e-10)
    assert_close(mu.mutual_green(psi, psi), dfm.green_tensor(psi), 1e-12)
    assert_close(mu.mutual_cauchy(psi, psi), dfm.cauchy_tensor(psi), 1e-10)


@FAST
@given(st.sampled_from(("SO", "O")), st.data())
def test_gamma_sigma_reduce_to_g_c_for_orthogonal_configurations_22(group, data):
    n = data.draw(dims)
    psi, phi = data.draw(matrices(group, n)), data.draw(matrices(group, n))
    assert_close(mu.mutual_gamma(psi, phi), mu.mutual_green(psi, phi), 1e-10)
    assert_close(mu.mutual_sigma(psi, phi), mu.mutual_cauchy(psi, phi), 1e-10)


@FAST
@given(st.data())
def test_transformation_rules_23_24_26_27(data):
    n = data.draw(dims)
    psi, phi, a = (data.draw(matrices("GL", n)) for _ in range(3))
    rot = data.draw(matrices("O", n))
    g, c = mu.mutual_green(psi, phi), mu.mutual_cauchy(psi, phi)
    gamma, sigma = mu.mutual_gamma(psi, phi), mu.mutual_sigma(psi, phi)
    # (23): A in O(n)
    assert_close(mu.mutual_green(rot @ psi, rot @ phi), g, 1e-10)
    assert_close(mu.mutual_cauchy(psi @ rot, phi @ rot), c, 1e-9)
    # (24): A in GL(n)
    assert_close(mu.mutual_green(psi @ a, phi @ a), _T(a) @ g @ a, 1e-10)
    assert_close(mu.mutual_cauchy(a @ psi, a @ phi), _T(_inv(a)) @ c @ _inv(a), 1e-9)
    # (26): spatial A in GL(n)
    assert_close(mu.mutual_gamma(a @ psi, a @ phi), gamma, 1e-9)
    assert_close(mu.mutual_sigma(a @ psi, a @ phi), a @ sigma @ _inv(a), 1e-9)
    # (27): material A in GL(n)
    assert_close(mu.mutual_gamma(psi @ a, phi @ a), _inv(a) @ gamma @ a, 1e-9)
    assert_close(mu.mutual_sigma(psi @ a, phi @ a), sigma, 1e-9)


@FAST
@given(st.data())
def test_trace_invariants_28_29(data):
    n = data.draw(dims)
    psi, phi = data.draw(matrices("GL", n)), data.draw(matrices("GL", n))
    a, b = data.draw(matrices("O", n)), data.draw(matrices("O", n))
    K = np.asarray(mu.mutual_trace_invariants(psi, phi))
    assert_close(K, _powers_traces(_T(psi) @ phi), 1e-10)
    # (28): Tr(G[psi, phi]^a) = Tr(C[psi, phi]^-a)
    assert_close(_powers_traces(_inv(mu.mutual_cauchy(psi, phi))), K, 1e-8)
    # (29): invariant under common orthogonal A psi B, A phi B
    assert_close(mu.mutual_trace_invariants(a @ psi @ b, a @ phi @ b), K, 1e-9)
    # and reduce to (17) for phi = psi
    assert_close(mu.mutual_trace_invariants(psi, psi), dfm.trace_invariants(psi), 1e-10)


@FAST
@given(st.data())
def test_affine_invariants_30_31_for_all_of_gl(data):
    """(31) holds for all A, B in GL(n) (the printed O(n) is a typo, docs/theory/paper-typos.md)."""
    n = data.draw(dims)
    psi, phi, a, b = (data.draw(matrices("GL", n)) for _ in range(4))
    M = np.asarray(mu.affine_invariants(psi, phi))
    assert_close(M, _powers_traces(_inv(psi) @ phi), 1e-9)
    assert_close(M, _powers_traces(phi @ _inv(psi)), 1e-9)  # Tr Gamma^a = Tr Sigma^a
    assert_close(mu.affine_invariants(a @ psi @ b, a @ phi @ b), M, 1e-8)


@FAST
@given(st.data())
def test_mutual_strains_33_33a(data):
    """(33) with the mutual tensors (docs/theory/paper-typos.md), and (33a)."""
    n = data.draw(dims)
    psi, phi, a = (data.draw(matrices("GL", n)) for _ in range(3))
    rot = data.draw(matrices("O", n))
    eye = np.eye(n)
    assert_close(mu.mutual_lagrange_strain(psi, phi), 0.5 * (_T(psi) @ phi - eye), 1e-12)
    assert_close(mu.mutual_euler_strain(psi, phi), 0.5 * (eye - _T(_inv(phi)) @ _inv(psi)), 1e-10)
    assert_close(mu.mutual_gamma_strain(psi, phi), _inv(psi) @ phi - eye, 1e-10)
    assert_close(mu.mutual_sigma_strain(psi, phi), phi @ _inv(psi) - eye, 1e-10)
    # They reduce to the single-body strains (32) for phi = psi ...
    assert_close(mu.mutual_lagrange_strain(psi, psi), dfm.lagrange_strain(psi), 1e-12)
    assert_close(mu.mutual_euler_strain(psi, psi), dfm.euler_strain(psi), 1e-10)
    # ... and (33) depends on both arguments (the printed G[phi], C[phi] would not).
    assert_close(mu.mutual_lagrange_strain(rot @ psi, phi), 0.5 * (_T(psi) @ _T(rot) @ phi - eye))
    # gamma, sigma vanish when the configurations coincide, for any phi in GL(n), ...
    assert_close(mu.mutual_gamma_strain(phi, phi), 0.0, atol=1e-10)
    assert_close(mu.mutual_sigma_strain(phi, phi), 0.0, atol=1e-10)
    # ... E, e when they coincide and are orthogonal.
    assert_close(mu.mutual_lagrange_strain(rot, rot), 0.0, atol=1e-12)
    assert_close(mu.mutual_euler_strain(rot, rot), 0.0, atol=1e-12)
    # gamma is spatially affine invariant, sigma materially (26), (27)
    assert_close(mu.mutual_gamma_strain(a @ psi, a @ phi), mu.mutual_gamma_strain(psi, phi), 1e-9)
    assert_close(mu.mutual_sigma_strain(psi @ a, phi @ a), mu.mutual_sigma_strain(psi, phi), 1e-9)


# ------------------------------------------------------------------- affine distance (75)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_affine_distance_75(group, data):
    n = data.draw(dims)
    phi_k, phi_l = data.draw(matrices(group, n)), data.draw(matrices("GL", n))
    x_k, x_l = data.draw(vectors(n)), data.draw(vectors(n))
    u = x_k - x_l
    metric = 0.5 * (_T(_inv(phi_k)) @ _inv(phi_k) + _T(_inv(phi_l)) @ _inv(phi_l))
    assert_close(mu.mean_cauchy_tensor(phi_k, phi_l), metric, 1e-10)
    assert_close(mu.mean_cauchy_tensor(phi_l, phi_k), metric, 1e-10)  # symmetric in K, L
    assert np.all(np.linalg.eigvalsh(metric) > 0)  # positive definite
    d2 = np.einsum("...i,...ij,...j->...", u, metric, u)
    assert_close(mu.affine_distance_squared(x_k, phi_k, x_l, phi_l), d2, 1e-10)
    assert_close(mu.affine_distance(x_k, phi_k, x_l, phi_l), np.sqrt(d2), 1e-10)
    assert_close(mu.affine_distance(x_l, phi_l, x_k, phi_k), np.sqrt(d2), 1e-10)
    assert_close(mu.affine_distance(x_k, phi_k, x_k, phi_l), 0.0, atol=0.0)


@FAST
@given(st.data())
def test_affine_distance_is_spatially_affine_invariant_76(data):
    n = data.draw(dims)
    phi_k, phi_l, a = (data.draw(matrices("GL", n)) for _ in range(3))
    x_k, x_l, b = (data.draw(vectors(n)) for _ in range(3))
    d = mu.affine_distance(x_k, phi_k, x_l, phi_l)

    def move(x):
        return np.einsum("...ij,...j->...i", a, x) + b

    assert_close(mu.affine_distance(move(x_k), a @ phi_k, move(x_l), a @ phi_l), d, 1e-9)


@FAST
@given(st.data())
def test_affine_distance_under_material_transformations(data):
    """Not invariant under phi -> phi B in general: C[phi B] = phi^-T B^-T B^-1 phi^-1.
    Exactly: B orthogonal leaves D unchanged (14), B = s Id divides it by |s|."""
    n = data.draw(dims)
    phi_k, phi_l = data.draw(matrices("GL", n)), data.draw(matrices("GL", n))
    rot = data.draw(matrices("O", n))
    x_k, x_l = data.draw(vectors(n)), data.draw(vectors(n))
    s = data.draw(st.floats(0.2, 5.0)) * data.draw(st.sampled_from((-1.0, 1.0)))
    d = np.asarray(mu.affine_distance(x_k, phi_k, x_l, phi_l))
    assert_close(mu.affine_distance(x_k, phi_k @ rot, x_l, phi_l @ rot), d, 1e-9)
    assert_close(mu.affine_distance(x_k, s * phi_k, x_l, s * phi_l), d / abs(s), 1e-9)


def test_affine_distance_changes_under_a_generic_material_shear():
    phi = np.eye(2)
    shear = np.array([[1.0, 1.0], [0.0, 1.0]])
    x_k, x_l = np.array([0.0, 1.0]), np.zeros(2)
    # u = e_2, phi B = shear: |shear^-1 e_2|^2 = 2, so D changes from 1 to sqrt(2).
    assert_close(mu.affine_distance(x_k, phi, x_l, phi), 1.0, 1e-14)
    assert_close(mu.affine_distance(x_k, phi @ shear, x_l, phi @ shear), np.sqrt(2.0), 1e-14)


# ------------------------------------------------------------------- relative volume (79)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_relative_volume_79(group, data):
    n = data.draw(dims)
    phi_k, phi_l = data.draw(matrices(group, n)), data.draw(matrices("GL", n))
    a, b = data.draw(matrices("GL", n)), data.draw(matrices("GL", n))
    ratio = np.linalg.det(phi_l) / np.linalg.det(phi_k)
    assert_close(mu.relative_volume(phi_k, phi_l), ratio, 1e-10)
    det_gamma = np.linalg.det(mu.mutual_gamma(phi_k, phi_l))
    assert_close(mu.relative_volume(phi_k, phi_l), det_gamma, 1e-9)
    # invariant under the spatial and the material affine action
    assert_close(mu.relative_volume(a @ phi_k @ b, a @ phi_l @ b), ratio, 1e-9)


def test_bad_input_names_the_argument():
    singular = np.array([[1.0, 2.0], [2.0, 4.0]])
    with pytest.raises(ValueError, match="psi is singular"):
        mu.mutual_gamma(singular, np.eye(2))
    with pytest.raises(ValueError, match="phi_k is singular"):
        mu.affine_distance(np.zeros(2), singular, np.ones(2), np.eye(2))
    with pytest.raises(ValueError, match="phi has dimension 3"):
        mu.mutual_green(np.eye(2), np.eye(3))
    with pytest.raises(ValueError, match="x_l"):
        mu.affine_distance(np.zeros(2), np.eye(2), np.ones(3), np.eye(2))
