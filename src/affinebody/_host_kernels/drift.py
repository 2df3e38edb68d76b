"""Numba kernel of the host drift (:mod:`affinebody.kinetic`): the exact flow of the af-is /
is-af / af-af internal kinetic energies, body by body.

With S = pi phi (left, af-is and af-af) or S = phi pi (right, is-af) and per-body coefficients
(c0, c1, c2) = (h (1/I~ + 1/A~), h / B~, h / I~) of (86):

    X_c = c0 S + c1 Tr(S) Id,   X_r = c2 (S^T - S),   C = expm(X_c),   R = expm(X_r);
    left:  phi -> phi C R,  pi -> R^T C^-1 pi;     right: phi -> R C phi,  pi -> pi C^-1 R^T.

expm is Higham's scaling and squaring (2005, scipy's): for 1-norms above 2.1 exactly the
algorithm of :func:`affinebody._linalg.expm` (Pade [13/13], the same number s of squarings,
(V - U)^-1 (V + U) by Gaussian elimination with the same partial pivoting, then s squarings);
below, the Pade approximant of the lowest degree (3, 5, 7 or 9) that is accurate to unit
roundoff there, 2 to 5 products instead of 6 (a time step's h X is small). Both agree with
the JAX flow to round-off. Bodies are independent: a range
of bodies can run on any thread, the result is the same bit for bit.

``N`` (the dimension) and the Pade constants are module constants written by
:func:`affinebody._host.specialized`; imported directly, the module is the n = 3 version
without a disk cache.
"""

import math

import numba
import numpy as np

# --- constants (written by affinebody._host.specialized)
N = 3
PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
          129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0,
          40840800.0, 960960.0, 16380.0, 182.0, 1.0)
THETA13 = 5.371920351148152
MAX_SQUARINGS = 20
CACHE = False
# --- end of constants

# error_model "numpy": a division by zero gives inf or nan, as in the JAX flow (no exception)
#: Pade [m/m] coefficients of exp for m = 3, 5, 7, 9 (rows, zero-padded) and the 1-norms up to
#: which each is accurate to unit roundoff (Higham 2005, as scipy.linalg.expm)
_PADE_LOW = np.array([
    [120.0, 60.0, 12.0, 1.0, 0, 0, 0, 0, 0, 0],
    [30240.0, 15120.0, 3360.0, 420.0, 30.0, 1.0, 0, 0, 0, 0],
    [17297280.0, 8648640.0, 1995840.0, 277200.0, 25200.0, 1512.0, 56.0, 1.0, 0, 0],
    [17643225600.0, 8821612800.0, 2075673600.0, 302702400.0, 30270240.0, 2162160.0, 110880.0,
     3960.0, 90.0, 1.0]])
_THETA_LOW = (1.495585217958292e-2, 2.539398330063230e-1, 9.504178996162932e-1,
              2.097847961257068e0)

_jit = numba.njit(fastmath=False, boundscheck=False, nogil=True, cache=CACHE, error_model="numpy")
_inline = numba.njit(fastmath=False, boundscheck=False, nogil=True, inline="always",
                     error_model="numpy")


@_inline
def _mul(a, b, out):
    """out = a b (out distinct from a and b)."""
    for r in range(N):
        for c in range(N):
            acc = 0.0
            for k in range(N):
                acc += a[r, k] * b[k, c]
            out[r, c] = acc


@_inline
def _solve(a, b, rows, out):
    """out = a^-1 b (b [N, N]): elimination with partial pivoting on the rows of [a | b] in
    ``rows`` [N, 2N], as ``_linalg._eliminate``, then back substitution."""
    for r in range(N):
        for c in range(N):
            rows[r, c] = a[r, c]
            rows[r, N + c] = b[r, c]
    for col in range(N - 1):
        for i in range(col + 1, N):  # the largest |entry| of the column becomes the pivot
            if abs(rows[i, col]) > abs(rows[col, col]):
                for c in range(2 * N):
                    tmp = rows[col, c]
                    rows[col, c] = rows[i, c]
                    rows[i, c] = tmp
        for i in range(col + 1, N):
            f = rows[i, col] / rows[col, col]
            for c in range(2 * N):
                rows[i, c] = rows[i, c] - f * rows[col, c]
    for i in range(N - 1, -1, -1):
        for c in range(N):
            acc = rows[i, N + c]
            for j in range(i + 1, N):
                acc = acc - rows[i, j] * out[j, c]
            out[i, c] = acc / rows[i, i]


