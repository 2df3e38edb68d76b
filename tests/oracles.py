"""Test oracles: independent solvers the reduced quantum spectra are checked against, and the
d'Alembert oscillator (whose spectrum and densities are known in closed form) as a config file.

Not library code: they exist only to test :mod:`affinebody.quantum` (and its benchmarks).
"""

from __future__ import annotations

from math import comb

import numpy as np
from scipy import linalg
from scipy.sparse.linalg import LinearOperator, eigsh

from affinebody.quantum.bases import Hermite1D
from affinebody.quantum.levels import Potential


def oscillator_config(hbar: float, inertia: float, k: float, extra: str) -> str:
    """The n = 2 d'Alembert oscillator V = (k/2) Tr G as the text of a config file, with the
    lines ``extra`` ("key = value") added to its [quantum] table."""
    return (f'[system]\nn = 2\n[quantum]\nhbar = {hbar}\nkinetic = "dalembert"\n'
            f'inertia = {inertia}\npotential = "0.5*{k}*trG"\n{extra}\n')


def cartesian_phi(abcd: np.ndarray) -> np.ndarray:
    """phi = [[a + c, d - b], [b + d, a - c]]: conformal (a, b) plus anticonformal (c, d) part."""
    a, b, c, d = np.moveaxis(abcd, -1, 0)
    return np.stack([np.stack([a + c, d - b], -1), np.stack([b + d, a - c], -1)], -2)


def signed_singular_values(phi: np.ndarray) -> np.ndarray:
    """Q of phi by SVD, descending, the last carrying the sign of det phi."""
    s = np.linalg.svd(phi, compute_uv=False)
    sign = np.sign(np.linalg.det(phi))
    s[..., -1] *= np.where(sign == 0, 1.0, sign)
    return s


def cartesian_n2_levels(potential: Potential, hbar: float, inertia: float, count: int, *,
                        size: int = 24, scale: float = 1.0, quad: int | None = None,
                        per_sector: int = 8, tol: float = 1e-13) -> np.ndarray:
    """Lowest ``count`` eigenvalues (with multiplicity) of H = -(hbar^2/2I) Lap_phi + V(phi)
    on R^4 = L(2, R), J = inertia * Id, by a Hermite product Galerkin method.

    Independent of the two-polar reduction: coordinates (a, b, c, d) of :func:`cartesian_phi`
    (T = I |(a', b', c', d')|^2), V evaluated on the full matrix phi through an SVD, Hermite
    functions of length ``scale`` in each coordinate, V by Gauss-Hermite quadrature, matrix-free
    Lanczos. If V is even in each coordinate (checked numerically on the grid), the 16 parity
    classes are solved separately, which leaves no degeneracy for Lanczos to drop.
    """
    quad = quad or size + 12
    quad += quad % 2
    herm = Hermite1D(size, scale, 0.0, quad)
    x, B = herm.nodes()
    lap = (hbar**2 / (4 * inertia)) * herm.laplacian()
    grid = np.stack(np.meshgrid(x, x, x, x, indexing="ij"), -1)
    V = np.asarray(potential(signed_singular_values(cartesian_phi(grid))), float)
    flips = [np.flip(V, axis=ax) for ax in range(4)]
    even = all(np.allclose(f, V, rtol=1e-11, atol=1e-11 * np.max(np.abs(V))) for f in flips)
    if even:
        half = x > 0
        xh = x[half]
        del xh
        classes = [tuple((p >> i) & 1 for i in range(4)) for p in range(16)]
        Vh = V[np.ix_(half, half, half, half)] * 16  # even integrand: 2 per axis
        Bs = {p: B[half][:, p::2] for p in (0, 1)}
        laps = {p: lap[p::2, p::2] for p in (0, 1)}
        Vgrid = Vh
    else:
        classes = [None]
        Bs, laps, Vgrid = {None: B}, {None: lap}, V
    values = []
    for cls in classes:
        Bax = [Bs[c] for c in (cls or (None,) * 4)]
        Lax = [laps[c] for c in (cls or (None,) * 4)]
        dims = tuple(b.shape[1] for b in Bax)
        dim = int(np.prod(dims))

        def matvec(v, Bax=Bax, Lax=Lax, dims=dims):
            c = v.reshape(dims)
            g = c
            for ax in range(4):
                g = np.moveaxis(np.tensordot(Bax[ax], g, axes=([1], [ax])), 0, ax)
            g = g * Vgrid
            for ax in range(4):
                g = np.moveaxis(np.tensordot(Bax[ax].T, g, axes=([1], [ax])), 0, ax)
            for ax in range(4):
                g = g + np.moveaxis(np.tensordot(Lax[ax], c, axes=([1], [ax])), 0, ax)
            return g.ravel()

        op = LinearOperator((dim, dim), matvec=matvec, dtype=float)
        k = min(per_sector if cls is not None else count + 4, dim - 2)
        w = eigsh(op, k=k, which="SA", tol=tol, return_eigenvectors=False)
        values.extend(np.sort(w))
    return np.sort(np.array(values))[:count]


def r9_radial_levels(V, ell: int, count: int, h: float = 0.1, R: float = 10.0) -> np.ndarray:
    """Lowest ``count`` levels of -chi''/2 + [(l+3)(l+4)/(2 r^2) + V(r)] chi = E chi, the R^9
    radial equation for the hyperspherical harmonics of degree l (chi = r^4 u; hbar = J = 1),
    by a sinc DVR on (0, R) with step h (the odd extension: chi(0) = 0). Independent of the
    two-polar reduction."""
    i = np.arange(1, int(R / h) + 1)
    d = i[:, None] - i[None, :]
    T = np.where(d == 0, np.pi**2 / 3 - 1 / (2 * i[:, None] ** 2),
                 2.0 * (-1.0) ** d * (1 / np.where(d == 0, 1, d) ** 2
                                      - 1 / (i[:, None] + i[None, :]) ** 2))
    r = h * i
    H = T / (2 * h * h) + np.diag((ell + 3) * (ell + 4) / (2 * r**2) + V(r))
    return linalg.eigvalsh(H, subset_by_index=[0, count - 1])


def r9_radial_states(V, count: int, h: float = 0.02, R: float = 10.0, max_degree: int = 8,
                     per_degree: int = 6) -> np.ndarray:
    """The lowest ``count`` states of -Lap/2 + V(|x|) on R^9 with multiplicity: each radial
    level of degree l counted dim H_l = C(l+8, 8) - C(l+6, 8) times."""
    states = []
    for ell in range(max_degree + 1):
        dim = comb(ell + 8, 8) - (comb(ell + 6, 8) if ell >= 2 else 0)
        states += [e for e in r9_radial_levels(V, ell, per_degree, h, R) for _ in range(dim)]
    return np.sort(states)[:count]
