"""Regression tests for jitted float64 reductions on the CPU backend.

Why this file exists: ``pyproject.toml`` excludes jax/jaxlib 0.10.2, which
silently returns wrong sums under ``jax.jit`` on CPU (upstream jax-ml/jax
issue #39103).  The faulty pattern is a dot product whose *right* operand is
contracted over its minor axis, ``dot(A[p, k], X[n, k]^T) -> [p, n]``, followed
(optionally after an elementwise op) by a reduction over the ``p`` axis.  That
is what ``jax.vmap(lambda r: jnp.sum(A @ r))(X)`` lowers to, i.e. the typical
"per-body quadratic/linear form of a small matrix" in this project.  0.10.2
fuses the dot and the reduce into one YNNPACK kernel, and for ``k`` in
{3, 5, 6, 7}, ``n > 16384`` and an operand below ~1 MiB, every output element
from index 16384 on is computed from the wrong input row (row ``j - 64`` on the
machine this was written on, ``j - 16`` in the upstream report): errors are
O(1), not rounding noise.  Plain ``jnp.sum``/``mean``/``cumsum``/``einsum``
etc. were found to be correct in 0.10.2; they are tested here as well so that
a different regression of the same kind would be caught too.

Every test states a mathematical fact, not a version: a jitted float64
reduction agrees with the exactly rounded sum (``math.fsum``), or, for
integer-valued data where every intermediate is exactly representable,
agrees with it exactly.

Tolerance.  For any summation order (sequential, pairwise, blocked, SIMD) the
float64 result of summing ``m`` terms satisfies
``|computed - exact| <= gamma_(m-1) * sum|x_i|`` with
``gamma_j = j*u / (1 - j*u)`` and ``u = 2**-53`` (Higham, *Accuracy and
Stability of Numerical Algorithms*, 2nd ed., sec. 4.2).  We use
``rtol(m) = max(1e-13, 2*m*u)`` relative to ``sum|x_i|``: a rigorous bound
(the factor 2 also covers one more rounding, e.g. the division in a mean or
the products of a dot), equal to 1e-13 for up to ~450 terms.  Float32
accumulation (error ~6e-8) or the 0.10.2 miscompile (error ~1) exceed it by
orders of magnitude, and a correct float64 implementation can never trip it.
The error is measured relative to ``sum|x_i|``, not ``|sum x_i|``: with
cancellation the latter is not a property any float64 algorithm has.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

U = 2.0**-53  # unit roundoff of IEEE-754 binary64
RTOL = 1e-13


def _enable_x64():
    # jax >= 0.8 (including 0.10.x) has the ``jax.enable_x64`` context manager;
    # older versions only had ``jax.experimental.enable_x64``.
    if hasattr(jax, "enable_x64"):
        return jax.enable_x64(True)
    from jax.experimental import enable_x64  # pragma: no cover

    return enable_x64()  # pragma: no cover


@pytest.fixture(autouse=True)
def _x64():
    """Enable float64 for each test only; global state is restored afterwards."""
    with _enable_x64():
        yield


def _rtol(m: int) -> float:
    return max(RTOL, 2.0 * m * U)


def _assert_matches_fsum(got, terms, *, divide_by: int = 1, what: str = "") -> None:
    """Assert got[i] == fsum(terms[i, :]) / divide_by within the bound in the module doc.

    ``terms`` has the summed axis last; ``got`` has the shape of ``terms[..., 0]``.
    """
    got = np.asarray(got)
    assert got.dtype == np.float64, f"{what}: expected float64 result, got {got.dtype}"
    terms = np.asarray(terms, dtype=np.float64)
    m = terms.shape[-1]
    rows = terms.reshape(-1, m)
    exact = np.array([math.fsum(r) for r in rows]) / divide_by
    scale = np.array([math.fsum(np.abs(r)) for r in rows]) / divide_by
    got = got.reshape(-1)
    assert got.shape == exact.shape, f"{what}: shape {got.shape} != {exact.shape}"
    err = np.abs(got - exact)
    bad = np.flatnonzero(~(err <= _rtol(m) * scale))
    if bad.size:
        i = bad[0]
        rel = err[i] / scale[i] if scale[i] else np.inf
        pytest.fail(
            f"{what}: {bad.size} of {got.size} results wrong (first at flat index {i}: "
            f"got {got[i]!r}, exact {exact[i]!r}, error {rel:.3g} x sum|terms|, "
            f"allowed {_rtol(m):.3g}; jax {jax.__version__})"
        )


def _assert_exact(got, want, what: str) -> None:
    got = np.asarray(got)
    assert got.dtype == np.float64, f"{what}: expected float64 result, got {got.dtype}"
    bad = np.flatnonzero(got != want)
    if bad.size:
        i = bad[0]
        pytest.fail(
            f"{what}: {bad.size} of {got.size} results wrong (first at index {i}: "
            f"got {got[i]!r}, exact {want[i]!r}; jax {jax.__version__})"
        )


def test_installed_jax_is_not_0_10_2():
    assert jax.__version__ != "0.10.2", (
        "jax 0.10.2 is excluded in pyproject.toml: on CPU it miscompiles jitted "
        "dot-followed-by-reduction (e.g. jax.vmap(lambda r: jnp.sum(A @ r))) and "
        "silently returns wrong float64 sums (jax-ml/jax#39103). Use jax/jaxlib 0.10.1."
    )


# --- the 0.10.2 miscompile: dot(A, X^T) fused with a reduction ------------------


def test_upstream_reproducer_vmapped_matvec_sum_of_squares():
    # jax-ml/jax#39103, verbatim in substance: rows (i, 0, 0), identity matrix,
    # so the exact answer is i**2 (exact in float64).  0.10.2 returns
    # 16320**2 instead of 16384**2 for the last row.
    n = 16_385
    i = jnp.arange(n, dtype=jnp.float64)
    x = jnp.stack((i, jnp.zeros_like(i), jnp.zeros_like(i)), axis=1)
    eye = jnp.eye(3, dtype=jnp.float64)
    f = jax.jit(jax.vmap(lambda row: jnp.sum((eye @ row) ** 2)))
    want = np.arange(n, dtype=np.float64) ** 2
    _assert_exact(f(x), want, "jit(vmap(sum((I @ row)**2)))")


_DOT_REDUCE_FORMS = {
    "vmap_sum_matvec": lambda a: jax.vmap(lambda r: jnp.sum(a @ r)),
    "vmap_sum_sq_matvec": lambda a: jax.vmap(lambda r: jnp.sum((a @ r) ** 2)),
    "sum_axis0_a_xT": lambda a: lambda x: jnp.sum(a @ x.T, axis=0),
    "lax_reduce_dot_general": lambda a: (
        lambda x: jax.lax.reduce(
            jax.lax.dot_general(a, x, (((1,), (1,)), ((), ()))), 0.0, jax.lax.add, (0,)
        )
    ),
}


def _exact_dot_reduce(form: str, a: np.ndarray, x: np.ndarray) -> np.ndarray:
    y = x.astype(np.int64) @ a.astype(np.int64).T  # exact integer arithmetic
    if form == "vmap_sum_sq_matvec":
        y = y * y
    return y.sum(axis=1).astype(np.float64)  # < 2**53, so exact


# (p, k, n): A is p x k, X is n x k.  The first group is inside the window in
# which 0.10.2 returns wrong rows (n > 16384, n*k*8 bytes <= ~1 MiB, k not a
# power of two); the rest are controls outside it.
_DOT_REDUCE_CASES = [
    (3, 3, 16_385),
    (3, 3, 20_000),
    (3, 3, 43_520),
    (4, 3, 20_000),
    (3, 5, 16_400),
    (6, 6, 20_000),
    (7, 7, 18_000),
    (3, 3, 1_000),
    (3, 3, 60_000),
    (4, 4, 20_000),
]


@pytest.mark.parametrize("form", sorted(_DOT_REDUCE_FORMS))
@pytest.mark.parametrize("p,k,n", _DOT_REDUCE_CASES, ids=lambda v: str(v))
def test_jit_dot_then_reduce_is_exact_on_integer_data(form, p, k, n):
    rng = np.random.default_rng(1000 * p + 10 * k + n)
    a = rng.integers(-9, 10, size=(p, k)).astype(np.float64)
    x = rng.integers(-999, 1000, size=(n, k)).astype(np.float64)
    got = jax.jit(_DOT_REDUCE_FORMS[form](jnp.asarray(a)))(x)
    _assert_exact(got, _exact_dot_reduce(form, a, x), f"{form} p={p} k={k} n={n}")


@pytest.mark.parametrize("n", [16_385, 20_000, 40_000])
def test_jit_vmapped_matvec_sum_matches_fsum(n):
    # Same pattern with real-valued data and a traced (non-constant) matrix.
    rng = np.random.default_rng(n)
    a = rng.standard_normal((3, 3))
    x = rng.standard_normal((n, 3))
    f = jax.jit(lambda a, x: jax.vmap(lambda r: jnp.sum(a @ r))(x))
    terms = (a[None, :, :] * x[:, None, :]).reshape(n, 9)  # the 9 products per row
    _assert_matches_fsum(f(a, x), terms, what=f"jit(vmap(sum(A @ r))) n={n}")


# --- plain reductions: a spread of sizes, layouts, axes and entry points --------

_SIZES = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 16, 17, 100, 1000, 100_000, 1_000_000]


def _vectors(n: int):
    rng = np.random.default_rng(n)
    yield "normal", rng.standard_normal(n)
    tiny = np.full(n, 1e-10)  # float32 accumulation would drop these entirely
    tiny[0] = 1.0
    yield "one_plus_tiny", tiny
    yield "alternating_1e8_1", np.where(np.arange(n) % 2 == 0, 1e8, 1.0)


@pytest.mark.parametrize("n", _SIZES)
def test_jit_sum_1d_matches_fsum(n):
    jsum = jax.jit(jnp.sum)
    for name, x in _vectors(n):
        _assert_matches_fsum(jsum(x), x, what=f"jit(sum) {name} n={n}")
        if n >= 2:
            s = x[::2]
            _assert_matches_fsum(
                jax.jit(lambda v: jnp.sum(v[::2]))(x), s, what=f"jit(sum(x[::2])) {name} n={n}"
            )


@pytest.mark.parametrize("n", [17, 100_000])
def test_jit_sum_entry_points_match_fsum(n):
    x = np.random.default_rng(n).standard_normal(n)
    ones = np.ones(n)
    cases = {
        "mean*n": (jax.jit(jnp.mean), n),
        "dot(x, 1)": (jax.jit(lambda v: jnp.dot(v, ones)), 1),
        "x @ 1": (jax.jit(lambda v: v @ ones), 1),
        "einsum(i->)": (jax.jit(lambda v: jnp.einsum("i->", v)), 1),
        "cumsum[-1]": (jax.jit(lambda v: jnp.cumsum(v)[-1]), 1),
        "lax.reduce": (jax.jit(lambda v: jax.lax.reduce(v, 0.0, jax.lax.add, (0,))), 1),
    }
    for name, (f, div) in cases.items():
        _assert_matches_fsum(f(x), x, divide_by=div, what=f"{name} n={n}")


@pytest.mark.parametrize("shape", [(17, 5), (5, 17), (100, 100), (16, 17, 3), (20_000, 3)])
def test_jit_sum_along_axes_matches_fsum(shape):
    x = np.random.default_rng(len(shape) * 1000 + shape[0]).standard_normal(shape)
    for axis in [*range(len(shape)), None]:
        terms = x.reshape(-1) if axis is None else np.moveaxis(x, axis, -1)
        m = terms.shape[-1]
        got = jax.jit(lambda v, ax=axis: jnp.sum(v, axis=ax))(x)
        _assert_matches_fsum(got, terms, what=f"jit(sum) shape={shape} axis={axis}")
        got = jax.jit(lambda v, ax=axis: jnp.mean(v, axis=ax))(x)
        _assert_matches_fsum(got, terms, divide_by=m, what=f"jit(mean) shape={shape} axis={axis}")
    # row sums through vmap, and the same reduction as an einsum
    rows = x.reshape(shape[0], -1)
    _assert_matches_fsum(jax.jit(jax.vmap(jnp.sum))(x), rows, what=f"jit(vmap(sum)) {shape}")
    if x.ndim == 2:
        _assert_matches_fsum(
            jax.jit(lambda v: jnp.einsum("ij->i", v))(x), x, what=f"einsum(ij->i) {shape}"
        )
        if shape[0] == shape[1]:
            _assert_matches_fsum(jax.jit(jnp.trace)(x), np.diagonal(x), what=f"jit(trace) {shape}")


def test_float64_sum_is_exact_for_dyadic_data_of_1e6_terms():
    # Multiples of 2**-10 below 2**20 in magnitude: every partial sum of 1e6 of
    # them has < 2**40 * 2**10 = 2**50 ulps, so float64 addition is exact in any
    # order and the result must equal the exact sum bit for bit (float32
    # accumulation could not represent it).
    n = 1_000_000
    rng = np.random.default_rng(7)
    x = rng.integers(-(2**30), 2**30, size=n).astype(np.float64) * 2.0**-10
    want = math.fsum(x)
    got = jax.jit(jnp.sum)(x)
    _assert_exact(np.atleast_1d(got), np.atleast_1d(want), "jit(sum) of 1e6 dyadic values")
    got2 = jax.jit(lambda v: jnp.sum(v.reshape(1000, 1000), axis=0).sum())(x)
    _assert_exact(np.atleast_1d(got2), np.atleast_1d(want), "jit(sum(axis=0).sum()) dyadic")
