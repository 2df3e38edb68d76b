"""Thermal equilibrium of one quantum affine body and its classical limit (paper, last section;
docs/theory/two-polar.md): the partition functions Z(beta) of af-is (74) / is-af (73) on GL+(2).

Quantum: Z_q(beta) = Tr exp(-beta H) = sum over all states of exp(-beta E), summed over every
SO(2) x SO(2) sector (s, k), s + k even, of the two-polar reduction (the reduced operator of
:mod:`affinebody.quantum.spectra`'s module docstring). For a potential V(q) = V_x(q1 - q2) +
V_sigma(q1 + q2) the dilatation sigma = ln det phi separates, so Z_q = Z_sigma * sum_{s,k}
Z_x(s, k): one 1D radial problem per sector and one Hermite problem for sigma
(:func:`partition_function_affine2`).

Classical: Z_cl(beta) = (2 pi hbar)^-4 int exp(-beta H) dphi dpi. The momentum integral is
Gaussian and leaves (2 pi / beta)^2 sqrt(det K(phi)) = (2 pi / beta)^2 sqrt(det k) |det phi|^-2,
i.e. the Haar measure (91) of the affine models (:func:`affine_metric_determinant`), so Z_cl is
a two-dimensional integral over the deformation invariants q
(:func:`classical_partition_function_affine2`).

The classical limit: Z_q / Z_cl -> 1 as hbar -> 0 at fixed beta, with Z_q / Z_cl - 1 = O(hbar^2)
(the Wigner-Kirkwood order; checked in the tests together with the af-is / is-af symmetry
phi -> phi^T). af-af (72) has an indefinite kinetic energy: neither Z exists (ValueError).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import linalg

from affinebody.quantum.bases import Hermite1D, Radial2D, inv_x2_minus_inv_sinh2
from affinebody.quantum.levels import AffineInertia, Potential


def affine_metric_determinant(model: str, n: int, I: float, A: float,  # noqa: E741
                              B: float) -> float:
    """det k of the kinetic metric T = 1/2 k(Omega, Omega) of (73) is-af / (74) af-is on gl(n) in
    Frobenius-orthonormal coordinates (Omega = Omega_hat or Omega): k acts as I + A on the
    symmetric traceless, I - A on the skew and I + A + n B on the pure-trace velocities
    (docs/theory/conventions.md), so
    det k = (I + A)^{n(n+1)/2 - 1} (I - A)^{n(n-1)/2} (I + A + n B).

    In the coordinates phi the metric is K(phi) = k o (phi^-1 x Id) with det K = det k
    |det phi|^{-2n}: sqrt(det K) is the Haar density |det phi|^-n of (91) times sqrt(det k).
    af-af (72) is indefinite: no classical partition function (ValueError).
    """
    if model not in ("af-is", "is-af"):
        raise ValueError(f"model must be 'af-is' or 'is-af' for a positive definite metric "
                         f"(got {model!r}; af-af (72) is indefinite)")
    if not (I > abs(A) and I + A + n * B > 0):
        raise ValueError(f"I > |A| and I + A + n B > 0 required (got I={I}, A={A}, B={B}, n={n})")
    return float((I + A) ** (n * (n + 1) // 2 - 1) * (I - A) ** (n * (n - 1) // 2)
                 * (I + A + n * B))


def _log_sinh_weight(x: np.ndarray) -> np.ndarray:
    """log sinh x for x > 0 without overflow."""
    return x + np.log1p(-np.exp(-2 * x)) - math.log(2.0)


def classical_partition_function_affine2(model: str, potential: Potential, hbar: float,
                                         beta: float, *, I: float, A: float,  # noqa: E741
                                         B: float, points: int = 400) -> float:
    """Z_cl(beta) = (2 pi hbar)^-4 int_{GL+(2) x R^4} exp(-beta H) dphi dpi for (73) / (74).

    The Gaussian momentum integral gives (2 pi / beta)^2 sqrt(det K(phi)) =
    (2 pi / beta)^2 sqrt(det k) |det phi|^-2 (:func:`affine_metric_determinant`), i.e. the Haar
    measure (91). In two-polar coordinates phi = L(alpha) diag(e^q) R(beta)^T the Haar measure
    is 2 sinh(q1 - q2) dq dalpha dbeta, and the map is 2-to-1 ((-L, q, -R) is the same phi: the
    quantum states need m + k even), so for V = V(q)
        int_{GL+(2)} f dHaar = (2 pi)^2 int_{q1 > q2} sinh(q1 - q2) f(q) dq.
    The q-integral is done in x = q1 - q2 > 0, sigma = q1 + q2 (dq = dx dsigma / 2) by
    Gauss-Legendre on the box where the integrand exceeds e^-45 of its maximum.
    ``potential`` takes the singular values Q = e^q [..., 2], as everywhere in spectra.py.
    """
    detk = affine_metric_determinant(model, 2, I, A, B)

    def log_integrand(x, s):
        q = np.stack([(s + x) / 2, (s - x) / 2], axis=-1)
        with np.errstate(over="ignore", invalid="ignore"):
            V = np.asarray(potential(np.exp(q)), float)
        return np.where(np.isfinite(V), _log_sinh_weight(x) - beta * V, -np.inf)

    xs = np.linspace(1e-6, 60, 1201)
    ss = np.linspace(-60, 60, 2401)
    X, S = np.meshgrid(xs, ss, indexing="ij")
    logf = log_integrand(X, S)
    top = np.max(logf)
    if not np.isfinite(top):
        raise ValueError("the potential gives no finite Boltzmann weight on the grid")
    inside = logf > top - 45
    if inside[-1, :].any() or inside[:, 0].any() or inside[:, -1].any():
        raise ValueError("potential is not confining enough for Z_cl on |q| < 60")
    xi = np.nonzero(inside.any(axis=1))[0]
    si = np.nonzero(inside.any(axis=0))[0]
    x_hi = xs[min(xi[-1] + 2, len(xs) - 1)]
    s_lo, s_hi = ss[max(si[0] - 2, 0)], ss[min(si[-1] + 2, len(ss) - 1)]
    gx, wx = np.polynomial.legendre.leggauss(points)
    x = x_hi * (gx + 1) / 2
    s = s_lo + (s_hi - s_lo) * (gx + 1) / 2
    Xg, Sg = np.meshgrid(x, s, indexing="ij")
    vals = np.exp(log_integrand(Xg, Sg) - top)
    integral = np.einsum("i,ij,j->", wx * x_hi / 2, vals, wx * (s_hi - s_lo) / 2) / 2
    config = (2 * math.pi) ** 2 * integral * math.exp(top)
    return float((2 * math.pi * hbar) ** -4 * (2 * math.pi / beta) ** 2 * math.sqrt(detk)
                 * config)


@dataclass(frozen=True)
class PartitionFunction:
    """Z(beta) = sum over all states of exp(-beta E), with its error estimate and extent."""

    value: float
    error: float
    sectors: int  # (s, k) sectors summed (each pair (s, k) ~ (-s, -k) counted once)
    max_spin: int  # largest |s| reached
    max_vorticity: int


def _boltzmann_sum(E: np.ndarray, beta: float, shift: float) -> float:
    return float(np.sum(np.exp(-beta * (E - shift))))


def _radial_sector_sums(model: str, potential_x: Callable[[np.ndarray], np.ndarray], hbar: float,
                        beta: float, inertia: AffineInertia, size: int, scale: float,
                        shift: float, tol: float) -> tuple[float, int, int, int]:
    """sum over sectors (s, k), s + k even, of sum_j exp(-beta (E_skj - shift)) for the x-part
    H_x = -(hbar^2/M)(1/sinh x) d sinh x d + U_sk(x) + V_x(x) (reduced af-is / is-af,
    :mod:`affinebody.quantum.spectra`). Sectors are walked by mu = (s + k)/2 >= 0
    (centrifugal order |mu|) and d = (s - k)/2, outward from the peak of each row, until a
    whole row adds less than tol of the sum."""
    M = inertia.M
    total, count, max_s, max_k = 0.0, 0, 0, 0
    mu = 0
    while True:
        f = Radial2D(mu, size, scale, size + 30)
        x, Bx = f.nodes()
        W = 0.25 + 0.25 * inv_x2_minus_inv_sinh2(x)
        centrifugal = mu * mu * (1 / (4 * np.sinh(x / 2) ** 2) - 1 / x**2)
        base = Bx.T @ (((hbar**2 / M) * (W + centrifugal) + potential_x(x))[:, None] * Bx)
        base += (hbar**2 / M) * f.laplacian()
        well = Bx.T @ ((hbar**2 / (4 * M * np.cosh(x / 2) ** 2))[:, None] * Bx)
        row = 0.0
        # the rotational term is smallest at k = 0 (af-is) / s = 0 (is-af): walk out from there
        peak = 0 if mu == 0 else (mu if model == "af-is" else -mu)
        for direction in (1, -1) if mu > 0 else (1,):
            d = peak if direction == 1 else peak - 1
            previous = np.inf
            while True:
                s, k = mu + d, mu - d
                rot = (k * k if model == "af-is" else s * s) * inertia.inv_I_tilde * hbar**2 / 2
                H = base - d * d * well + rot * np.eye(size)
                E = linalg.eigvalsh(0.5 * (H + H.T))
                mult = 1 if (mu == 0 and d == 0) else 2
                z = mult * _boltzmann_sum(E, beta, shift)
                row += z
                count += 1
                max_s, max_k = max(max_s, abs(s)), max(max_k, abs(k))
                if z < 1e-2 * tol * (total + row) and z <= previous:
                    break  # past the peak and negligible: the rest decreases
                previous = z
                d += direction
        total += row
        if row < 1e-2 * tol * total:
            break
        mu += 1
    return total, count, max_s, max_k


def partition_function_affine2(model: str, potential_x: Callable[[np.ndarray], np.ndarray],
                               potential_sigma: Callable[[np.ndarray], np.ndarray], hbar: float,
                               beta: float, *, I: float, A: float, B: float,  # noqa: E741
                               size: int = 40, scale: float | None = None,
                               scale_sigma: float | None = None, tol: float = 1e-10,
                               check: bool = True) -> PartitionFunction:
    """Quantum Z(beta) = Tr exp(-beta H) of af-is (74) / is-af (73) on GL+(2) for a potential
    V(q) = V_x(q1 - q2) + V_sigma(q1 + q2), summed over *all* (s, k) sectors, s + k even.

    For such V the dilatation sigma = ln det phi separates (H = H_x + H_sigma, the reduced
    operator of :mod:`affinebody.quantum.spectra`), so Z = Z_sigma * sum_{s,k} Z_x(s, k):
    one 1D problem per sector (2D-radial Laguerre basis conjugated by sqrt(x / sinh x), as in
    :func:`~affinebody.quantum.n2.haar2_block`) and one Hermite problem for sigma.
    Energies are measured from the minimum of V (no shift of Z). ``error`` (if ``check``) is
    the larger change of Z under a basis 10 smaller and a scale 1.2 times wider; scales default
    to the harmonic lengths at the minima of V_x (x = 0) and V_sigma.
    """
    if model not in ("af-is", "is-af"):
        raise ValueError(f"model must be 'af-is' or 'is-af' (got {model!r}; the af-af sector "
                         "sum is unbounded below)")
    affine_metric_determinant(model, 2, I, A, B)  # validates the region
    inertia = AffineInertia(model, I, A, B)
    M, dil = inertia.M, inertia.dilatation
    sig = np.linspace(-30, 30, 6001)
    Vs = np.asarray(potential_sigma(sig), float)
    centre = float(sig[np.argmin(Vs)])
    h = 1e-3
    curv_x = float((potential_x(np.array([2 * h]))[0] - potential_x(np.array([0.0]))[0])
                   / (2 * h * h))  # V_x = c x^2 + ...: V(2h) - V(0) = 4 c h^2
    curv_s = float((potential_sigma(np.array([centre + h]))[0] - 2 * np.min(Vs)
                    + potential_sigma(np.array([centre - h]))[0]) / (2 * h * h))
    if scale is None:
        scale = (hbar**2 / (M * max(curv_x, 1e-3))) ** 0.25
    if scale_sigma is None:
        scale_sigma = (hbar**2 / (dil * max(curv_s, 1e-3))) ** 0.25
    shift = float(min(np.min(Vs), 0.0) + potential_x(np.array([0.0]))[0])

    def evaluate(size_, scale_, scale_sigma_):
        hs = Hermite1D(size_, scale_sigma_, centre, size_ + 30)
        s_nodes, Bs = hs.nodes()
        Hs = Bs.T @ (np.asarray(potential_sigma(s_nodes), float)[:, None] * Bs)
        Hs += (hbar**2 / dil) * hs.laplacian()
        z_sigma = _boltzmann_sum(linalg.eigvalsh(0.5 * (Hs + Hs.T)), beta, 0.0)
        z_x, count, ms, mk = _radial_sector_sums(model, potential_x, hbar, beta, inertia, size_,
                                                 scale_, shift, tol)
        return z_sigma * z_x, count, ms, mk

    z, count, ms, mk = evaluate(size, scale, scale_sigma)
    error = 0.0
    if check:
        for args in ((size - 10, scale, scale_sigma), (size, 1.2 * scale, 1.2 * scale_sigma)):
            error = max(error, abs(evaluate(*args)[0] - z))
    factor = math.exp(beta * shift)
    return PartitionFunction(z * factor, error * factor, count, ms, mk)


__all__ = [
    "affine_metric_determinant", "classical_partition_function_affine2", "PartitionFunction",
    "partition_function_affine2"
]
