"""Determinant, inverse, linear solves and the exponential of small matrices without LAPACK
(n <= 3).

Every configuration phi of this project is an n x n matrix with n <= 3, and so are most
matrices built from it (Gamma = psi^-1 phi (21), the inertia J, Newton blocks of the
constraints). For them ``det``, ``slogdet``, ``inv`` and ``solve`` here use Gaussian
elimination with partial pivoting, unrolled and branch-free (the pivot rows are chosen with
``where``): a = P^T L U, det a = sign(P) prod_i U_ii, and solve / inv by back substitution
(inv(a) = solve(a, Id)).

Why not ``jnp.linalg``: on CPU jaxlib 0.10 runs a batched inverse or solve as LAPACK
getrf/trsm FFI kernels that fan out over the XLA intra-op thread pool (``ParallelBatchMap``)
and block until their sub-tasks finish. When XLA runs two such kernels at once on a pool of
two threads (large vmapped batches: all pairs of 125 bodies in 3D on a 2-core machine), both
threads wait for sub-tasks that no free thread can run: the process deadlocks, idle, forever
(see ``affinebody/_xla.py``). The closed forms are plain elementwise XLA arithmetic, contain no
LAPACK custom call, fuse with their neighbours, and are faster for such tiny matrices.

Accuracy. Partial pivoting is backward stable, so ``det``, ``inv`` and ``solve`` keep the
forward error of LAPACK's pivoted LU, a few cond(a) * eps, also for the states that matter here:
a body sheared along a geodesic of an isochoric motion (det phi = 1, two small singular values)
reaches cond 1e8 and beyond, where the unpivoted cofactor formulas (adj(a) / det(a)) that this
module used before, and that ``jnp.linalg.det`` uses for 2 x 2 and 3 x 3, lose accuracy like
cond(a)^2 * eps: at cond 1e10 the cofactor det of a det-1 matrix came out as 16.8, enough to
flip its sign, which the run driver watches (GL+). tests/test_linalg.py measures this against
exact rational arithmetic. The elimination costs about 2x (n = 2) to 5x (n = 3) the cofactor
formulas per matrix, tens of nanoseconds, once per body per force evaluation.

All functions act on the last two axes, broadcast over leading (batch) axes, are jit-, vmap- and
grad-safe (polynomials and one division), and keep the input's precision (float64 in this
project). For n > 3 they fall back to ``jnp.linalg``.
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp

CLOSED_FORM_MAX_N = 3


def _compiled(f):
    """``f`` compiled as one program per input shape and dtype (``jax.jit``).

    Called on concrete arrays (set-up code, checks, tests) the unrolled elimination would
    otherwise run op by op, each of its dozens of operations compiled and dispatched on its
    own; inside a traced function the call is inlined as before. Arguments become arrays
    first, so lists and NumPy arrays are accepted as they were."""
    jitted = jax.jit(f)

    @functools.wraps(f)
    def call(*arrays):
        return jitted(*(jnp.asarray(x) for x in arrays))

    return call


def fused_products() -> bool:
    """Whether :func:`matmul` writes tiny products as elementwise arithmetic: on a GPU, where a
    batched dot of 3 x 3 blocks is a library call of its own (measured on an H100, 10^6 bodies:
    1.24 ms per product against 0.31 ms fused, and 10 chained products 12.8 ms against
    1.3 ms); on a CPU XLA's batched dot is the faster (and keeps earlier results bit for bit)."""
    return jax.default_backend() != "cpu"


def matmul(a: jax.Array, b: jax.Array) -> jax.Array:
    """a @ b over the last two axes, broadcast over leading ones; for n <= 3 on a GPU
    (:func:`fused_products`) as sum_k a[..., i, k] b[..., k, j], which XLA fuses with its
    neighbours."""
    if fused_products() and a.shape[-1] <= CLOSED_FORM_MAX_N:
        return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)
    return a @ b


# --------------------------------------------------------------------------------------------
# Tiny matrices as entries: an n x m matrix as a list of n rows of m arrays [...] (one number
# per body or pair), every operation on them elementwise. The Triton pair kernels
# (``affinebody._pair_triton``) compute on blocks of pairs this way, and :func:`expm` on a GPU.


def entries(a: jax.Array) -> list:
    """The entries of a [..., n, m] as a list of rows of arrays [...]."""
    return [[a[..., i, j] for j in range(a.shape[-1])] for i in range(a.shape[-2])]


def from_entries(rows: list) -> jax.Array:
    """The matrix [..., n, m] of entries (rows of arrays [...])."""
    return jnp.stack([jnp.stack(row, -1) for row in rows], -2)


def entries_sum(terms):
    """The sum of ``terms`` (a non-empty iterable), left to right."""
    return functools.reduce(operator.add, terms)


