"""Shared hypothesis strategies and assertions for the property tests.

Random matrices of every configuration group of paper §1 (GL, GL+, the coset GL-, SL, UL,
SO, O, R+SO, R+O) for n = 1, 2, 3, batched over a leading axis, with a controlled condition
number: an element is built as L diag(s) R^T with L, R Haar-random rotations (from a seed that
hypothesis draws) and log-singular values drawn by hypothesis from [-c/2, c/2], so that
cond(phi) <= exp(c). Hypothesis likes to repeat values, so coincident singular values (the
degenerate points of the two-polar decomposition) come up on their own as well.

Use with ``st.data()`` to share n between several draws::

    n = data.draw(dims)
    phi = data.draw(matrices("GL", n))
"""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

#: Groups (and the coset GL-) that ``matrices`` samples.
SAMPLED_GROUPS = ("GL", "GL+", "GL-", "SL", "UL", "SO", "O", "R+SO", "R+O")
DIMS = (1, 2, 3)
#: Default batch shape: small, fixed, so that JAX compiles each operation once per n.
BATCH = (3,)
#: Default bound c on log cond(phi).
MAX_LOG_COND = 3.0

dims = st.sampled_from(DIMS)
seeds = st.integers(0, 2**32 - 1)


def orthogonal(rng: np.random.Generator, n: int, batch=BATCH, det: float | None = None):
    """Haar-random orthogonal matrices [*batch, n, n] (QR with sign fix).

    det = +1 or -1 fixes the determinant; None leaves it random.
    """
    z = rng.standard_normal(tuple(batch) + (n, n))
    q, r = np.linalg.qr(z)
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]
    if det is not None:
        flip = np.where(np.sign(np.linalg.det(q)) == det, 1.0, -1.0)
        q[..., :, 0] = q[..., :, 0] * flip[..., None]
    return q


def random_signs(rng: np.random.Generator, batch) -> np.ndarray:
    return rng.choice([-1.0, 1.0], size=tuple(batch))


def element_from_log_singular_values(group: str, log_s: np.ndarray, rng: np.random.Generator):
    """An element of ``group`` with singular values exp(log_s) (normalised for SL/UL/R+...)."""
    n = log_s.shape[-1]
    batch = log_s.shape[:-1]
    if group in ("SO", "O", "R+SO", "R+O"):
        det = 1.0 if group.endswith("SO") else None
        u = orthogonal(rng, n, batch, det)
        if group.startswith("R+"):
            u = u * np.exp(log_s[..., :1, None])
        return u
    if group in ("SL", "UL"):
        log_s = log_s - np.mean(log_s, axis=-1, keepdims=True)
    if group in ("GL+", "SL"):
        sign = np.ones(batch)
    elif group == "GL-":
        sign = -np.ones(batch)
    elif group in ("GL", "UL"):
        sign = random_signs(rng, batch)
    else:
        raise ValueError(f"unknown group {group!r}")
    left = orthogonal(rng, n, batch, 1.0)
    right = orthogonal(rng, n, batch, 1.0)
    d = np.exp(log_s)
    d[..., -1] = d[..., -1] * sign
    return (left * d[..., None, :]) @ np.swapaxes(right, -1, -2)


def _log_singular_values(n: int, batch, max_log_cond: float):
    half = max_log_cond / 2
    return hnp.arrays(
        np.float64,
        tuple(batch) + (n,),
        elements=st.floats(-half, half, allow_nan=False, allow_infinity=False),
    )


@st.composite
def matrices(draw, group: str, n: int | None = None, batch=BATCH, max_log_cond=MAX_LOG_COND):
    """float64 array [*batch, n, n] of elements of ``group`` (one of SAMPLED_GROUPS)."""
    if n is None:
        n = draw(dims)
    log_s = draw(_log_singular_values(n, batch, max_log_cond))
    rng = np.random.default_rng(draw(seeds))
    return element_from_log_singular_values(group, log_s, rng)


@st.composite
def degenerate_matrices(draw, n: int | None = None, batch=BATCH):
    """Invertible matrices with coincident singular values: c * orthogonal, or L D R^T with
    D having a repeated entry (all entries equal for n <= 2), of either determinant sign."""
    if n is None:
        n = draw(dims)
    rng = np.random.default_rng(draw(seeds))
    a = draw(st.floats(-1.0, 1.0))
    b = draw(st.floats(-1.0, 1.0))
    pattern = draw(st.sampled_from(["all", "top", "bottom"]))
    log_s = np.full(tuple(batch) + (n,), a)
    if n == 3 and pattern == "top":
        log_s[..., 2] = b
    elif n == 3 and pattern == "bottom":
        log_s[..., 0] = b
    left = orthogonal(rng, n, batch, 1.0)
    right = orthogonal(rng, n, batch, None)
    return (left * np.exp(log_s)[..., None, :]) @ np.swapaxes(right, -1, -2)


def square_matrices(n: int, batch=BATCH, bound: float = 2.0):
    """General n x n matrices (velocities xi, momenta pi, Lie algebra elements)."""
    return hnp.arrays(
        np.float64,
        tuple(batch) + (n, n),
        elements=st.floats(-bound, bound, allow_nan=False, allow_infinity=False),
    )


def vectors(n: int, batch=BATCH, bound: float = 3.0):
    """Vectors [*batch, n] (centres x, velocities v, momenta p)."""
    return hnp.arrays(
        np.float64,
        tuple(batch) + (n,),
        elements=st.floats(-bound, bound, allow_nan=False, allow_infinity=False),
    )


@st.composite
def positive_spectrum_matrices(draw, n: int | None = None, batch=BATCH):
    """P diag(lambda) P^-1 with lambda in [e^-2, e^2] and cond(P) <= e: real positive
    eigenvalues, so the principal logarithm is real and log(phi) = P diag(log lambda) P^-1."""
    if n is None:
        n = draw(dims)
    log_lam = draw(_log_singular_values(n, batch, 4.0))
    p = draw(matrices("GL", n, batch, max_log_cond=1.0))
    return (p * np.exp(log_lam)[..., None, :]) @ np.linalg.inv(p), p, log_lam


def assert_close(actual, expected, rtol: float = 1e-9, atol: float | None = None, err=""):
    """assert_allclose with an absolute floor rtol * max(1, max|expected|)."""
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    if atol is None:
        scale = max(1.0, float(np.max(np.abs(expected)))) if expected.size else 1.0
        atol = rtol * scale
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=atol, err_msg=err)
