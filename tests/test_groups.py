"""Configuration groups of paper §1: membership, projections, Lie algebras, expm/logm."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import groups
from strategies import (
    SAMPLED_GROUPS,
    assert_close,
    dims,
    matrices,
    orthogonal,
    positive_spectrum_matrices,
    square_matrices,
)

FAST = settings(max_examples=12, deadline=None)

# Module-level jit: groups.logm's run-time loop (and expm's branches) would be re-traced on
# every eager call; compiled once per shape here.
expm = jax.jit(groups.expm)
logm = jax.jit(groups.logm)

#: Groups each sampled set must belong to (paper §1: SO c O, SO c SL c UL, R+SO c GL+, ...).
MEMBER_OF = {
    "GL": ("GL",),
    "GL+": ("GL", "GL+"),
    "GL-": ("GL",),
    "SL": ("GL", "GL+", "SL", "UL"),
    "UL": ("GL", "UL"),
    "SO": ("GL", "GL+", "SL", "UL", "SO", "O", "R+SO", "R+O"),
    "O": ("GL", "UL", "O", "R+O"),
    "R+SO": ("GL", "GL+", "R+SO", "R+O"),
    "R+O": ("GL", "R+O"),
}
#: Groups a sample with det < 0 can never belong to.
NEEDS_POSITIVE_DET = ("GL+", "SL", "SO", "R+SO")


def _frobenius(a):
    return np.sqrt(np.sum(np.asarray(a) ** 2, axis=(-2, -1)))


def _in_group_numpy(phi, group, tol=1e-9):
    """Independent membership test in NumPy (for checking projections)."""
    phi = np.asarray(phi)
    n = phi.shape[-1]
    det = np.linalg.det(phi)
    g = np.swapaxes(phi, -1, -2) @ phi
    if group in ("GL", "GL+"):
        ok = np.abs(det) > 1e-12
        return ok & (det > 0) if group == "GL+" else ok
    if group == "SL":
        return np.abs(det - 1) < tol
    if group == "UL":
        return np.abs(np.abs(det) - 1) < tol
    s2 = np.trace(g, axis1=-2, axis2=-1) / n
    if group in ("SO", "O"):
        s2 = np.ones_like(s2)
    metric = np.max(np.abs(g - s2[..., None, None] * np.eye(n)), axis=(-2, -1)) < tol * s2
    return metric & (det > 0) if group in ("SO", "R+SO") else metric


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_samples_are_members_of_their_groups(group, data):
    phi = data.draw(matrices(group))
    for target in MEMBER_OF[group]:
        assert np.all(groups.is_member(phi, target, tol=1e-9)), (group, target)
    if np.all(np.linalg.det(phi) < 0):
        for target in NEEDS_POSITIVE_DET:
            assert not np.any(groups.is_member(phi, target)), (group, target)


@FAST
@given(st.data())
def test_membership_rejects_generic_elements(data):
    n = data.draw(st.sampled_from((2, 3)))
    # Singular values exactly 1 and 2 (det = 2^k): not unimodular, not a scaled rotation.
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    d = np.ones(n)
    d[0] = 2.0
    phi = (orthogonal(rng, n, (3,), 1.0) * d) @ orthogonal(rng, n, (3,), 1.0)
    for target in ("SL", "UL", "SO", "O", "R+SO", "R+O"):
        assert not np.any(groups.is_member(phi, target)), target
    assert np.all(groups.is_member(phi, "GL+"))
    singular = phi.copy()
    singular[..., :, 1] = 3.0 * singular[..., :, 0]
    assert not np.any(groups.is_member(singular, "GL"))


def test_unknown_group_is_a_value_error_naming_it():
    with pytest.raises(ValueError, match="SU"):
        groups.is_member(jnp.eye(2), "SU")
    with pytest.raises(ValueError, match="Sp"):
        groups.project(jnp.eye(2), "Sp")


# ---------------------------------------------------------------- projection onto the groups


def _has_nearest_scaled_rotation(phi):
    """Whether R+SO(n) has a nearest point to phi: the Kabsch rotation U must have
    Tr(U^T phi) = s_1 + ... + s_(n-1) + sign(det phi) s_n > 0; otherwise the infimum of the
    distance is reached only at the zero matrix (e.g. n = 1 and phi < 0)."""
    s = np.linalg.svd(phi, compute_uv=False)
    s[..., -1] *= np.sign(np.linalg.det(phi))
    return bool(np.all(np.sum(s, axis=-1) > 1e-6 * np.abs(s).sum(axis=-1)))


@FAST
@given(st.sampled_from(("GL", "GL+", "GL-", "SL", "UL", "O", "R+O")), st.data())
def test_projection_lands_in_group_and_is_idempotent(source, data):
    phi = data.draw(matrices(source))
    n = phi.shape[-1]
    for group in groups.GROUPS:
        if group == "SL" and n % 2 == 0 and np.any(np.linalg.det(phi) < 0):
            continue  # no scalar multiple of det<0, n even is in SL (documented in project)
        if group == "GL+" and np.any(np.linalg.det(phi) < 0):
            continue  # GL+ is open: no nearest point to det<0; project returns phi (see report)
        if group == "R+SO" and not _has_nearest_scaled_rotation(phi):
            continue
        projected = np.asarray(groups.project(phi, group))
        assert np.all(_in_group_numpy(projected, group)), group
        assert np.all(groups.is_member(projected, group, tol=1e-9)), group
        assert_close(groups.project(projected, group), projected, 1e-10, err=group)


@FAST
@given(st.sampled_from(SAMPLED_GROUPS), st.data())
def test_projection_is_identity_on_members(source, data):
    phi = data.draw(matrices(source))
    for group in MEMBER_OF[source]:
        assert_close(groups.project(phi, group), phi, 1e-10, err=f"{source} -> {group}")


def _nearest_orthogonal_is_unique(phi, proper):
    """[*batch] bools: whether one element of O(n) (proper: SO(n)) is nearest to phi. O(n):
    always (phi invertible: the polar factor). SO(n) with det phi < 0: only when the smallest
    singular value is simple (its direction is the one flipped); for an improper orthogonal
    phi (all singular values 1) every rotation that flips one direction is as near."""
    if not proper:
        return np.ones(phi.shape[:-2], bool)
    s = np.linalg.svd(phi, compute_uv=False)
    gap = s[..., -2] - s[..., -1] > 1e-6 * s[..., 0] if phi.shape[-1] > 1 else True
    return (np.linalg.det(phi) > 0) | gap


def _kabsch(phi, proper):
    """Nearest (special) orthogonal matrix from NumPy's SVD, written out independently."""
    u, s, vt = np.linalg.svd(phi)
    d = np.ones(s.shape)
    if proper:
        d[..., -1] = np.sign(np.linalg.det(u @ vt))
    return (u * d[..., None, :]) @ vt