def entries_matmul(a: list, b: list) -> list:
    """a b of entries (a n x k, b k x m)."""
    return [[entries_sum(a[i][k] * b[k][j] for k in range(len(b))) for j in range(len(b[0]))]
            for i in range(len(a))]


def entries_transpose(a: list) -> list:
    """a^T of entries."""
    return [list(row) for row in zip(*a, strict=True)]


def entries_combination(terms, identity=None) -> list:
    """sum_t c_t M_t (+ ``identity`` Id) of entries: ``terms`` [(c_t, M_t)] with scalar or
    array [...] coefficients c_t."""
    n, m = len(terms[0][1]), len(terms[0][1][0])
    out = [[entries_sum(c * mat[i][j] for c, mat in terms) for j in range(m)] for i in range(n)]
    if identity is not None:
        for i in range(n):
            out[i][i] = out[i][i] + identity
    return out


def entries_solve(a: list, b: list) -> list:
    """x of entries with a x = b (a n x n, b n x k): the Gaussian elimination with partial
    pivoting of :func:`_eliminate` (``where`` selects), then back substitution."""
    n = len(a)
    rows = [list(a[i]) + list(b[i]) for i in range(n)]
    for col in range(n - 1):
        for i in range(col + 1, n):  # the largest |entry| of the column becomes the pivot
            swap = jnp.abs(rows[i][col]) > jnp.abs(rows[col][col])
            pairs = list(zip(rows[i], rows[col], strict=True))
            rows[col] = [jnp.where(swap, p, q) for p, q in pairs]
            rows[i] = [jnp.where(swap, q, p) for p, q in pairs]
        for i in range(col + 1, n):
            factor = rows[i][col] / rows[col][col]
            rows[i] = [r - factor * p for r, p in zip(rows[i], rows[col], strict=True)]
    x: list = [None] * n
    for i in reversed(range(n)):
        r = rows[i][n:]
        for j in range(i + 1, n):
            r = [v - rows[i][j] * w for v, w in zip(r, x[j], strict=True)]
        x[i] = [v / rows[i][i] for v in r]
    return x


def _square(a, name: str = "a") -> jax.Array:
    a = jnp.asarray(a)
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise ValueError(f"{name} must be a square matrix [..., n, n] (got shape {a.shape})")
    if not jnp.issubdtype(a.dtype, jnp.inexact):
        a = a.astype(jnp.result_type(a, 0.0))
    return a


def _eliminate(a: jax.Array, b: jax.Array | None):
    """Gaussian elimination with partial pivoting on the rows of [a | b] (b [..., n, k] or
    None), n <= 3, unrolled; the row exchanges are ``where`` selects, so it is branch-free and
    differentiable. Returns (the rows of [U | L^-1 P b], the sign of the permutation)."""
    n = a.shape[-1]
    batch = a.shape[:-2] if b is None else jnp.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    rows = [jnp.broadcast_to(a[..., i, :], batch + (n,)) for i in range(n)]
    if b is not None:
        k = b.shape[-1]
        rows = [jnp.concatenate([r, jnp.broadcast_to(b[..., i, :], batch + (k,))], -1)
                for i, r in enumerate(rows)]
    sign = jnp.ones(batch, dtype=a.dtype)
    for col in range(n - 1):
        for i in range(col + 1, n):  # the largest |entry| of the column becomes the pivot
            swap = jnp.abs(rows[i][..., col]) > jnp.abs(rows[col][..., col])
            rows[col], rows[i] = (jnp.where(swap[..., None], rows[i], rows[col]),
                                  jnp.where(swap[..., None], rows[col], rows[i]))
            sign = jnp.where(swap, -sign, sign)
        for i in range(col + 1, n):
            rows[i] = rows[i] - (rows[i][..., col] / rows[col][..., col])[..., None] * rows[col]
    return rows, sign


def _pivoted_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """x [..., n, k] with a x = b for a [..., n, n], b [..., n, k] (leading axes broadcast),
    n <= 3: :func:`_eliminate`, then back substitution."""
    n = a.shape[-1]
    rows, _ = _eliminate(a, b)
    x: list = [None] * n
    for i in reversed(range(n)):
        r = rows[i][..., n:]
        for j in range(i + 1, n):
            r = r - rows[i][..., j:j + 1] * x[j]
        x[i] = r / rows[i][..., i:i + 1]
    return jnp.stack(x, -2)


@_compiled
def det(a) -> jax.Array:
    """det(a) [...] of a [..., n, n]: the product of the pivots of :func:`_eliminate` and the
    sign of its row permutation (n <= 3), accurate to a few cond(a) * eps."""
    a = _square(a)
    n = a.shape[-1]
    if n > CLOSED_FORM_MAX_N:
        return jnp.linalg.det(a)
    if n == 1:
        return a[..., 0, 0]
    rows, sign = _eliminate(a, None)
    out = sign
    for i in range(n):
        out = out * rows[i][..., i]
    return out


