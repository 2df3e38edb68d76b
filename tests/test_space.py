"""Periodic boxes: the minimum image is the nearest lattice image (checked against an explicit
search over images), wrapping maps into the cell, perpendicular widths, validation."""

import itertools

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody.space import Space, as_space, free_space, orthorhombic, triclinic

TRICLINIC = np.array([[4.0, 1.3, -0.8], [0.0, 3.5, 0.9], [0.0, 0.0, 4.2]])


def nearest_image(h: np.ndarray, u: np.ndarray, reach: int = 3) -> np.ndarray:
    """The shortest u + H m over m in {-reach..reach}^n (explicit search)."""
    n = h.shape[0]
    shifts = np.array(list(itertools.product(range(-reach, reach + 1), repeat=n))) @ h.T
    images = u[:, None, :] + shifts[None]
    best = np.argmin(np.sum(images**2, axis=-1), axis=1)
    return images[np.arange(u.shape[0]), best]


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
@pytest.mark.parametrize("matrix", [np.diag([3.1, 4.0, 5.2]), TRICLINIC, TRICLINIC[:2, :2]],
                         ids=["orthorhombic", "triclinic", "triclinic-2d"])
def test_displacement_is_the_nearest_image_within_half_the_width(matrix, seed):
    rng = np.random.default_rng(seed)
    space = triclinic(matrix)
    n = matrix.shape[0]
    x_k = rng.uniform(-10, 10, size=(64, n))
    x_l = rng.uniform(-10, 10, size=(64, n))
    u = np.asarray(space.displacement(jnp.asarray(x_k), jnp.asarray(x_l)))
    # always x_K - x_L plus a lattice vector
    m = np.linalg.solve(matrix, (u - (x_k - x_l)).T).T
    np.testing.assert_allclose(m, np.round(m), atol=1e-9)
    # and the nearest image whenever that one lies within max_cutoff
    nearest = nearest_image(matrix, x_k - x_l)
    in_range = np.linalg.norm(nearest, axis=-1) < space.max_cutoff
    assert np.any(in_range)
    np.testing.assert_allclose(u[in_range], nearest[in_range], atol=1e-12)


def test_orthorhombic_equals_diagonal_triclinic_and_free_space_is_plain_difference():
    rng = np.random.default_rng(3)
    x_k, x_l = (jnp.asarray(rng.uniform(-9, 9, size=(50, 3))) for _ in range(2))
    edges = (3.0, 4.5, 5.0)
    ortho = orthorhombic(edges)
    assert ortho.orthorhombic and ortho == as_space(edges) == as_space(np.diag(edges))
    expected = np.asarray(x_k - x_l) - np.asarray(edges) * np.round(
        np.asarray(x_k - x_l) / np.asarray(edges))
    np.testing.assert_array_equal(ortho.displacement(x_k, x_l), expected)
    assert not triclinic(TRICLINIC).orthorhombic
    np.testing.assert_array_equal(free_space().displacement(x_k, x_l), x_k - x_l)
    assert free_space().max_cutoff == np.inf and not as_space(None).periodic


def test_wrap_maps_into_the_cell_by_lattice_vectors_and_displacements_are_periodic():
    rng = np.random.default_rng(4)
    space = triclinic(TRICLINIC)
    x = jnp.asarray(rng.uniform(-20, 20, size=(100, 3)))
    wrapped = space.wrap(x)
    s = np.asarray(space.fractional(wrapped))
    assert np.all(s >= 0) and np.all(s < 1)
    m = np.linalg.solve(TRICLINIC, np.asarray(wrapped - x).T)
    np.testing.assert_allclose(m, np.round(m), atol=1e-9)
    shifted = x + jnp.asarray(rng.integers(-3, 4, size=(100, 3)) @ TRICLINIC.T, dtype=float)
    np.testing.assert_allclose(space.displacement(shifted, x[::-1]),
                               space.displacement(x, x[::-1]), atol=1e-12)


def test_perpendicular_widths_and_volume():
    space = triclinic(TRICLINIC)
    a, b, c = TRICLINIC.T
    volume = abs(np.dot(a, np.cross(b, c)))
    expected = [volume / np.linalg.norm(np.cross(b, c)), volume / np.linalg.norm(np.cross(c, a)),
                volume / np.linalg.norm(np.cross(a, b))]
    np.testing.assert_allclose(space.widths, expected, rtol=1e-13)
    assert space.volume == pytest.approx(volume, rel=1e-13)
    assert space.max_cutoff == pytest.approx(min(expected) / 2, rel=1e-13)
    np.testing.assert_allclose(orthorhombic((2.0, 3.0)).widths, [2.0, 3.0])


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: triclinic([[1.0, 0.0], [0.0, -1.0]]), "det > 0"),
        (lambda: orthorhombic((1.0, 0.0)), "must be > 0"),
        (lambda: orthorhombic("abc"), "list of n positive edges"),
        (lambda: Space(((1.0, 2.0),)), "n x n matrix"),
        (lambda: orthorhombic((4.0, 4.0)).check_cutoff(2.5, "r_cut"), "r_cut = 2.5 exceeds"),
        (lambda: orthorhombic((4.0, 4.0)).check_dimension(3), "2-dimensional but n = 3"),
    ],
)
def test_bad_boxes_are_refused(make, message):
    with pytest.raises(ValueError, match=message):
        make()