@FAST
@given(st.sampled_from(("GL", "GL-", "GL+")), st.data())
def test_orthogonal_projection_is_frobenius_nearest(source, data):
    n = data.draw(dims)
    phi = data.draw(matrices(source, n))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    for group, proper in (("SO", True), ("O", False)):
        u = np.asarray(groups.project(phi, group))
        unique = _nearest_orthogonal_is_unique(phi, proper)
        assert_close(u[unique], _kabsch(phi, proper)[unique], 1e-9, err=group)
        best = _frobenius(phi - u)
        # Brute force: no random element of the group, and no nearby one, is closer.
        for _ in range(8):
            other = orthogonal(rng, n, phi.shape[:-2], 1.0 if proper else None)
            assert np.all(_frobenius(phi - other) >= best - 1e-12)
            w = rng.standard_normal(phi.shape)
            nearby = u @ scipy.linalg.expm(1e-3 * (w - np.swapaxes(w, -1, -2)))
            assert np.all(_frobenius(phi - nearby) >= best - 1e-12)


@FAST
@given(st.sampled_from(("GL", "GL+")), st.data())
def test_scaled_rotation_projection_is_frobenius_nearest(source, data):
    n = data.draw(dims)
    phi = data.draw(matrices(source, n))
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    for group, proper in (("R+SO", True), ("R+O", False)):
        if proper and not _has_nearest_scaled_rotation(phi):
            continue
        projected = np.asarray(groups.project(phi, group))
        best = _frobenius(phi - projected)
        scale = np.sqrt(np.sum(projected**2, axis=(-2, -1)) / n)
        u = projected / scale[..., None, None]
        for _ in range(8):
            w = rng.standard_normal(phi.shape)
            nearby_u = u @ scipy.linalg.expm(1e-3 * (w - np.swapaxes(w, -1, -2)))
            for factor in (1 - 1e-3, 1.0, 1 + 1e-3):
                nearby = (factor * scale)[..., None, None] * nearby_u
                assert np.all(_frobenius(phi - nearby) >= best - 1e-12), group