@_compiled
def slogdet(a) -> tuple[jax.Array, jax.Array]:
    """(sign, log|det a|) of a [..., n, n], as ``jnp.linalg.slogdet`` (sign 0, log -inf when
    det a = 0)."""
    a = _square(a)
    if a.shape[-1] > CLOSED_FORM_MAX_N:
        sign, logabsdet = jnp.linalg.slogdet(a)
        return sign, logabsdet
    d = det(a)
    return jnp.sign(d), jnp.log(jnp.abs(d))


@_compiled
def inv(a) -> jax.Array:
    """a^-1 [..., n, n] of a [..., n, n] (pivoted elimination against Id for n <= 3)."""
    a = _square(a)
    n = a.shape[-1]
    if n > CLOSED_FORM_MAX_N:
        return jnp.linalg.inv(a)
    if n == 1:
        return 1.0 / a
    return _pivoted_solve(a, jnp.eye(n, dtype=a.dtype))


@_compiled
def solve(a, b) -> jax.Array:
    """x with a x = b, as ``jnp.linalg.solve``: a [..., n, n]; b a vector [n] (x [..., n]) or a
    stack of matrices [..., n, k] (x [..., n, k]), leading axes broadcast against a's. Solve a
    stack of vectors as ``solve(a, b[..., None])[..., 0]``."""
    a = _square(a)
    b = jnp.asarray(b)
    n = a.shape[-1]
    vector = b.ndim == 1
    if (b.shape[0] if vector else b.shape[-2] if b.ndim >= 2 else -1) != n:
        raise ValueError(f"solve: b must have shape [{n}] or [..., {n}, k] for a of shape "
                         f"{a.shape} (got {b.shape}); for a stack of vectors use "
                         f"solve(a, b[..., None])[..., 0]")
    dtype = jnp.result_type(a, b, 0.0)
    a, b = a.astype(dtype), b.astype(dtype)
    if n > CLOSED_FORM_MAX_N:
        return _lapack_solve(a, b)
    if vector:
        return _pivoted_solve(a, b[:, None])[..., 0]
    return _pivoted_solve(a, b)


def _lapack_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """jnp.linalg.solve, with one factorisation (no batch) when a has no leading axes: the
    right-hand sides of every batch entry become columns of one [n, K] system."""
    if a.ndim > 2 or b.ndim <= 2:
        return jnp.linalg.solve(a, b)
    n, k = b.shape[-2], b.shape[-1]
    columns = jnp.moveaxis(b, -2, 0).reshape(n, -1)  # [n, batch * k]
    x = jnp.linalg.solve(a, columns).reshape((n,) + b.shape[:-2] + (k,))
    return jnp.moveaxis(x, 0, -2)


def inverse_cholesky_factor(k) -> jax.Array:
    """F [..., d, d], upper triangular, with F F^T = k^-1 for symmetric positive definite
    k [..., d, d] (any small d: the thermostats' d = n^2 <= 9), NaN where k is not positive
    definite; without LAPACK.

    k = L L^T (Cholesky, column by column, unrolled), then F = L^-T (forward substitution
    against Id, row by row): F F^T = L^-T L^-1 = (L L^T)^-1. Of k only the lower triangle is
    read. Why not ``jnp.linalg.eigh`` or ``cholesky``: each is a batched LAPACK kernel, and two
    of them ready at once in one program deadlock XLA's CPU pool of two threads (module
    docstring); an ordering between them in the jaxpr (an optimisation barrier) does not
    survive compilation. Backward stable like LAPACK's potrf; d^3/3 operations per matrix."""
    k = _square(jnp.asarray(k), "k")
    d = k.shape[-1]
    index = jnp.arange(d)
    columns: list = []  # L[..., :, j]
    for j in range(d):
        v = k[..., :, j]
        for c in columns:
            v = v - c * c[..., j:j + 1]
        pivot = v[..., j]
        root = jnp.sqrt(jnp.where(pivot > 0, pivot, jnp.nan))
        columns.append(jnp.where(index >= j, v / root[..., None], 0.0))
    lower = jnp.stack(columns, -1)
    eye = jnp.eye(d, dtype=k.dtype)
    rows: list = []  # rows of L^-1
    for i in range(d):
        r = eye[i] + jnp.zeros_like(lower[..., i, :])
        for m, row in enumerate(rows):
            r = r - lower[..., i, m:m + 1] * row
        rows.append(r / lower[..., i, i:i + 1])
    return jnp.swapaxes(jnp.stack(rows, -2), -1, -2)


#: Pade [13/13] coefficients of exp (Higham 2005, "The scaling and squaring method for the matrix
#: exponential revisited"); THETA13: the 1-norm up to which it is accurate to unit roundoff
#: (also the constants of the host kernel ``_host_kernels/drift.py``).
PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
           129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
           40840800.0, 960960.0, 16380.0, 182.0, 1.0)
