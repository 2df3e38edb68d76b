"""Energy levels of one quantum affine body, sector by sector, in bases orthonormal under the
measure of the two-polar reduction (paper, last section; docs/theory/two-polar.md).

The configuration phi = L diag(Q) R^T is split into its SO(n) x SO(n) orbit (L, R) and the
signed singular values Q (d'Alembert, Lebesgue measure prod_{a<b} |Q_a^2 - Q_b^2|, domain
Q_1 >= ... >= |Q_n|: det phi = 0 is *not* a wall) or their logarithms q (affine models on GL+,
Haar measure prod_{a<b} |sinh(q_a - q_b)|). Each irreducible (spin, vorticity) sector is a
separate eigenproblem on the reduced space, solved densely (no Lanczos, so no copy of a
degenerate level is lost); levels of different sectors that coincide are merged and their
sectors listed, so multiplicities can be checked against the group theory.

Discretisations (all Galerkin, potential matrices by Gauss quadrature):

* n = 2, d'Alembert, J = I Id. Write phi = [[a+c, d-b], [b+d, a-c]] = Z + W with the conformal
  part z = a + ib and the anticonformal part w = c + id: Q_1 = |z| + |w|, Q_2 = |z| - |w|,
  Tr(phi^T phi) = 2(|z|^2 + |w|^2) and T = I(|z'|^2 + |w'|^2), so
  H = -(hbar^2 / 4I)(Lap_z + Lap_w) + V. L-rotations multiply z, w by e^{i alpha}, R-rotations
  by e^{-i beta}, e^{i beta}; a state e^{i(m1 arg z + m2 arg w)} has spin s = m1 + m2 and
  vorticity k = m2 - m1. In the sector (m1, m2) the reduced problem lives on r1 = |z|,
  r2 = |w| >= 0 with measure r1 r2 (= (Q_1^2 - Q_2^2)/4) and centrifugal terms
  hbar^2 m_i^2 / (4 I r_i^2), i.e. (rho -+ tau)^2 / (4 I (Q_1 +- Q_2)^2) of
  docs/theory/two-polar.md with rho = hbar s, tau = hbar k. Basis: products of 2D-radial
  oscillator functions r^|m| L_j^|m|(r^2/b^2) e^{-r^2/2b^2} (generalised Laguerre, orthonormal
  under r dr), exact for the oscillator and exponentially convergent for smooth confining V.
* n = 2, affine models (73) is-af, (74) af-is, (72) af-af on GL+(2). With x = q_1 - q_2 > 0 and
  sigma = q_1 + q_2, the reduced operator of docs/theory/two-polar.md (M = I + A) is
  H = -(hbar^2/M)(1/sinh x) d_x sinh x d_x - hbar^2/(M + 2B) d_sigma^2
      + hbar^2 (s+k)^2 / (16 M sinh^2(x/2)) - hbar^2 (s-k)^2 / (16 M cosh^2(x/2))
      + hbar^2 k^2 / (2 I~)   [is-af: s^2; af-af: none] + V(q).
  The basis is g(x) u_j(x) h_l(sigma) with g = sqrt(x / sinh x) (so the functions are
  orthonormal under sinh x dx dsigma), u_j the 2D-radial Laguerre functions of order
  m = |s+k|/2 and h_l Hermite functions. Conjugating by g turns the x-part into the flat 2D
  radial operator plus the smooth term W = 1/4 + (1/x^2 - 1/sinh^2 x)/4.
* n = 3: every SO(3) x SO(3) sector (j, j') and the dedicated scalar / spin = vorticity = 1
  bases, in :mod:`affinebody.quantum.n3` (imported by :func:`solve` when n = 3).

Honesty: every sector is solved with the main basis, with a smaller nested basis and
(n = 2) with a wider one (scale x 1.3); the spread is the per-level error estimate, and levels
whose estimate exceeds the tolerance (e.g. pseudo-levels of a continuous spectrum) are
reported separately as unconverged, never as levels.

Partition functions and the classical limit (n = 2, af-is / is-af) are in
:mod:`affinebody.quantum.thermal`. The names that moved to n3 / thermal stay reachable here
(``spectra.ChamberQuadrature``, ``spectra.partition_function_affine2``, ...) through a lazy
module ``__getattr__``, so that importing this module never imports those.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import linalg, optimize, special

#: A potential as a function of the signed singular values Q [..., n] (Q_n carries sign det).
Potential = Callable[[np.ndarray], np.ndarray]

MODELS = ("dalembert", "af-is", "is-af", "af-af")
SECTORS3 = ("all", "scalar", "spin1", "scalar+spin1")


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Sector:
    """An SO(n) x SO(n) sector: spin s (L-rotations), vorticity k (R-rotations), parity.

    ``parity`` is the eigenvalue of Psi(phi) -> Psi(-phi) where that is a symmetry, else None.
    """

    spin: int
    vorticity: int
    parity: int | None = None
    #: number of states: 1 for the SO(2) x SO(2) characters (n = 2), dim(j) dim(j') =
    #: (2j + 1)(2j' + 1) for the n = 3 sector (spin j, vorticity j')
    dimension: int = 1

    def as_dict(self) -> dict:
        return {"spin": self.spin, "vorticity": self.vorticity, "parity": self.parity,
                "dimension": self.dimension}


def state_count(sectors: tuple[Sector, ...]) -> int:
    """Number of states of the sectors listed (the sum of their dimensions)."""
    return sum(sec.dimension for sec in sectors)


@dataclass(frozen=True)
class Level:
    """One energy level: value, multiplicity (= sum of the dimensions of the sectors listed),
    convergence."""

    energy: float
    multiplicity: int
    sectors: tuple[Sector, ...]
    error: float
    block: tuple  # key of the reduced block the eigenvector lives in
    index: int  # index of the eigenvector within that block

    def as_dict(self) -> dict:
        first = self.sectors[0]
        return {
            "energy": self.energy,
            "multiplicity": self.multiplicity,
            "spin": first.spin,
            "vorticity": first.vorticity,
            "parity": first.parity,
            "sectors": [s.as_dict() for s in self.sectors],
            "error": self.error,
        }


@dataclass
class Block:
    """A reduced eigenproblem (one radial problem shared by the sectors listed)."""

    key: tuple
    sectors: tuple[Sector, ...]
    basis: Basis
    energies: np.ndarray
    vectors: np.ndarray
    errors: np.ndarray


@dataclass
class Spectrum:
    """Converged levels (ascending), unconverged candidates, and the solved blocks."""

    levels: list[Level]
    unconverged: list[Level]
    blocks: dict[tuple, Block]
    model: str
    n: int
    sectors: str  # "all", or for n = 3 "scalar", "spin1", "scalar+spin1"
    settings: dict = field(default_factory=dict)
    #: False where the sector sum is unbounded below (af-af): the levels are then only those of
    #: the sectors explored (|s|, |k| <= max_spin) and not the lowest of the body
    bounded_below: bool = True
    warnings: list[str] = field(default_factory=list)

    def energies(self, count: int | None = None) -> list[float]:
        """Energies in ascending order, each repeated by its multiplicity (first ``count``)."""
        values = [lv.energy for lv in self.levels for _ in range(lv.multiplicity)]
        return values if count is None else values[:count]

    def level_of_state(self, k: int) -> Level:
        """The level holding the k-th entry (0-based) of :meth:`energies`."""
        seen = 0
        for lv in self.levels:
            seen += lv.multiplicity
            if k < seen:
                return lv
        raise ValueError(f"--state {k} is beyond the {seen} converged states computed")


# ------------------------------------------------------------------ one-dimensional bases
def gauss_basis(jacobi_diag: np.ndarray, jacobi_off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss nodes and the matrix B[g, j] = sqrt(w_g) p_j(t_g) of orthonormal polynomials.

    Golub-Welsch: the eigenvectors of the Jacobi matrix (the matrix of t in the orthonormal
    basis) are exactly sqrt(w_g) p_j(t_g), with the sign fixed by p_0 > 0. No overflow for large
    degrees or parameters, unlike explicit weights and polynomial values.
    """
    nodes, vecs = linalg.eigh_tridiagonal(jacobi_diag, jacobi_off)
    vecs = vecs * np.sign(vecs[0])[None, :]
    return nodes, vecs.T