# ---------------------------------------------------------------------------- Lie algebras


def _inner(a, b):
    return np.sum(np.asarray(a) * np.asarray(b), axis=(-2, -1))


@FAST
@given(st.sampled_from(groups.GROUPS), st.data())
def test_project_algebra_is_an_orthogonal_projection(group, data):
    n = data.draw(dims)
    x = data.draw(square_matrices(n))
    y = data.draw(square_matrices(n))
    px = np.asarray(groups.project_algebra(x, group))
    py = np.asarray(groups.project_algebra(y, group))
    algebra = groups.lie_algebra(group)
    trace_px = np.trace(px, axis1=-2, axis2=-1)
    skew_px = 0.5 * (px - np.swapaxes(px, -1, -2))
    if algebra == "sl":
        assert_close(trace_px, 0.0, 1e-12)
    if algebra == "so":
        assert_close(px, skew_px, 1e-12)
    if algebra == "R+so":
        assert_close(px, skew_px + (trace_px / n)[..., None, None] * np.eye(n), 1e-12)
    assert_close(groups.project_algebra(px, group), px, 1e-12)  # idempotent
    assert_close(_inner(px, y), _inner(x, py), 1e-12)  # self-adjoint
    assert_close(_inner(x - px, py), 0.0, 1e-12)  # the discarded part is orthogonal


@FAST
@given(st.sampled_from(groups.GROUPS), st.data())
def test_exponential_of_algebra_lies_in_connected_group(group, data):
    n = data.draw(dims)
    x = data.draw(square_matrices(n, bound=1.0))
    element = expm(groups.project_algebra(x, group))
    connected = {"GL": "GL+", "UL": "SL", "O": "SO", "R+O": "R+SO"}.get(group, group)
    assert np.all(_in_group_numpy(element, connected, tol=1e-10)), group
    assert np.all(groups.is_member(element, group, tol=1e-10)), group


@FAST
@given(st.data())
def test_expm_against_scipy_and_one_parameter_subgroup(data):
    n = data.draw(dims)
    x = data.draw(square_matrices(n, bound=1.0))
    s, t = 0.3, -0.7
    assert_close(expm(x), np.stack([scipy.linalg.expm(m) for m in x]), 1e-12)
    assert_close(expm(s * x) @ expm(t * x), expm((s + t) * x), 1e-12)


@FAST
@given(st.data())
def test_logm_inverts_expm_for_small_x(data):
    n = data.draw(dims)
    x = data.draw(square_matrices(n, bound=0.5))  # spectral radius <= n/2 < pi
    assert_close(logm(expm(x)), x, 1e-10)


@FAST
@given(positive_spectrum_matrices())
def test_expm_inverts_logm_on_matrices_with_positive_spectrum(sample):
    phi, p, log_lam = sample
    log_phi = logm(phi)
    expected = (p * log_lam[..., None, :]) @ np.linalg.inv(p)
    assert_close(log_phi, expected, 1e-9)
    assert_close(expm(log_phi), phi, 1e-9)


@FAST
@given(st.data())
def test_logm_of_rotation_and_of_spd_matrix(data):
    n = data.draw(dims)
    w = data.draw(square_matrices(n, bound=0.5))
    w = w - np.swapaxes(w, -1, -2)  # |angle| <= (n-1) < pi
    log_r = np.asarray(logm(expm(w)))
    assert_close(log_r, -np.swapaxes(log_r, -1, -2), 1e-10)  # logm of SO(n) is in so(n)
    spd = data.draw(matrices("GL+", n))
    spd = np.swapaxes(spd, -1, -2) @ spd
    assert_close(logm(spd), np.stack([scipy.linalg.logm(m).real for m in spd]), 1e-9)


