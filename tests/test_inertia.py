"""Inertia of an affine body from its constituents: paper eqs. (8), (9)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from affinebody import inertia
from strategies import assert_close, dims, matrices, vectors

FAST = settings(max_examples=15, deadline=None)


@st.composite
def constituents(draw, n=None):
    """Masses [P] > 0 and generic positions [P, n] with P = n + 3 (spanning R^n)."""
    if n is None:
        n = draw(dims)
    count = n + 3
    masses = draw(hnp.arrays(np.float64, (count,), elements=st.floats(0.1, 5.0)))
    positions = draw(hnp.arrays(np.float64, (count, n), elements=st.floats(-3.0, 3.0)))
    # Keep the spread of the points away from a hyperplane (J well conditioned).
    centred = positions - positions.mean(axis=0)
    singular = np.linalg.svd(centred, compute_uv=False)
    if singular[-1] < 0.3:
        positions = positions + 0.5 * np.eye(count, n)
    return masses, positions


def _second_moment(masses, positions, about):
    rel = positions - about
    return np.einsum("p,pk,pl->kl", masses, rel, rel)


@FAST
@given(constituents())
def test_from_constituents_8(sample):
    masses, positions = sample
    M, J, centre = (np.asarray(v) for v in inertia.from_constituents(masses, positions))
    assert_close(M, masses.sum(), 1e-14)
    assert_close(centre, masses @ positions / masses.sum(), 1e-12)
    assert_close(J, _second_moment(masses, positions, centre), 1e-11)
    assert_close(J, J.T, 1e-14)
    assert np.all(np.linalg.eigvalsh(J) > 0)
    # Parallel-axis (Steiner) theorem: the moment about the origin is J + M c c^T.
    assert_close(_second_moment(masses, positions, 0.0), J + M * np.outer(centre, centre), 1e-11)
    # Scaling all masses scales M and J, not the centre.
    M2, J2, centre2 = inertia.from_constituents(3.0 * masses, positions)
    assert_close(M2, 3 * M, 1e-14)
    assert_close(J2, 3 * J, 1e-11)
    assert_close(centre2, centre, 1e-12)


@FAST
@given(st.data())
def test_inertia_is_translation_invariant_and_rotates_covariantly(data):
    n = data.draw(dims)
    masses, positions = data.draw(constituents(n))
    shift = data.draw(vectors(n, ()))
    rot = data.draw(matrices("O", n, ()))
    _, J, centre = inertia.from_constituents(masses, positions)
    _, J_shifted, centre_shifted = inertia.from_constituents(masses, positions + shift)
    assert_close(J_shifted, J, 1e-10)
    assert_close(centre_shifted, np.asarray(centre) + shift, 1e-12)
    _, J_rotated, centre_rotated = inertia.from_constituents(masses, positions @ rot.T)
    assert_close(J_rotated, rot @ np.asarray(J) @ rot.T, 1e-10)
    assert_close(centre_rotated, rot @ np.asarray(centre), 1e-12)


def _ball_quadrature(mass, radius, n):
    """Point masses reproducing the uniform n-ball's second moments *exactly*.

    Tensor Gauss-Legendre rules in the radius (and cos of the polar angle for n = 3) and the
    trapezoid rule in the azimuth, with weights times the volume element as masses: exact
    for the polynomial/trigonometric integrands of the second moments."""
    rho, w_rho = np.polynomial.legendre.leggauss(4)
    rho, w_rho = radius * (rho + 1) / 2, w_rho * radius / 2
    if n == 1:
        x, w = np.polynomial.legendre.leggauss(3)
        points, weights = radius * x[:, None], w
    elif n == 2:
        angle = 2 * np.pi * np.arange(8) / 8
        r, a = np.meshgrid(rho, angle, indexing="ij")
        points = np.stack([r * np.cos(a), r * np.sin(a)], axis=-1).reshape(-1, 2)
        weights = (w_rho[:, None] * rho[:, None] * np.ones_like(angle)).ravel()
    else:
        mu, w_mu = np.polynomial.legendre.leggauss(4)
        angle = 2 * np.pi * np.arange(8) / 8
        r, c, a = np.meshgrid(rho, mu, angle, indexing="ij")
        s = np.sqrt(1 - c**2)
        points = np.stack([r * s * np.cos(a), r * s * np.sin(a), r * c], axis=-1).reshape(-1, 3)
        weights = (w_rho[:, None, None] * rho[:, None, None] ** 2 * w_mu[None, :, None]
                   * np.ones_like(a)).ravel()
    return mass * weights / weights.sum(), points


@pytest.mark.parametrize("n", [1, 2, 3])
def test_uniform_ball_against_exact_quadrature(n):
    mass, radius = 2.5, 0.7
    masses, positions = _ball_quadrature(mass, radius, n)
    M, J, centre = inertia.from_constituents(masses, positions)
    assert_close(M, mass, 1e-14)
    assert_close(centre, 0.0, atol=1e-14)
    assert_close(J, inertia.uniform_ball(mass, radius, n), 1e-12)
    assert_close(inertia.uniform_ball(mass, radius, n), mass * radius**2 / (n + 2) * np.eye(n))


def test_uniform_ball_against_monte_carlo():
    """n = 3, 40000 uniform points (fixed seed): for the unit ball Var(x^2) = 3/35 - 1/25, so
    the relative standard error of each diagonal entry is ~0.5 %; 3 % is ~6 sigma."""
    rng = np.random.default_rng(12345)
    cube = rng.uniform(-1.0, 1.0, size=(80000, 3))
    points = cube[np.sum(cube**2, axis=1) <= 1.0][:40000]
    assert points.shape[0] == 40000
    masses = np.full(points.shape[0], 4.0 / points.shape[0])
    _, J, _ = inertia.from_constituents(masses, 1.5 * points)
    expected = inertia.uniform_ball(4.0, 1.5, 3)
    assert_close(J, expected, atol=0.03 * float(expected[0, 0]))


@pytest.mark.parametrize(
    "positions",
    [
        np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [-1.0, -1.0]]),  # collinear in 2D
        np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]]),  # plane
        np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]),  # point
        np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),  # P = n: a plane
        np.array([[0.5]]),  # one point on a line
    ],
)
def test_degenerate_constituents_are_refused_naming_J(positions):
    masses = np.ones(positions.shape[0])
    with pytest.raises(ValueError, match="J must be positive definite"):
        inertia.from_constituents(masses, positions)


def test_bad_masses_and_shapes():
    positions = np.eye(3)
    with pytest.raises(ValueError, match="masses"):
        inertia.from_constituents(np.array([1.0, -1.0, 1.0]), positions)
    with pytest.raises(ValueError, match="masses"):
        inertia.from_constituents(np.array([1.0, 0.0, 1.0]), positions)
    with pytest.raises(ValueError, match=r"masses must have shape \[P\]"):
        inertia.from_constituents(np.ones(2), positions)


def test_check_inertia():
    good = np.diag([1.0, 2.0, 3.0])
    assert_close(inertia.check_inertia(good), good, 0.0)
    with pytest.raises(ValueError, match="J must be symmetric"):
        inertia.check_inertia(np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="J must be positive definite"):
        inertia.check_inertia(np.diag([1.0, -1.0]))
    with pytest.raises(ValueError, match="J must be positive definite"):
        inertia.check_inertia(np.diag([1.0, 0.0]))
    with pytest.raises(ValueError, match="float64"):
        inertia.check_inertia(good.astype(np.float32))
    with pytest.raises(ValueError, match="J must have shape"):
        inertia.check_inertia(np.ones(3))