def laguerre_jacobi(m: float, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi matrix of t for Laguerre polynomials orthonormal under t^m e^-t dt on (0, inf)."""
    j = np.arange(size, dtype=float)
    return 2 * j + m + 1, -np.sqrt((j[1:]) * (j[1:] + m))


def hermite_jacobi(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Jacobi matrix of x for Hermite polynomials orthonormal under e^{-x^2} dx."""
    j = np.arange(1, size, dtype=float)
    return np.zeros(size), np.sqrt(j / 2)


@dataclass(frozen=True)
class Radial2D:
    """2D-radial oscillator functions u_j(r) = sqrt(2) b^-1 (r/b)^m e^{-t/2} l_j(t), t = r^2/b^2.

    Orthonormal under r dr; ``laplacian`` is the exact Galerkin matrix of
    -(1/r)(r u')' + m^2 u / r^2, namely (2 diag(2j+m+1) - T)/b^2 with T the Jacobi matrix.
    """

    m: int
    size: int
    scale: float
    quad: int

    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        t, B = gauss_basis(*laguerre_jacobi(self.m, self.quad))
        return self.scale * np.sqrt(t), B[:, : self.size]

    def laplacian(self) -> np.ndarray:
        d, o = laguerre_jacobi(self.m, self.size)
        T = np.diag(d) + np.diag(o, 1) + np.diag(o, -1)
        return (2 * np.diag(d) - T) / self.scale**2

    def evaluate(self, r: np.ndarray) -> np.ndarray:
        """u_j(r) at arbitrary r >= 0, shape [..., size]."""
        t = (np.asarray(r, float) / self.scale) ** 2
        out = np.empty(t.shape + (self.size,))
        with np.errstate(divide="ignore", invalid="ignore"):
            log_power = np.where(t > 0, 0.5 * self.m * np.log(np.where(t > 0, t, 1.0)),
                                 0.0 if self.m == 0 else -np.inf)
        front = np.exp(log_power - 0.5 * t - 0.5 * special.gammaln(self.m + 1))
        p_prev = np.zeros_like(t)
        p = np.ones_like(t)
        for j in range(self.size):
            out[..., j] = p
            a = 2 * j + self.m + 1
            b_next = math.sqrt((j + 1) * (j + 1 + self.m))
            b_here = math.sqrt(j * (j + self.m))
            p_prev, p = p, ((a - t) * p - b_here * p_prev) / b_next
        return out * (front * math.sqrt(2) / self.scale)[..., None]


@dataclass(frozen=True)
class Hermite1D:
    """Hermite functions h_j(x) = b^-1/2 psi_j((x - c)/b), orthonormal under dx.

    ``laplacian`` is the exact Galerkin matrix of -d^2/dx^2, (2 diag(j + 1/2) - X^2)/b^2.
    """

    size: int
    scale: float
    centre: float
    quad: int

    def nodes(self) -> tuple[np.ndarray, np.ndarray]:
        y, B = gauss_basis(*hermite_jacobi(self.quad))
        return self.centre + self.scale * y, B[:, : self.size]

    def laplacian(self) -> np.ndarray:
        d, o = hermite_jacobi(self.size + 1)
        X = np.diag(o, 1) + np.diag(o, -1)
        X2 = (X @ X)[: self.size, : self.size]
        return (2 * np.diag(np.arange(self.size) + 0.5) - X2) / self.scale**2

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        y = (np.asarray(x, float) - self.centre) / self.scale
        out = np.empty(y.shape + (self.size,))
        p_prev = np.zeros_like(y)
        p = np.full_like(y, math.pi**-0.25)
        for j in range(self.size):
            out[..., j] = p
            p_prev, p = p, (math.sqrt(2.0 / (j + 1)) * y * p - math.sqrt(j / (j + 1)) * p_prev)
        return out * (np.exp(-0.5 * y * y) / math.sqrt(self.scale))[..., None]


# --------------------------------------------------------------------- reduced problems
@dataclass(frozen=True)
class Basis:
    """What is needed to evaluate a block's eigenfunctions: kind plus its 1D factors."""

    kind: str  # "lebesgue2", "haar2", "scalar3"
    factors: tuple

    def reduced_values(self, coords: tuple[np.ndarray, ...]) -> np.ndarray:
        """Basis functions at reduced coordinates (r1, r2) / (x, sigma) / Q [P, 3]."""
        if self.kind == "lebesgue2":
            u1 = self.factors[0].evaluate(coords[0])
            u2 = self.factors[1].evaluate(coords[1])
            return (u1[..., :, None] * u2[..., None, :]).reshape(u1.shape[:-1] + (-1,))
        if self.kind == "haar2":
            x, sigma = coords
            g = sqrt_x_over_sinh(x)
            u = self.factors[0].evaluate(x) * g[..., None]
            h = self.factors[1].evaluate(sigma)
            return (u[..., :, None] * h[..., None, :]).reshape(u.shape[:-1] + (-1,))
        return self.factors[0].evaluate(coords[0])


def sqrt_x_over_sinh(x: np.ndarray) -> np.ndarray:
    """g(x) = sqrt(x / sinh x), smooth (-> 1 - x^2/12 at 0): the conjugation of the Haar radial
    part (module docstring)."""
    x = np.asarray(x, float)
    small = np.abs(x) < 1e-4
    safe = np.where(small, 1.0, x)
    return np.where(small, 1 - x * x / 12, np.sqrt(safe / np.sinh(safe)))


def inv_x2_minus_inv_sinh2(x: np.ndarray) -> np.ndarray:
    """1/x^2 - 1/sinh^2 x, smooth (-> 1/3 at 0)."""
    x = np.asarray(x, float)
    small = np.abs(x) < 2e-2
    safe = np.where(small, 1.0, x)
    series = 1 / 3 - x**2 / 15 + 2 * x**4 / 189
    return np.where(small, series, 1 / safe**2 - 1 / np.sinh(safe) ** 2)


def _dense_lowest(H: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    count = min(count, H.shape[0])
    w, v = linalg.eigh(H, subset_by_index=[0, count - 1], driver="evr")
    return w, v


def lebesgue2_block(potential: Potential, hbar: float, inertia: float, m1: int, m2: int,
                    size: int, scale: float, quad: int | None = None
                    ) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of the n = 2 d'Alembert sector (|m1|, |m2|), J = inertia * Id."""
    quad = quad or size + 24
    f1 = Radial2D(abs(m1), size, scale, quad)
    f2 = Radial2D(abs(m2), size, scale, quad)
    r1, B1 = f1.nodes()
    r2, B2 = f2.nodes()
    R1, R2 = np.meshgrid(r1, r2, indexing="ij")
    Q = np.stack([R1 + R2, R1 - R2], axis=-1)
    V = np.asarray(potential(Q), float)
    B = (B1[:, None, :, None] * B2[None, :, None, :]).reshape(quad * quad, size * size)
    H = B.T @ (V.reshape(-1, 1) * B)
    eye = np.eye(size)
    H += (hbar**2 / (4 * inertia)) * (np.kron(f1.laplacian(), eye) + np.kron(eye, f2.laplacian()))
    return 0.5 * (H + H.T), Basis("lebesgue2", (f1, f2))


@dataclass(frozen=True)
class AffineInertia:
    """Inertial constants of (72)-(74) as they enter the reduced Hamiltonian (n = 2)."""

    model: str
    I: float  # noqa: E741
    A: float
    B: float

    @property
    def M(self) -> float:
        return (0.0 if self.model == "af-af" else self.I) + self.A

    @property
    def inv_I_tilde(self) -> float:
        """1/I~ of (86); 0 for af-af."""
        if self.model == "af-af":
            return 0.0
        return self.I / (self.I**2 - self.A**2)

    @property
    def dilatation(self) -> float:
        """M + nB (n = 2): the coefficient of the dilatational kinetic term."""
        return self.M + 2 * self.B


def haar2_block(potential: Potential, hbar: float, inertia: AffineInertia, spin: int,
                vorticity: int, size: tuple[int, int], scale: tuple[float, float], centre: float,
                quad: tuple[int, int] | None = None) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of the n = 2 affine sector (s, k) on GL+(2), see module docstring."""
    nx, ns = size
    qx, qs = quad or (nx + 24, ns + 24)
    m = abs(spin + vorticity) // 2
    fx = Radial2D(m, nx, scale[0], qx)
    fs = Hermite1D(ns, scale[1], centre, qs)
    x, Bx = fx.nodes()
    sigma, Bs = fs.nodes()
    M = inertia.M
    W = 0.25 + 0.25 * inv_x2_minus_inv_sinh2(x)
    centrifugal = m * m * (1 / (4 * np.sinh(x / 2) ** 2) - 1 / x**2)
    rotational = {"af-is": vorticity**2, "is-af": spin**2, "af-af": 0}[inertia.model]
    smooth_x = (hbar**2 / M) * (W + centrifugal) - (
        hbar**2 * (spin - vorticity) ** 2 / (16 * M * np.cosh(x / 2) ** 2))
    X, S = np.meshgrid(x, sigma, indexing="ij")
    q = np.stack([(S + X) / 2, (S - X) / 2], axis=-1)
    with np.errstate(over="ignore"):  # e^q overflows far out, where V is +inf anyway
        V = np.asarray(potential(np.exp(q)), float) + smooth_x[:, None]
    B = (Bx[:, None, :, None] * Bs[None, :, None, :]).reshape(qx * qs, nx * ns)
    H = B.T @ (V.reshape(-1, 1) * B)
    H += np.kron((hbar**2 / M) * fx.laplacian(), np.eye(ns))
    H += np.kron(np.eye(nx), (hbar**2 / inertia.dilatation) * fs.laplacian())
    H += np.eye(nx * ns) * (hbar**2 * rotational * inertia.inv_I_tilde / 2)
    return 0.5 * (H + H.T), Basis("haar2", (fx, fs))


# ------------------------------------------------------------------------ scale choice
def variational_parameters(energy: Callable[[np.ndarray], float], start: np.ndarray
                           ) -> np.ndarray:
    """The basis parameters (log-scales, centre) minimising ``energy`` (Nelder-Mead from
    ``start``; coarse: only the basis quality depends on them)."""
    res = optimize.minimize(energy, start, method="Nelder-Mead",
                            options={"xatol": 1e-3, "fatol": 1e-10, "maxiter": 200})
    return res.x


def auto_scale_lebesgue2(potential: Potential, hbar: float, inertia: float) -> float:
    """Oscillator length minimising the sum of the 3 lowest (0,0)-sector levels, small basis."""
    def energy(logb):
        b = float(np.exp(np.clip(logb[0], -6, 6)))
        H, _ = lebesgue2_block(potential, hbar, inertia, 0, 0, 6, b, 30)
        return float(np.sum(linalg.eigvalsh(H)[:3]))
    return float(np.exp(np.clip(variational_parameters(energy, np.array([0.0]))[0], -6, 6)))


def auto_scale_haar2(potential: Potential, hbar: float, inertia: AffineInertia
                     ) -> tuple[float, float, float]:
    """(scale_x, scale_sigma, centre_sigma) minimising the sum of low (0,0)-sector levels."""
    sig = np.linspace(-8, 8, 161)
    Vline = np.asarray(potential(np.exp(np.stack([sig / 2, sig / 2], -1))), float)
    centre0 = float(sig[np.argmin(np.where(np.isfinite(Vline), Vline, np.inf))])

    def energy(p):
        bx, bs = np.exp(np.clip(p[:2], -5, 3))
        H, _ = haar2_block(potential, hbar, inertia, 0, 0, (6, 6), (bx, bs), p[2], (30, 30))
        return float(np.sum(linalg.eigvalsh(H)[:3]))
    p = variational_parameters(energy, np.array([0.0, 0.0, centre0]))
    bx, bs = np.exp(np.clip(p[:2], -5, 3))
    return float(bx), float(bs), float(p[2])


# ------------------------------------------------------------------------- solver
@dataclass(frozen=True)
class Settings:
    """Discretisation settings (see :mod:`affinebody.quantum.config` for the config names)."""

    basis_size: int = 24  # per reduced coordinate (n = 2); polynomial degree (n = 3)
    scale: float | None = None  # None: variational choice
    scale_sigma: float | None = None
    centre: float | None = None
    tolerance: float = 1e-7  # absolute error allowed per level (relative to max(1, |E|))
    check_shrink: int = 4  # the nested check basis has basis_size - check_shrink functions
    check_widen: float = 1.3  # the widened check basis has scale x check_widen
    max_spin: int = 40  # largest |m1|, |m2| (n = 2) explored
    merge: float = 1e-8  # levels closer than merge * max(1,|E|) are one degenerate level


def solve_block(build: Callable[[int, float], tuple[np.ndarray, Basis]], size: int, scale: float,
                count: int, settings: Settings
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Basis]:
    """The ``count`` lowest eigenpairs of ``build(size, scale)`` and their error estimates: the
    larger change under the nested basis ``size - check_shrink`` and the widened basis
    ``scale * check_widen`` (skipped when check_widen == 1); inf where a check basis has fewer
    levels. Returns (energies, eigenvectors, errors, basis)."""
    H, basis = build(size, scale)
    if H.size == 0:  # no basis function (an n = 3 sector starting above this degree)
        return np.zeros(0), np.zeros((0, 0)), np.zeros(0), basis
    E, vec = _dense_lowest(H, count)
    Hs, _ = build(size - settings.check_shrink, scale)
    Es = linalg.eigvalsh(Hs)[: len(E)] if Hs.size else np.zeros(0)
    if settings.check_widen == 1.0:
        Ew = E
    else:
        Hw, _ = build(size, scale * settings.check_widen)
        Ew = linalg.eigvalsh(Hw)[: len(E)]
    err = np.full(len(E), np.inf)
    k = min(len(Es), len(Ew))
    err[:k] = np.maximum(np.abs(E[:k] - Es[:k]), np.abs(E[:k] - Ew[:k]))
    return E, vec, err, basis


def is_converged(E: float, err: float, settings: Settings) -> bool:
    """err within tolerance * max(1, |E|), and small against |E| itself: pseudo-levels of a
    continuous spectrum in a wide basis (E ~ hbar^2 / (I b^2) -> 0) move by a fixed fraction
    of E when the basis is widened, however small E is."""
    return bool(err <= settings.tolerance * max(1.0, abs(E)) and err <= 1e-2 * abs(E) + 1e-12)


def merge_levels(entries: list[tuple[float, float, tuple[Sector, ...], tuple, int]],
                 settings: Settings) -> list[Level]:
    """Levels (ascending) from entries (energy, error, sectors, block key, index): energies
    closer than settings.merge * max(1, |E|) are one degenerate level listing every sector."""
    entries = sorted(entries, key=lambda e: e[0])
    levels: list[Level] = []
    for E, err, sectors, key, idx in entries:
        if levels and abs(E - levels[-1].energy) <= settings.merge * max(1.0, abs(E)):
            last = levels[-1]
            levels[-1] = Level(last.energy, last.multiplicity + state_count(sectors),
                               last.sectors + sectors, max(last.error, err), last.block,
                               last.index)
        else:
            levels.append(Level(E, state_count(sectors), sectors, err, key, idx))
    return levels


def _n2_sectors(key: tuple, model: str) -> tuple[Sector, ...]:
    """The (s, k) sectors sharing the reduced block ``key``."""
    if model == "dalembert":
        a, b = key  # |m1|, |m2|
        pairs = {(s1 * a, s2 * b) for s1 in (1, -1) for s2 in (1, -1)}
        out = [(m1 + m2, m2 - m1) for m1, m2 in pairs]
    else:
        s, k = key
        out = list({(s, k), (-s, -k)})
    out.sort(key=lambda p: (-p[0], -p[1]))
    # k labels R -> R(beta) R, i.e. phi -> phi R(beta)^T: the vorticity V_12 = (Sigma_hat -
    # Sigma_hat^T)_12, generating phi -> phi R(t), has eigenvalue -hbar k (reduction.py).
    return tuple(Sector(s, -k, (-1) ** abs(s)) for s, k in out)


def solve(model: str, n: int, potential: Potential, hbar: float, *, inertia: float = 1.0,
          I: float = 1.0, A: float = 0.0, B: float = 0.0, levels: int = 10,  # noqa: E741
          settings: Settings | None = None, sectors: str = "auto",
          progress: Callable[[str], None] | None = None) -> Spectrum:
    """The lowest ``levels`` states (counted with multiplicity) of the reduced problem.
    ``progress`` (n = 3, all sectors) receives a line per sector as it starts.

    ``model`` in :data:`MODELS`; d'Alembert uses J = inertia * Id, the affine models (I, A, B).
    ``sectors``: "all" (every sector: n = 2 the characters (s, k), n = 3 the SO(3) x SO(3)
    sectors (j, j') by :mod:`affinebody.quantum.n3`), "auto" = "all"; for n = 3 also "scalar"
    (spin = vorticity = 0), "spin1" (spin = vorticity = 1, 9 states per level) or
    "scalar+spin1" (the dedicated bases of those sectors; the result warns that the other
    sectors are left out).
    """
    settings = settings or Settings()
    if model not in MODELS:
        raise ValueError(f"quantum.kinetic must be one of {MODELS} (got {model!r})")
    if n not in (2, 3):
        raise ValueError(f"system.n must be 2 or 3 for quantum spectra (got {n})")
    if sectors == "auto":
        sectors = "all"
    if n == 2 and sectors != "all":
        raise ValueError(f"quantum.sectors must be 'all' or 'auto' for n = 2 (got {sectors!r})")
    if n == 3 and sectors not in SECTORS3:
        raise ValueError(f"quantum.sectors must be one of {', '.join(SECTORS3)} for n = 3 (got "
                         f"{sectors!r})")
    if n == 3:
        from affinebody.quantum import channels3, n3

        if sectors == "all":
            return n3.solve_all_sectors(model, potential, hbar, inertia,
                                        AffineInertia(model, I, A, B), levels, settings,
                                        progress)
        if model == "dalembert" and sectors == "scalar":
            return channels3.solve_dalembert_scalar(potential, hbar, inertia, levels, settings)
        return channels3.solve_channels(model, potential, hbar, inertia,
                                        AffineInertia(model, I, A, B), levels, settings, sectors)
    found = LevelCollector(settings)
    info: dict = {"basis_size": settings.basis_size}
    count = levels + 4
    if model == "dalembert":
        b = settings.scale or auto_scale_lebesgue2(potential, hbar, inertia)
        info["scale"] = b

        def build_for(a, c):
            return lambda size, s: lebesgue2_block(potential, hbar, inertia, a, c, size, s)
        shells = ((a, L - a) for L in range(2 * settings.max_spin + 1) for a in range(L + 1)
                  if a <= settings.max_spin and L - a <= settings.max_spin)
        shell_of = lambda key: key[0] + key[1]
    else:
        inert = AffineInertia(model, I, A, B)
        bx, bs, c0 = auto_scale_haar2(potential, hbar, inert)
        bx = settings.scale or bx
        bs = settings.scale_sigma or bs
        c0 = c0 if settings.centre is None else settings.centre
        info.update(scale=bx, scale_sigma=bs, centre=c0)

        def build_for(s, k):
            return lambda size, sc: haar2_block(
                potential, hbar, inert, s, k, (size, size), (sc, bs * sc / bx), c0)
        # representatives of (s, k) ~ (-s, -k), s + k even; shell = max(|s|, |k|)
        shells = ((s, k) for L in range(settings.max_spin + 1) for s in range(0, L + 1)
                  for k in range(-L, L + 1) if max(s, abs(k)) == L and (s + k) % 2 == 0
                  and (s > 0 or k >= 0))
        shell_of = lambda key: max(abs(key[0]), abs(key[1]))

    current_shell, shell_min = 0, np.inf
    shell_minima: list[float] = []
    for key in shells:
        shell = shell_of(key)
        if shell != current_shell:
            shell_minima.append(shell_min)
            if shell_complete(found.known(), levels, shell_min):
                break
            current_shell, shell_min = shell, np.inf
        E, vec, err, basis = solve_block(build_for(*key), settings.basis_size,
                                         info["scale"], count, settings)
        shell_min = min(shell_min, float(E[0]))
        found.record(key, _n2_sectors(key, model), basis, E, vec, err)
    else:
        shell_minima.append(shell_min)
        info["max_spin_reached"] = True
    warnings = []
    bounded = True
    if model == "af-af":
        bounded = False
        warnings.append(_afaf_warning(hbar, A, settings.max_spin, shell_minima))
    elif info.get("max_spin_reached"):
        warnings.append(f"the sector search stopped at max_spin = {settings.max_spin} before the "
                        f"{levels} lowest states were certain: raise quantum.max_spin")
    merged, unconverged = found.levels(levels)
    return Spectrum(merged, unconverged, found.blocks, model, n, "all", info, bounded, warnings)


def _afaf_warning(hbar: float, A: float, max_spin: int, shell_minima: list[float]) -> str:
    """af-af (72) is indefinite: in the sector s = -k the reduced potential (module docstring,
    no rotational term since 1/I~ = 0) is -hbar^2 s^2 / (4 A cosh^2((q1 - q2)/2)), a well
    whose depth grows like s^2: the lowest level of shell |s| tends to -infinity."""
    trend = ", ".join(f"{e:.4g}" for e in shell_minima[-4:] if np.isfinite(e))
    return (f"af-af: the kinetic energy (72) is indefinite and the spectrum is unbounded below "
            f"(sector s = -k has the well -hbar^2 s^2/(4A cosh^2((q1-q2)/2)), depth "
            f"{hbar**2 * max_spin**2 / (4 * A):.4g} at |s| = {max_spin}); lowest level per shell "
            f"up to max_spin = {max_spin}: {trend}; the levels listed are those of the sectors "
            f"|s|, |k| <= max_spin only, not the lowest of the body")


def kth_energy(entries, count: int) -> float:
    """The ``count``-th lowest energy of the entries counted with their states (inf if fewer)."""
    values = sorted(v for e in entries for v in [e[0]] * state_count(e[2]))
    return values[count - 1] if len(values) >= count else np.inf


def shell_complete(known: list, levels: int, shell_min: float) -> bool:
    """The sector search may stop: the candidates found (converged or not; an unconverged one
    still bounds what a higher shell could add) hold ``levels`` states, all below the lowest
    level ``shell_min`` of the shell just solved."""
    return (sum(state_count(e[2]) for e in known) >= levels
            and shell_min > kth_energy(known, levels))


def truncate_levels(levels: list[Level], count: int) -> list[Level]:
    """The lowest levels that hold the first ``count`` states (the last may hold more)."""
    out, total = [], 0
    for lv in levels:
        if total >= count:
            break
        out.append(lv)
        total += lv.multiplicity
    return out


def eigen_parity(vector: np.ndarray, parity: np.ndarray) -> int | None:
    """Parity of an eigenvector in a basis of functions of definite ``parity`` (+1 / -1):
    +1 or -1 when its weight lies (to 1e-8) on one class, None when it mixes them."""
    even = float(np.sum(vector[parity == 1] ** 2))
    return 1 if even > 1 - 1e-8 else (-1 if even < 1e-8 else None)


@dataclass
class LevelCollector:
    """The solved blocks of a spectrum being assembled, their converged levels (as entries for
    :func:`merge_levels`) and the unconverged candidates."""

    settings: Settings
    blocks: dict = field(default_factory=dict)
    entries: list = field(default_factory=list)
    unconverged: list = field(default_factory=list)

    def _add(self, E: float, err: float, sectors: tuple, key: tuple, index: int) -> None:
        if is_converged(E, err, self.settings):
            self.entries.append((float(E), float(err), sectors, key, index))
        else:
            self.unconverged.append(Level(float(E), state_count(sectors), sectors, float(err),
                                          key, index))

    def record(self, key: tuple, sectors: tuple, basis: Basis, E, vec, err) -> None:
        """One block whose eigenvectors all belong to ``sectors`` (level i: index i)."""
        self.blocks[key] = Block(key, sectors, basis, E, vec, err)
        for i in range(len(E)):
            self._add(E[i], err[i], sectors, key, i)

    def record_each(self, key: tuple, sectors_of: Callable[[int | None], tuple], basis: Basis,
                    E, vec, err, parity: np.ndarray) -> None:
        """One block per eigenvector, keyed ``key + (i,)``, its sectors labelled by its parity
        (:func:`eigen_parity` over the basis functions' ``parity``)."""
        for i in range(len(E)):
            sec = sectors_of(eigen_parity(vec[:, i], parity))
            one = key + (i,)
            self.blocks[one] = Block(one, sec, basis, E[i:i + 1], vec[:, i:i + 1], err[i:i + 1])
            self._add(E[i], err[i], sec, one, 0)

    def known(self) -> list:
        """Entries of every candidate, converged or not (a bound on what is still missing)."""
        return self.entries + [(lv.energy, lv.error, lv.sectors, lv.block, 0)
                               for lv in self.unconverged]

    def levels(self, count: int | None) -> tuple[list[Level], list[Level]]:
        """(the lowest ``count`` states as merged levels, the unconverged candidates up to the
        highest of them, ascending); ``count`` None: every level and candidate found."""
        merged = merge_levels(self.entries, self.settings)
        if count is None:
            return merged, sorted(self.unconverged, key=lambda lv: lv.energy)
        merged = truncate_levels(merged, count)
        top = (merged[-1].energy if merged and sum(lv.multiplicity for lv in merged) >= count
               else np.inf)
        limit = top + self.settings.merge * max(1.0, abs(top))
        return merged, sorted((lv for lv in self.unconverged if lv.energy <= limit),
                              key=lambda lv: lv.energy)


# ------------------------------------------------------- independent Cartesian check (n = 2)
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
    from scipy.sparse.linalg import LinearOperator, eigsh

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


# ------------------------------------------------------------- names that moved (lazy access)
#: old name -> (module of affinebody.quantum, name there) for the code moved out of this module
#: and the helpers renamed
_MOVED: dict[str, tuple[str, str]] = {
    **{name: ("thermal", name) for name in (
        "affine_metric_determinant", "classical_partition_function_affine2",
        "PartitionFunction", "partition_function_affine2")},
    **{name: ("channels3", name) for name in (
        "ChamberQuadrature", "ScalarBasis3", "scalar3_block", "auto_scale_scalar3", "Jet",
        "Grid3", "haar3_grid", "channel3_block", "channel3_forms", "auto_scale_haar3")},
}


def __getattr__(name: str):
    """``spectra.<name>`` for the names in :data:`_MOVED`, importing their module on first use
    (a top-level import would be a cycle: channels3, n3 and thermal import this module)."""
    if name in _MOVED:
        module, attribute = _MOVED[name]
        return getattr(importlib.import_module(f"affinebody.quantum.{module}"), attribute)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