def _conditioned_matrices(n: int, rng) -> np.ndarray:
    """Matrices [K, n, n] across every conditioning: well conditioned, sheared to cond 10^k
    (k = 1 .. 17, past what float64 resolves), singular, zero, scaled by 1e+-150, not finite."""
    mats = [np.eye(n) + 0.2 * rng.standard_normal((n, n)) for _ in range(4)]
    for k in range(1, 18):
        q1, _ = np.linalg.qr(rng.standard_normal((n, n)))
        q2, _ = np.linalg.qr(rng.standard_normal((n, n)))
        mats.append(q1 @ np.diag(np.logspace(0.0, -k, n)) @ q2)
    rank_one = np.outer(rng.standard_normal(n), rng.standard_normal(n))
    mats += [rank_one, np.zeros((n, n)), 1e150 * mats[0], 1e-150 * mats[1]]
    for bad in (np.nan, np.inf):
        m = mats[0].copy()
        m[0, -1] = bad
        mats.append(m)
    return np.stack(mats)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_invertibility_screen_decides_as_the_singular_values(n):
    """is_invertible on JAX arrays (a determinant bound first, singular values only when a
    matrix of the batch is not clearly invertible) agrees, matrix by matrix, with the
    criterion from the singular values (NumPy's SVD): on a batch across every conditioning,
    on each matrix alone (where the bound decides the clear ones) and under vmap."""
    from affinebody._checks import SINGULAR_RTOL, is_invertible, reciprocal_condition

    mats = _conditioned_matrices(n, np.random.default_rng(n))
    with np.errstate(all="ignore"):
        expected = reciprocal_condition(mats) > SINGULAR_RTOL
    assert expected.any() and not expected.all()
    np.testing.assert_array_equal(np.asarray(is_invertible(jnp.asarray(mats))), expected)
    alone = jax.jit(is_invertible)
    np.testing.assert_array_equal([bool(alone(jnp.asarray(m))) for m in mats], expected)
    np.testing.assert_array_equal(np.asarray(jax.vmap(is_invertible)(jnp.asarray(mats))),
                                  expected)


def test_gl_plus_membership_is_membership_not_conditioning():
    """An isochoric shear phi = expm(t S), S symmetric traceless (det phi = 1), is in GL+ at
    any condition number float64 resolves (here 1e10, two small singular values, n = 3), and
    a system accepts it as a state (the check a resumed run applies); det phi < 0, and a phi
    whose determinant float64 cannot tell from 0, are not in GL+."""
    from affinebody import _linalg
    from affinebody.kinetic import AffineIsotropic, DAlembertTranslational, KineticEnergy
    from affinebody.potentials import Dilatation
    from affinebody.state import State
    from affinebody.system import HamiltonianSystem

    s = np.diag([2.0, -1.0, -1.0]) / 3.0
    rotation = scipy.linalg.expm(np.array([[0.0, 0.3, -0.2], [-0.3, 0.0, 0.5],
                                           [0.2, -0.5, 0.0]]))
    t = np.log(1e10)  # singular values e^(2t/3), e^(-t/3), e^(-t/3): cond = e^t
    phi = rotation @ scipy.linalg.expm(t * s) @ rotation.T
    assert np.linalg.cond(phi) == pytest.approx(1e10, rel=1e-6)
    assert abs(float(_linalg.det(jnp.asarray(phi))) - 1.0) < 1e-5
    is_member = groups.is_member
    assert bool(is_member(phi, "GL+", tol=1e-9)) and bool(is_member(phi, "GL", tol=1e-9))
    flipped = phi @ np.diag([1.0, 1.0, -1.0])
    assert not bool(is_member(flipped, "GL+")) and bool(is_member(flipped, "GL"))
    singular = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    assert not bool(is_member(singular, "GL"))
    system = HamiltonianSystem(
        KineticEnergy(DAlembertTranslational(1.0), AffineIsotropic(I=1.0, A=0.2, B=0.1)),
        Dilatation(stiffness=10.0), group="GL+")
    state = State(jnp.zeros((1, 3)), jnp.asarray(phi[None]), jnp.zeros((1, 3)),
                  jnp.zeros((1, 3, 3)))
    checked = system.check(state)
    np.testing.assert_array_equal(np.asarray(checked.phi), phi[None])