THETA13 = 5.371920351148152
#: squarings available: norms up to THETA13 * 2**MAX_SQUARINGS (~5.6e6 for 20)
MAX_SQUARINGS = 20


@_compiled
def expm(a) -> jax.Array:
    """Matrix exponential, batched, without LAPACK for n <= 3 (for n > 3:
    ``jax.scipy.linalg.expm``).

    Scaling and squaring with the Pade [13/13] approximant: s = ceil(log2(|a|_1 / theta_13))
    (at least 0), r13(a / 2^s) = (V - U)^-1 (V + U) solved in closed form (V - U is well
    conditioned for |a / 2^s|_1 <= theta_13), then squared s times -- as a fixed number of
    masked squarings, so the function stays reverse-differentiable under jit and vmap. The
    same algorithm as scipy's and jax's expm (tests/test_linalg.py: at least as close to
    scipy's as jax's own, which solves the Pade system with LAPACK).
    """
    a = _square(a)
    n = a.shape[-1]
    if n > CLOSED_FORM_MAX_N:
        return jax.scipy.linalg.expm(a)
    if fused_products():
        return from_entries(_entries_expm(entries(a)))
    norm = jnp.max(jnp.sum(jnp.abs(a), axis=-2), axis=-1)  # 1-norm, [...]
    ratio = jnp.where(norm > 0, norm / THETA13, 1.0)
    s = jnp.clip(jnp.ceil(jnp.log2(ratio)), 0, MAX_SQUARINGS)
    x = a / (2.0**s)[..., None, None]
    eye = jnp.broadcast_to(jnp.eye(n, dtype=a.dtype), a.shape)
    b = PADE13
    mm = matmul
    x2 = mm(x, x)
    x4 = mm(x2, x2)
    x6 = mm(x4, x2)
    u = mm(x, mm(x6, b[13] * x6 + b[11] * x4 + b[9] * x2) + b[7] * x6 + b[5] * x4 + b[3] * x2
           + b[1] * eye)
    v = mm(x6, b[12] * x6 + b[10] * x4 + b[8] * x2) + b[6] * x6 + b[4] * x4 + b[2] * x2 + b[0] * eye
    r = solve(v - u, v + u)

    def square(i, m):
        return jnp.where((i < s)[..., None, None], mm(m, m), m)
    return jax.lax.fori_loop(0, MAX_SQUARINGS, square, r)


def _entries_expm(a: list) -> list:
    """:func:`expm` of entries, the same algorithm, for a GPU: each product there, written as
    a sum over an axis, is a reduction that ends XLA's fusion, so the unrolled form ran every
    product and masked squaring as a kernel of its own over the batch (the af-is drift: two
    exponentials a step). Entry by entry, the Pade step is elementwise arithmetic that XLA
    fuses, and the squarings are a loop whose body is one fused squaring; not unrolled, as
    XLA recomputes every entry at each of its uses through a fused chain of products (on a
    CPU, 8 unrolled squarings took 51 s to compile, 12 more than 8 GB). Forced on one CPU
    core at 10^5 matrices (an indication only: a CPU runs the batched dots): 84 ms against
    524 ms for the unrolled form (docs/performance.md, "Running on an NVIDIA GPU")."""
    n = len(a)
    norm = functools.reduce(jnp.maximum, [entries_sum(jnp.abs(a[i][j]) for i in range(n))
                                          for j in range(n)])  # 1-norm, [...]
    ratio = jnp.where(norm > 0, norm / THETA13, 1.0)
    s = jnp.clip(jnp.ceil(jnp.log2(ratio)), 0, MAX_SQUARINGS)
    x = [[v / 2.0**s for v in row] for row in a]
    b = PADE13
    mm = entries_matmul
    x2 = mm(x, x)
    x4 = mm(x2, x2)
    x6 = mm(x4, x2)
    u = mm(x, entries_combination([(1.0, mm(x6, entries_combination(
        [(b[13], x6), (b[11], x4), (b[9], x2)]))), (b[7], x6), (b[5], x4), (b[3], x2)], b[1]))
    v = entries_combination([(1.0, mm(x6, entries_combination(
        [(b[12], x6), (b[10], x4), (b[8], x2)]))), (b[6], x6), (b[4], x4), (b[2], x2)], b[0])
    r = entries_solve(entries_combination([(1.0, v), (-1.0, u)]),
                      entries_combination([(1.0, v), (1.0, u)]))

    def square(i, m):
        squared = mm(m, m)
        return [[jnp.where(i < s, p, q) for p, q in zip(row_p, row_q, strict=True)]
                for row_p, row_q in zip(squared, m, strict=True)]
    return jax.lax.fori_loop(0, MAX_SQUARINGS, square, r)