@_jit
def _expm(a, out, work, rows):
    """out = expm(a): for |a|_1 <= 2.1 the Pade [m/m] approximant of the lowest degree
    m in (3, 5, 7, 9) accurate to unit roundoff at that norm (Higham 2005), else Pade [13/13]
    with scaling and squaring exactly as ``_linalg.expm`` (the same number of squarings)."""
    x, x2, x4, x6, t1, t2, u, v = (work[0], work[1], work[2], work[3], work[4], work[5],
                                   work[6], work[7])
    norm = 0.0
    for c in range(N):
        col = 0.0
        for r in range(N):
            col += abs(a[r, c])
        norm = max(norm, col)
    if norm <= _THETA_LOW[3]:
        k = 0
        while norm > _THETA_LOW[k]:
            k += 1
        w = _PADE_LOW[k]
        half = k + 1  # m = 2 half + 1: even powers a^0 .. a^(2 half) in x2, x4, x6, x (a^8)
        _mul(a, a, x2)
        if half >= 2:
            _mul(x2, x2, x4)
        if half >= 3:
            _mul(x4, x2, x6)
        if half >= 4:
            _mul(x6, x2, x)
        for r in range(N):
            for c in range(N):
                odd = w[1] if r == c else 0.0
                even = w[0] if r == c else 0.0
                odd += w[3] * x2[r, c]
                even += w[2] * x2[r, c]
                if half >= 2:
                    odd += w[5] * x4[r, c]
                    even += w[4] * x4[r, c]
                if half >= 3:
                    odd += w[7] * x6[r, c]
                    even += w[6] * x6[r, c]
                if half >= 4:
                    odd += w[9] * x[r, c]
                    even += w[8] * x[r, c]
                t1[r, c] = odd
                v[r, c] = even
        _mul(a, t1, u)
        squarings = 0.0
    else:
        squarings = min(max(math.ceil(math.log2(norm / THETA13)), 0.0), float(MAX_SQUARINGS))
        _pade13(a, squarings, x, x2, x4, x6, t1, t2, u, v)
    for r in range(N):  # r(a) = (V - U)^-1 (V + U), squared s times
        for c in range(N):
            t1[r, c] = v[r, c] - u[r, c]
            t2[r, c] = v[r, c] + u[r, c]
    _solve(t1, t2, rows, out)
    for _ in range(int(squarings)):
        _mul(out, out, t1)
        for r in range(N):
            for c in range(N):
                out[r, c] = t1[r, c]


@_inline
def _pade13(a, squarings, x, x2, x4, x6, t1, t2, u, v):
    """U and V of the Pade [13/13] approximant of exp at a / 2^squarings."""
    scale = 2.0 ** squarings
    for r in range(N):
        for c in range(N):
            x[r, c] = a[r, c] / scale
    w = PADE13
    _mul(x, x, x2)
    _mul(x2, x2, x4)
    _mul(x4, x2, x6)
    for r in range(N):
        for c in range(N):
            t1[r, c] = w[13] * x6[r, c] + w[11] * x4[r, c] + w[9] * x2[r, c]
    _mul(x6, t1, t2)
    for r in range(N):
        for c in range(N):
            t2[r, c] = (t2[r, c] + w[7] * x6[r, c] + w[5] * x4[r, c] + w[3] * x2[r, c]
                        + (w[1] if r == c else 0.0))
    _mul(x, t2, u)
    for r in range(N):
        for c in range(N):
            t1[r, c] = w[12] * x6[r, c] + w[10] * x4[r, c] + w[8] * x2[r, c]
    _mul(x6, t1, v)
    for r in range(N):
        for c in range(N):
            v[r, c] = (v[r, c] + w[6] * x6[r, c] + w[4] * x4[r, c] + w[2] * x2[r, c]
                       + (w[0] if r == c else 0.0))


@_jit
def isotropic_flow(start, stop, left, phi, pi, coefs, phi_out, pi_out):
    """The exact isotropic drift (module docstring) of bodies start..stop-1: phi, pi
    [bodies, N, N], coefs [bodies, 3] = (c0, c1, c2), results into phi_out, pi_out."""
    s = np.empty((N, N))
    xc = np.empty((N, N))
    xr = np.empty((N, N))
    c = np.empty((N, N))
    r = np.empty((N, N))
    m = np.empty((N, N))
    y = np.empty((N, N))
    work = np.empty((8, N, N))  # the expm's scratch matrices
    t1, t2 = np.empty((N, N)), np.empty((N, N))
    rows = np.empty((N, 2 * N))
    for b in range(start, stop):
        if left:
            _mul(pi[b], phi[b], s)
        else:
            _mul(phi[b], pi[b], s)
        tr = 0.0
        for k in range(N):
            tr += s[k, k]
        c0, c1, c2 = coefs[b, 0], coefs[b, 1], coefs[b, 2]
        for i in range(N):
            for j in range(N):
                xc[i, j] = c0 * s[i, j] + (c1 * tr if i == j else 0.0)
                xr[i, j] = c2 * (s[j, i] - s[i, j])
        _expm(xc, c, work, rows)
        _expm(xr, r, work, rows)
        if left:  # phi C R and R^T C^-1 pi
            _mul(phi[b], c, m)
            _mul(m, r, phi_out[b])
            _solve(c, pi[b], rows, y)
            for i in range(N):
                for j in range(N):
                    acc = 0.0
                    for k in range(N):
                        acc += r[k, i] * y[k, j]
                    pi_out[b, i, j] = acc
        else:  # R C phi and (C^-T pi^T)^T R^T
            _mul(r, c, m)
            _mul(m, phi[b], phi_out[b])
            for i in range(N):
                for j in range(N):
                    t1[i, j] = c[j, i]
                    t2[i, j] = pi[b, j, i]
            _solve(t1, t2, rows, y)
            for i in range(N):
                for j in range(N):
                    acc = 0.0
                    for k in range(N):
                        acc += y[k, i] * r[j, k]
                    pi_out[b, i, j] = acc
