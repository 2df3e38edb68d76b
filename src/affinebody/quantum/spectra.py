"""Energy levels of one quantum affine body, sector by sector, in bases orthonormal under the
measure of the two-polar reduction (paper, last section; DERIVATIONS.md, "Quantum").

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
  hbar^2 m_i^2 / (4 I r_i^2), i.e. (rho -+ tau)^2 / (4 I (Q_1 +- Q_2)^2) of DERIVATIONS.md with
  rho = hbar s, tau = hbar k. Basis: products of 2D-radial oscillator functions
  r^|m| L_j^|m|(r^2/b^2) e^{-r^2/2b^2} (generalised Laguerre, orthonormal under r dr), exact
  for the oscillator and exponentially convergent for smooth confining V.
* n = 2, affine models (73) is-af, (74) af-is, (72) af-af on GL+(2). With x = q_1 - q_2 > 0 and
  sigma = q_1 + q_2, the reduced operator of DERIVATIONS.md (M = I + A) is
  H = -(hbar^2/M)(1/sinh x) d_x sinh x d_x - hbar^2/(M + 2B) d_sigma^2
      + hbar^2 (s+k)^2 / (16 M sinh^2(x/2)) - hbar^2 (s-k)^2 / (16 M cosh^2(x/2))
      + hbar^2 k^2 / (2 I~)   [is-af: s^2; af-af: none] + V(q).
  The basis is g(x) u_j(x) h_l(sigma) with g = sqrt(x / sinh x) (so the functions are
  orthonormal under sinh x dx dsigma), u_j the 2D-radial Laguerre functions of order
  m = |s+k|/2 and h_l Hermite functions. Conjugating by g turns the x-part into the flat 2D
  radial operator plus the smooth term W = 1/4 + (1/x^2 - 1/sinh^2 x)/4.
* n = 3, d'Alembert, the scalar sector (spin = vorticity = 0): functions of Q invariant under
  the Weyl group (permutations and even sign changes of Q). Basis: Gaussian times invariant
  polynomials in p2 = sum Q^2, e3 = Q1 Q2 Q3, p4 = sum Q^4, orthonormalised under
  prod (Q_a^2 - Q_b^2) dQ on the chamber Q_1 > Q_2 > |Q_3| by an Arnoldi process on a
  quadrature grid (radial Gauss-Legendre x Duffy-mapped triangle). Contains every oscillator
  eigenfunction of degree <= the basis degree, so the oscillator is exact.

Honesty: every sector is solved with the main basis, with a smaller nested basis and
(n = 2) with a wider one (scale x 1.3); the spread is the per-level error estimate, and levels
whose estimate exceeds the tolerance (e.g. pseudo-levels of a continuous spectrum) are
reported separately as unconverged, never as levels.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from itertools import product

import numpy as np
from scipy import linalg, optimize, special

#: A potential as a function of the signed singular values Q [..., n] (Q_n carries sign det).
Potential = Callable[[np.ndarray], np.ndarray]

MODELS = ("dalembert", "af-is", "is-af", "af-af")
SECTORS3 = ("all", "scalar", "spin1", "scalar+spin1")
_N3_PARTIAL = ("n = 3: only the (spin, vorticity) sectors {sectors} are computed; states of the "
               "other SO(3) x SO(3) sectors (j, j') are not in this list")


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


def _states(sectors: tuple[Sector, ...]) -> int:
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
    x = np.asarray(x, float)
    small = np.abs(x) < 1e-4
    safe = np.where(small, 1.0, x)
    return np.where(small, 1 - x * x / 12, np.sqrt(safe / np.sinh(safe)))


def _inv_x2_minus_inv_sinh2(x: np.ndarray) -> np.ndarray:
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
    W = 0.25 + 0.25 * _inv_x2_minus_inv_sinh2(x)
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


# ------------------------------------------------------------- n = 3 scalar sector
@dataclass(frozen=True)
class ChamberQuadrature:
    """Nodes Q [P, 3] and weights for int over Q_1 > Q_2 > |Q_3| of f(Q) prod(Q_a^2 - Q_b^2) dQ.

    The chamber is the cone over the triangle with vertices e1, (1,1,1), (1,1,-1):
    Q = rho y/|y|, y on the triangle (Duffy-mapped square), Gauss-Legendre in rho on
    [0, rho_max]; the weight prod(Q_a^2 - Q_b^2) is included in the weights.
    """

    nodes: np.ndarray
    weights: np.ndarray

    @classmethod
    def build(cls, rho_max: float, n_rho: int = 60, n_angle: int = 28) -> ChamberQuadrature:
        xr, wr = special.roots_legendre(n_rho)
        rho, w_rho = rho_max * (xr + 1) / 2, rho_max * wr / 2
        xa, wa = special.roots_legendre(n_angle)
        u, wu = (xa + 1) / 2, wa / 2
        U, Vv = np.meshgrid(u, u, indexing="ij")
        WU = np.outer(wu, wu) * (1 - U)  # Duffy: a = u, b = (1 - u) v
        a, b = U.ravel(), ((1 - U) * Vv).ravel()
        c = 1 - a - b
        e1, v2, v3 = np.eye(3)[0], np.ones(3), np.array([1.0, 1.0, -1.0])
        y = a[:, None] * e1 + b[:, None] * v2 + c[:, None] * v3
        ny = np.linalg.norm(y, axis=1)
        # dQ = 2 d(area coords) lambda^2 d lambda with Q = lambda y; lambda = rho / |y|
        w_ang = 2 * WU.ravel() / ny**3
        Q = (rho[:, None, None] * (y / ny[:, None])[None, :, :]).reshape(-1, 3)
        w = (w_rho[:, None] * rho[:, None] ** 2 * w_ang[None, :]).ravel()
        J = (Q[:, 0] ** 2 - Q[:, 1] ** 2) * (Q[:, 0] ** 2 - Q[:, 2] ** 2) * (
            Q[:, 1] ** 2 - Q[:, 2] ** 2)
        return cls(Q, w * J)


@dataclass(frozen=True)
class ScalarBasis3:
    """Weyl-invariant polynomials of degree <= ``degree`` times e^{-|Q|^2/2b^2}, orthonormal
    under prod (Q_a^2 - Q_b^2) dQ on the chamber (Arnoldi on a quadrature grid).

    ``recipe[j] = (parent, generator, coefficients, norm)``: phi_j = (g phi_parent -
    sum_i c_i phi_i) / norm, replayable at any points. ``parity`` of phi_j under Q_3 -> -Q_3
    (phi -> -phi) is (-1)^(power of e3).
    """

    degree: int
    scale: float
    recipe: tuple
    parity: np.ndarray
    norm0: float

    @staticmethod
    def _generators(Q: np.ndarray, scale: float):
        y = Q / scale
        p2 = np.sum(y * y, axis=-1)
        e3 = np.prod(y, axis=-1)
        p4 = np.sum(y**4, axis=-1)
        g2 = 2 * y
        g3 = np.stack([y[..., 1] * y[..., 2], y[..., 0] * y[..., 2], y[..., 0] * y[..., 1]],
                      axis=-1)
        g4 = 4 * y**3
        # gradients with respect to Q (chain rule 1/scale)
        return [(p2, g2 / scale), (e3, g3 / scale), (p4, g4 / scale)]

    def evaluate(self, Q: np.ndarray, with_gradient: bool = False):
        Q = np.asarray(Q, float)
        gens = self._generators(Q, self.scale)
        r2 = np.sum(Q * Q, axis=-1) / self.scale**2
        f0 = np.exp(-0.5 * r2) / self.norm0
        vals = [f0]
        grads = [(-Q / self.scale**2) * f0[..., None]]
        for parent, gen, coeffs, norm in self.recipe:
            g, dg = gens[gen]
            v = g * vals[parent]
            d = dg * vals[parent][..., None] + g[..., None] * grads[parent]
            for i, c in coeffs:
                v = v - c * vals[i]
                d = d - c * grads[i]
            vals.append(v / norm)
            grads.append(d / norm)
        values = np.stack(vals, axis=-1)
        if with_gradient:
            return values, np.stack(grads, axis=-1)
        return values

    @classmethod
    def build(cls, degree: int, scale: float, quad: ChamberQuadrature) -> ScalarBasis3:
        Q, w = quad.nodes, quad.weights
        gens = cls._generators(Q, scale)
        r2 = np.sum(Q * Q, axis=-1) / scale**2
        f0 = np.exp(-0.5 * r2)
        norm0 = math.sqrt(float(np.sum(w * f0 * f0)))
        vals = [f0 / norm0]
        exps = [(0, 0, 0)]
        parity = [1]
        recipe = []
        monomials = sorted(
            ((i, j, k) for i in range(degree // 2 + 1) for j in range(degree // 3 + 1)
             for k in range(degree // 4 + 1) if 2 * i + 3 * j + 4 * k <= degree and (i, j, k)
             != (0, 0, 0)),
            key=lambda e: (2 * e[0] + 3 * e[1] + 4 * e[2], e[1], e[2]))
        index = {(0, 0, 0): 0}
        for mono in monomials:
            gen = next(a for a in range(3) if mono[a] > 0)
            parent_mono = tuple(e - (a == gen) for a, e in enumerate(mono))
            parent = index[parent_mono]
            v = gens[gen][0] * vals[parent]
            coeffs: dict[int, float] = {}
            for _ in range(2):  # classical Gram-Schmidt, twice
                basis = np.stack(vals, axis=1)
                c = basis.T @ (w * v)
                v = v - basis @ c
                for i, ci in enumerate(c):
                    coeffs[i] = coeffs.get(i, 0.0) + float(ci)
            norm = math.sqrt(float(np.sum(w * v * v)))
            index[mono] = len(vals)
            vals.append(v / norm)
            exps.append(mono)
            parity.append((-1) ** mono[1])
            recipe.append((parent, gen, tuple(coeffs.items()), norm))
        return cls(degree, scale, tuple(recipe), np.array(parity), norm0)


def scalar3_block(potential: Potential, hbar: float, inertia: float, degree: int, scale: float,
                  quad: ChamberQuadrature | None = None) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of the n = 3 d'Alembert scalar sector (spin = vorticity = 0):
    H = -(hbar^2/2I)(1/J_L) sum_a d_a J_L d_a + V (DERIVATIONS.md), weak form
    int [(hbar^2/2I) grad f . grad g + V f g] J_L dQ on the chamber (natural boundary)."""
    quad = quad or ChamberQuadrature.build(scale * (8.0 + 0.75 * math.sqrt(degree + 1)),
                                           n_rho=40 + 2 * degree, n_angle=16 + degree)
    basis = ScalarBasis3.build(degree, scale, quad)
    F, dF = basis.evaluate(quad.nodes, with_gradient=True)
    w = quad.weights
    V = np.asarray(potential(quad.nodes), float)
    H = F.T @ ((w * V)[:, None] * F)
    H += (hbar**2 / (2 * inertia)) * np.einsum("pai,p,paj->ij", dF, w, dF, optimize=True)
    return 0.5 * (H + H.T), Basis("scalar3", (basis,))


# ------------------------------------------------------------------------ scale choice
def _variational(energy: Callable[[np.ndarray], float], start: np.ndarray) -> np.ndarray:
    res = optimize.minimize(energy, start, method="Nelder-Mead",
                            options={"xatol": 1e-3, "fatol": 1e-10, "maxiter": 200})
    return res.x


def auto_scale_lebesgue2(potential: Potential, hbar: float, inertia: float) -> float:
    """Oscillator length minimising the sum of the 3 lowest (0,0)-sector levels, small basis."""
    def energy(logb):
        b = float(np.exp(np.clip(logb[0], -6, 6)))
        H, _ = lebesgue2_block(potential, hbar, inertia, 0, 0, 6, b, 30)
        return float(np.sum(linalg.eigvalsh(H)[:3]))
    return float(np.exp(np.clip(_variational(energy, np.array([0.0]))[0], -6, 6)))


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
    p = _variational(energy, np.array([0.0, 0.0, centre0]))
    bx, bs = np.exp(np.clip(p[:2], -5, 3))
    return float(bx), float(bs), float(p[2])


def auto_scale_scalar3(potential: Potential, hbar: float, inertia: float) -> float:
    quad = ChamberQuadrature.build(12.0, 40, 16)

    def energy(logb):
        b = float(np.exp(np.clip(logb[0], -2.4, 0.4)))
        H, _ = scalar3_block(potential, hbar, inertia, 4, b, quad)
        return float(np.sum(linalg.eigvalsh(H)[:2]))
    return float(np.exp(np.clip(_variational(energy, np.array([-0.5]))[0], -2.4, 0.4)))


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


def _solve_block(build: Callable[[int, float], tuple[np.ndarray, Basis]], size: int, scale: float,
                 count: int, settings: Settings
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, Basis]:
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


def _converged(E: float, err: float, settings: Settings) -> bool:
    """err within tolerance * max(1, |E|), and small against |E| itself: pseudo-levels of a
    continuous spectrum in a wide basis (E ~ hbar^2 / (I b^2) -> 0) move by a fixed fraction
    of E when the basis is widened, however small E is."""
    return bool(err <= settings.tolerance * max(1.0, abs(E)) and err <= 1e-2 * abs(E) + 1e-12)


def _merge(entries: list[tuple[float, float, tuple[Sector, ...], tuple, int]],
           settings: Settings) -> list[Level]:
    entries = sorted(entries, key=lambda e: e[0])
    levels: list[Level] = []
    for E, err, sectors, key, idx in entries:
        if levels and abs(E - levels[-1].energy) <= settings.merge * max(1.0, abs(E)):
            last = levels[-1]
            levels[-1] = Level(last.energy, last.multiplicity + _states(sectors),
                               last.sectors + sectors, max(last.error, err), last.block,
                               last.index)
        else:
            levels.append(Level(E, _states(sectors), sectors, err, key, idx))
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
          settings: Settings | None = None, sectors: str = "auto") -> Spectrum:
    """The lowest ``levels`` states (counted with multiplicity) of the reduced problem.

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
    if n == 3 and sectors == "all":
        from affinebody.quantum.n3 import solve_all_sectors
        return solve_all_sectors(model, potential, hbar, inertia, AffineInertia(model, I, A, B),
                                 levels, settings)
    if n == 3 and (model != "dalembert" or sectors != "scalar"):
        return _solve_n3(model, potential, hbar, inertia, AffineInertia(model, I, A, B), levels,
                         settings, sectors)
    blocks: dict[tuple, Block] = {}
    entries: list = []
    unconverged: list[Level] = []
    info: dict = {"basis_size": settings.basis_size}

    def record(key, secs, E, vec, err, basis):
        blocks[key] = Block(key, secs, basis, E, vec, err)
        for i, (e, de) in enumerate(zip(E, err, strict=True)):
            if _converged(e, de, settings):
                entries.append((float(e), float(de), secs, key, i))
            else:
                unconverged.append(Level(float(e), _states(secs), secs, float(de), key, i))

    count = levels + 4
    if n == 3:
        b = settings.scale or auto_scale_scalar3(potential, hbar, inertia)
        info["scale"] = b
        quad = ChamberQuadrature.build(b * (8.0 + 0.75 * math.sqrt(settings.basis_size + 1)),
                                       n_rho=40 + 2 * settings.basis_size,
                                       n_angle=16 + settings.basis_size)
        # a Gaussian of another width is a poor polynomial basis: the check here is the degree
        # only (basis_size - check_shrink), which flags every level the smaller space misses
        E, vec, err, basis = _solve_block(
            lambda d, s: scalar3_block(potential, hbar, inertia, d, s, quad),
            settings.basis_size, b, count, replace(settings, check_widen=1.0))
        # parity under phi -> -phi is a symmetry iff V(Q1,Q2,-Q3) = V(Q)
        Qn = quad.nodes
        sym = np.allclose(potential(Qn * np.array([1, 1, -1.0])), potential(Qn),
                          rtol=1e-12, atol=1e-12)
        par = basis.factors[0].parity
        for i in range(len(E)):
            weight_even = float(np.sum(vec[par == 1, i] ** 2))
            p = 1 if weight_even > 1 - 1e-8 else (-1 if weight_even < 1e-8 else None)
            sec = (Sector(0, 0, p if sym else None),)
            key = ("scalar", i)
            blocks[key] = Block(key, sec, basis, E[i:i + 1], vec[:, i:i + 1], err[i:i + 1])
            if _converged(E[i], err[i], settings):
                entries.append((float(E[i]), float(err[i]), sec, key, 0))
            else:
                unconverged.append(Level(float(E[i]), 1, sec, float(err[i]), key, 0))
        return Spectrum(_merge(entries, settings), unconverged, blocks, model, n, "scalar", info,
                        True, [_N3_PARTIAL.format(sectors="(0, 0)")])

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
            total = sum(_states(e[2]) for e in entries)
            if total >= levels and shell_min > _kth(entries, levels):
                break
            current_shell, shell_min = shell, np.inf
        E, vec, err, basis = _solve_block(build_for(*key), settings.basis_size,
                                          info["scale"], count, settings)
        shell_min = min(shell_min, float(E[0]))
        record(key, _n2_sectors(key, model), E, vec, err, basis)
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
    merged = _truncate(_merge(entries, settings), levels)
    top = merged[-1].energy if sum(lv.multiplicity for lv in merged) >= levels else np.inf
    limit = top + settings.merge * max(1.0, abs(top))
    unconverged = sorted((lv for lv in unconverged if lv.energy <= limit),
                         key=lambda lv: lv.energy)
    return Spectrum(merged, unconverged, blocks, model, n, "all", info, bounded, warnings)


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


def _kth(entries, count: int) -> float:
    values = sorted(v for e in entries for v in [e[0]] * _states(e[2]))
    return values[count - 1] if len(values) >= count else np.inf


def _truncate(levels: list[Level], count: int) -> list[Level]:
    out, total = [], 0
    for lv in levels:
        if total >= count:
            break
        out.append(lv)
        total += lv.multiplicity
    return out


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


# --------------------------------------------- classical limit: partition functions (n = 2)
def affine_metric_determinant(model: str, n: int, I: float, A: float,  # noqa: E741
                              B: float) -> float:
    """det k of the kinetic metric T = 1/2 k(Omega, Omega) of (73) is-af / (74) af-is on gl(n) in
    Frobenius-orthonormal coordinates (Omega = Omega_hat or Omega): k acts as I + A on the
    symmetric traceless, I - A on the skew and I + A + n B on the pure-trace velocities
    (NOTES.md), so det k = (I + A)^{n(n+1)/2 - 1} (I - A)^{n(n-1)/2} (I + A + n B).

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
    ``potential`` takes the singular values Q = e^q [..., 2], as everywhere in this module.
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
    H_x = -(hbar^2/M)(1/sinh x) d sinh x d + U_sk(x) + V_x(x) (reduced af-is / is-af, module
    docstring). Sectors are walked by mu = (s + k)/2 >= 0 (centrifugal order |mu|) and
    d = (s - k)/2, outward from the peak of each row, until a whole row adds less than tol of
    the sum."""
    M = inertia.M
    total, count, max_s, max_k = 0.0, 0, 0, 0
    mu = 0
    while True:
        f = Radial2D(mu, size, scale, size + 30)
        x, Bx = f.nodes()
        W = 0.25 + 0.25 * _inv_x2_minus_inv_sinh2(x)
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
    operator of the module docstring), so Z = Z_sigma * sum_{s,k} Z_x(s, k): one 1D problem
    per sector (2D-radial Laguerre basis conjugated by sqrt(x / sinh x), as in
    :func:`haar2_block`) and one Hermite problem for sigma. Energies are measured from the
    minimum of V (no shift of Z). ``error`` (if ``check``) is the larger change of Z under a
    basis 10 smaller and a scale 1.2 times wider; scales default to the harmonic lengths at
    the minima of V_x (x = 0) and V_sigma.
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


# ------------------------------------------------- n = 3: spin = vorticity = 1 and af-is
@dataclass(frozen=True)
class Jet:
    """A function on a quadrature grid with its gradient: value [P], grad [P, 3]."""

    value: np.ndarray
    grad: np.ndarray

    def __add__(self, other: Jet) -> Jet:
        return Jet(self.value + other.value, self.grad + other.grad)

    def __sub__(self, other: Jet) -> Jet:
        return Jet(self.value - other.value, self.grad - other.grad)

    def __mul__(self, other: Jet | float) -> Jet:
        if isinstance(other, Jet):
            return Jet(self.value * other.value,
                       self.grad * other.value[:, None] + other.grad * self.value[:, None])
        return Jet(self.value * other, self.grad * other)

    def apply(self, f: Callable, df: Callable) -> Jet:
        return Jet(f(self.value), df(self.value)[:, None] * self.grad)

    @staticmethod
    def coordinates(x: np.ndarray) -> list[Jet]:
        eye = np.eye(3)
        return [Jet(x[:, a], np.broadcast_to(eye[a], x.shape).copy()) for a in range(3)]

    @staticmethod
    def one(points: int) -> Jet:
        return Jet(np.ones(points), np.zeros((points, 3)))


@dataclass(frozen=True)
class Grid3:
    """Reduced-space quadrature for n = 3: nodes x [P, 3] (Q or q), weights [P] with the
    measure J of the reduction (prod |Q_a^2 - Q_b^2| or prod sinh(q_a - q_b)) included."""

    nodes: np.ndarray
    weights: np.ndarray


def haar3_grid(scale: float, scale_sigma: float, centre: float, n_r: int, n_angle: int,
               n_sigma: int) -> Grid3:
    """Quadrature on the chamber q1 > q2 > q3 with weight prod_{a<b} sinh(q_a - q_b) dq.

    q = (sigma/3)(1, 1, 1) + r (cos t e_u + sin t e_v), e_u = (1, -1, 0)/sqrt2,
    e_v = (1, 1, -2)/sqrt6, chamber t in (pi/6, pi/2), dq = r dr dt dsigma / sqrt3;
    Gauss-Legendre in r on [0, 9 scale] and in t, Gauss-Hermite in sigma (centre, scale_sigma).
    """
    xr, wr = special.roots_legendre(n_r)
    r_max = 9.0 * scale
    r, w_r = r_max * (xr + 1) / 2, r_max * wr / 2
    xt, wt = special.roots_legendre(n_angle)
    t, w_t = np.pi / 6 + (np.pi / 3) * (xt + 1) / 2, (np.pi / 3) * wt / 2
    z, w_z = special.roots_hermite(n_sigma)
    sigma, w_s = centre + scale_sigma * z, scale_sigma * w_z * np.exp(z * z)
    eu = np.array([1.0, -1.0, 0.0]) / math.sqrt(2)
    ev = np.array([1.0, 1.0, -2.0]) / math.sqrt(6)
    R, T, S = np.meshgrid(r, t, sigma, indexing="ij")
    q = (S[..., None] / 3 + R[..., None] * (np.cos(T)[..., None] * eu
                                            + np.sin(T)[..., None] * ev)).reshape(-1, 3)
    w = (w_r[:, None, None] * r[:, None, None] * w_t[None, :, None] * w_s[None, None, :]
         ).ravel() / math.sqrt(3)
    J = np.sinh(q[:, 0] - q[:, 1]) * np.sinh(q[:, 0] - q[:, 2]) * np.sinh(q[:, 1] - q[:, 2])
    return Grid3(q, w * J)


def _sqrt_x_over_sinh_derivative_ratio(x: np.ndarray) -> np.ndarray:
    """d/dx log sqrt(x / sinh x) = (1/x - coth x)/2, smooth (-> -x/6 at 0)."""
    small = np.abs(x) < 1e-3
    safe = np.where(small, 1.0, x)
    return np.where(small, -x / 6, 0.5 * (1 / safe - 1 / np.tanh(safe)))


def _channel_candidates(kind: str, x: np.ndarray, degree: int, scale: float,
                        scale_sigma: float, centre: float, spin1: bool
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate basis functions on the grid: values [P, d, K], gradients [P, d, 3, K] and the
    parity class [K] (d = 1 scalar, d = 3 for spin = vorticity = 1).

    "lebesgue3" (d'Alembert, x = Q): Gaussian e^{-|Q|^2/2b^2} times invariant polynomials of
    the Weyl group (permutations, even sign changes; generated by p2, e3 = Q1 Q2 Q3, p4) times,
    for spin 1, the equivariant generators grad p2 ~ Q, grad e3 = (Q2 Q3, Q1 Q3, Q1 Q2),
    grad p4 ~ Q^3 (the covariants of a reflection group are free over the invariants with the
    gradients of the basic invariants as basis). Parity under phi -> -phi: (-1)^degree.
    "haar3" (af-is, x = q): g(q) = prod sqrt((q_a - q_b)/sinh(q_a - q_b)) times the Gaussian
    in the traceless part y (scale b) and in sigma = sum q (scale_sigma, centre) times S3
    invariants (sigma, sum y^2, sum y^3) times, for spin 1, the generators 1, y, y^2.
    """
    jets = Jet.coordinates(x)
    P = x.shape[0]
    if kind == "lebesgue3":
        y = [j * (1 / scale) for j in jets]
        p2 = y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
        gauss = p2.apply(lambda v: np.exp(-0.5 * v), lambda v: -0.5 * np.exp(-0.5 * v))
        inv = {"p2": (p2, 2), "e3": (y[0] * y[1] * y[2], 3),
               "p4": (y[0] * y[0] * y[0] * y[0] + y[1] * y[1] * y[1] * y[1]
                      + y[2] * y[2] * y[2] * y[2], 4)}
        vectors = [(y, 1), ([y[1] * y[2], y[0] * y[2], y[0] * y[1]], 2),
                   ([v * v * v for v in y], 3)]
        front = gauss
    else:
        mean = (jets[0] + jets[1] + jets[2]) * (1 / 3)
        y = [(j - mean) * (1 / scale) for j in jets]
        t = (jets[0] + jets[1] + jets[2] - Jet(np.full(P, centre), np.zeros((P, 3)))) * (
            1 / scale_sigma)
        p2 = y[0] * y[0] + y[1] * y[1] + y[2] * y[2]
        gexp = (p2 + t * t).apply(lambda v: np.exp(-0.5 * v), lambda v: -0.5 * np.exp(-0.5 * v))
        g = Jet.one(P)
        for a, b in ((0, 1), (0, 2), (1, 2)):
            diff = jets[a] - jets[b]
            g = g * diff.apply(sqrt_x_over_sinh, lambda v: sqrt_x_over_sinh(v)
                               * _sqrt_x_over_sinh_derivative_ratio(v))
        front = g * gexp
        inv = {"t": (t, 1), "p2": (p2, 2),
               "p3": (y[0] * y[0] * y[0] + y[1] * y[1] * y[1] + y[2] * y[2] * y[2], 3)}
        one = Jet.one(P)
        vectors = [([one, one, one], 0), (y, 1), ([v * v for v in y], 2)]
    names = list(inv)
    degrees = [inv[k][1] for k in names]
    monomials = [e for e in product(*(range(degree // dg + 1) for dg in degrees))
                 if sum(k * dg for k, dg in zip(e, degrees, strict=True)) <= degree]
    monomials.sort(key=lambda e: sum(k * dg for k, dg in zip(e, degrees, strict=True)))
    values, grads, parity = [], [], []
    cache: dict[tuple, Jet] = {}

    def monomial(e: tuple) -> Jet:
        if e in cache:
            return cache[e]
        if not any(e):
            out = front
        else:
            i = next(i for i, k in enumerate(e) if k)
            lower = tuple(k - (j == i) for j, k in enumerate(e))
            out = monomial(lower) * inv[names[i]][0]
        cache[e] = out
        return out

    for e in monomials:
        deg = sum(k * dg for k, dg in zip(e, degrees, strict=True))
        base = monomial(e)
        if not spin1:
            values.append(base.value[:, None])
            grads.append(base.grad[:, None, :])
            parity.append((-1) ** deg)
            continue
        for vec, vdeg in vectors:
            if deg + vdeg > degree:
                continue
            comps = [base * v for v in vec]
            values.append(np.stack([c.value for c in comps], axis=1))
            grads.append(np.stack([c.grad for c in comps], axis=1))
            parity.append((-1) ** (deg + vdeg))
    return np.stack(values, -1), np.stack(grads, -1), np.array(parity)


def channel3_block(kind: str, potential: Potential, hbar: float, inertia: AffineInertia | float,
                   grid: Grid3, degree: int, scale: float, scale_sigma: float = 1.0,
                   centre: float = 0.0, spin1: bool = False) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of an n = 3 sector, scalar (spin = vorticity = 0) or spin =
    vorticity = 1 (reduction.py: Psi = sum_a f_a(x) (L^T u)_a (R^T w)_a, norm sum_a int f_a^2 J),
    in the weak form

        int [ (hbar^2/2) sum_a grad f_a . G grad f_a + V |f|^2
              + sum_{a<b} 2 hbar^2 (c_+^{ab} (f_a - f_b)^2 + c_-^{ab} (f_a + f_b)^2)
              + 2 hbar^2 (c_rho + c_tau) |f|^2 ] J dx,

    the quadratic form of U_sector of reduction.py restricted to diagonal F (checked against
    ``TwoPolarReduction.sector_potential`` in the tests). d'Alembert ("lebesgue3"): G = Id/I,
    c_+ = 1/(4 I (Q_a - Q_b)^2), c_- = 1/(4 I (Q_a + Q_b)^2), no constant. Affine ("haar3"):
    G = Id/M - B/(M (M + 3B)), c_+ = 1/(16 M sinh^2((q_a - q_b)/2)),
    c_- = -1/(16 M cosh^2(...)), 2 (c_rho + c_tau) = 1/I~ (af-is, is-af) or 0 (af-af).
    The candidates of :func:`_channel_candidates` are orthonormalised (QR) under the measure.
    """
    x, w = grid.nodes, grid.weights
    vals, grads, parity = _channel_candidates(kind, x, degree, scale, scale_sigma, centre, spin1)
    order = np.argsort(-parity, kind="stable")  # even first: odd ones orthogonalised to them
    vals, grads, parity = vals[..., order], grads[..., order], parity[order]
    P, d, K = vals.shape
    sw = np.sqrt(w)[:, None, None]
    Qr, Rr = np.linalg.qr((sw * vals).reshape(P * d, K))
    keep = np.abs(np.diag(Rr)) > 1e-10 * np.max(np.abs(np.diag(Rr)))
    T = linalg.solve_triangular(Rr[np.ix_(keep, keep)], np.eye(int(keep.sum())))
    vals = vals[..., keep] @ T
    grads = grads[..., keep] @ T
    parity = parity[keep]
    H, S = channel3_forms(kind, potential, hbar, inertia, grid, vals, grads, spin1)
    # the basis is orthonormal up to rounding: finish with a Cholesky change of basis
    Lc = np.linalg.cholesky(0.5 * (S + S.T))
    Linv = linalg.solve_triangular(Lc, np.eye(len(S)), lower=True)
    H = Linv @ H @ Linv.T
    data = (kind, grid, vals @ Linv.T, parity, spin1)
    return 0.5 * (H + H.T), Basis("grid3", data)


def channel3_forms(kind: str, potential: Potential, hbar: float,
                   inertia: AffineInertia | float, grid: Grid3, vals: np.ndarray,
                   grads: np.ndarray, spin1: bool) -> tuple[np.ndarray, np.ndarray]:
    """(H, S): the weak-form Hamiltonian and the Gram matrix of :func:`channel3_block` for
    functions given by values [P, d, K] and gradients [P, d, 3, K] on ``grid``."""
    x, w = grid.nodes, grid.weights
    if kind == "lebesgue3":
        I_ = float(inertia)
        G = np.eye(3) / I_
        coords = "Q"
    else:
        M = inertia.M
        G = np.eye(3) / M - inertia.B / (M * (M + 3 * inertia.B)) * np.ones((3, 3))
        coords = "q"
    Q = x if coords == "Q" else np.exp(x)
    V = np.asarray(potential(Q), float)
    gradG = np.matmul(G, grads)  # [P, d, 3, K]: G acts on the gradient index

    def gram(left: np.ndarray, weight: np.ndarray, right: np.ndarray) -> np.ndarray:
        shape = (1,) * (left.ndim - 2)
        lw = left * weight.reshape((-1,) + shape + (1,))
        return lw.reshape(-1, left.shape[-1]).T @ right.reshape(-1, right.shape[-1])

    H = (hbar**2 / 2) * gram(gradG, w, grads)
    H += gram(vals, w * V, vals)
    if spin1:
        for a, b in ((0, 1), (0, 2), (1, 2)):
            # divided difference (f_a - f_b)/(x_a - x_b): finite at the wall x_a = x_b
            diff = (vals[:, a] - vals[:, b]) / (x[:, a] - x[:, b])[:, None]
            both = vals[:, a] + vals[:, b]
            if kind == "lebesgue3":
                w_diff = (hbar**2 / (2 * I_)) * w  # 2 hbar^2 c_+ (Q_a - Q_b)^2
                both = both / (x[:, a] + x[:, b])[:, None]
                w_both = (hbar**2 / (2 * I_)) * w  # 2 hbar^2 c_- (Q_a + Q_b)^2
            else:
                h = 0.5 * (x[:, a] - x[:, b])
                w_diff = 2 * hbar**2 * w * (2 * h) ** 2 / (16 * M * np.sinh(h) ** 2)
                w_both = -2 * hbar**2 * w / (16 * M * np.cosh(h) ** 2)
            H += diff.T @ (w_diff[:, None] * diff) + both.T @ (w_both[:, None] * both)
        if kind == "haar3":
            H += hbar**2 * inertia.inv_I_tilde * gram(vals, w, vals)
    return H, gram(vals, w, vals)


def auto_scale_haar3(potential: Potential, hbar: float, inertia: AffineInertia
                     ) -> tuple[float, float, float]:
    """(scale, scale_sigma, centre) of the n = 3 affine basis minimising the sum of the two
    lowest scalar levels in a small basis (clipped: a continuous spectrum drives the scales
    to the clip, where the honesty check flags the pseudo-levels)."""
    sig = np.linspace(-12, 12, 241)
    line = np.asarray(potential(np.exp(np.stack([sig / 3] * 3, axis=-1))), float)
    centre0 = float(sig[np.argmin(np.where(np.isfinite(line), line, np.inf))])

    def energy(p):
        b, bs = np.exp(np.clip(p[:2], -3, 1.5))
        grid = haar3_grid(b, bs, p[2], 24, 10, 12)
        H, _ = channel3_block("haar3", potential, hbar, inertia, grid, 4, b, bs, p[2])
        return float(np.sum(linalg.eigvalsh(H)[:2]))
    p = _variational(energy, np.array([-0.5, -0.5, centre0]))
    b, bs = np.exp(np.clip(p[:2], -3, 1.5))
    return float(b), float(bs), float(p[2])


def _solve_n3(model: str, potential: Potential, hbar: float, inertia_scalar: float,
              inertia: AffineInertia, levels: int, settings: Settings, sectors: str) -> Spectrum:
    """n = 3: the scalar and/or spin = vorticity = 1 sectors by :func:`channel3_block`."""
    blocks: dict[tuple, Block] = {}
    entries: list = []
    unconverged: list[Level] = []
    info: dict = {"basis_size": settings.basis_size}
    degree = settings.basis_size
    count = levels + 4
    wanted = {"scalar": (False,), "spin1": (True,), "scalar+spin1": (False, True)}[sectors]
    if model == "dalembert":
        b = settings.scale or auto_scale_scalar3(potential, hbar, inertia_scalar)
        info["scale"] = b
        quad = ChamberQuadrature.build(b * (8.0 + 0.75 * math.sqrt(degree + 1)),
                                       n_rho=40 + 2 * degree, n_angle=16 + degree)
        grid = Grid3(quad.nodes, quad.weights)
        flip = quad.nodes * np.array([1.0, 1.0, -1.0])
        symmetric = np.allclose(potential(flip), potential(quad.nodes), rtol=1e-12, atol=1e-12)

        def build(spin1):
            # a Gaussian of another width is a poor polynomial basis: degree check only
            return lambda d, sc: channel3_block("lebesgue3", potential, hbar, inertia_scalar,
                                                grid, d, sc, spin1=spin1)
        check = replace(settings, check_widen=1.0)
    else:
        if settings.scale is None or settings.scale_sigma is None or settings.centre is None:
            b, bs, c0 = auto_scale_haar3(potential, hbar, inertia)
        b = settings.scale or b
        bs = settings.scale_sigma or bs
        c0 = c0 if settings.centre is None else settings.centre
        info.update(scale=b, scale_sigma=bs, centre=c0)
        symmetric = False  # -phi is not in GL+(3)

        def build(spin1):
            def block(d, sc):
                grid = haar3_grid(sc, bs * sc / b, c0, 20 + 2 * d, 10 + d, 6 + d)
                return channel3_block("haar3", potential, hbar, inertia, grid, d, sc,
                                      bs * sc / b, c0, spin1=spin1)
            return block
        # widening the Gaussian by 1.3 leaves the polynomial space too far for a check at
        # 1e-7; 1.1 still moves every pseudo-level of a continuous spectrum by far more
        check = replace(settings, check_widen=min(settings.check_widen, 1.1))
    for spin1 in wanted:
        E, vec, err, basis = _solve_block(build(spin1), degree, info["scale"], count, check)
        parity = basis.factors[3]
        for i in range(len(E)):
            even = float(np.sum(vec[parity == 1, i] ** 2))
            p = 1 if even > 1 - 1e-8 else (-1 if even < 1e-8 else None)
            j = 1 if spin1 else 0
            sec = (Sector(j, j, p if symmetric else None, (2 * j + 1) ** 2),)
            key = ("spin1" if spin1 else "scalar", i)
            blocks[key] = Block(key, sec, basis, E[i:i + 1], vec[:, i:i + 1], err[i:i + 1])
            if _converged(E[i], err[i], settings):
                entries.append((float(E[i]), float(err[i]), sec, key, 0))
            else:
                unconverged.append(Level(float(E[i]), _states(sec), sec, float(err[i]), key, 0))
    label = {"scalar": "(0, 0)", "spin1": "(1, 1)", "scalar+spin1": "(0, 0) and (1, 1)"}
    warnings = [_N3_PARTIAL.format(sectors=label[sectors])]
    bounded = True
    if model == "af-af":
        bounded = False
        warnings.append("af-af: the kinetic energy (72) is indefinite; the sectors computed are "
                        "bounded below but the sum over all sectors (j, j') is not (the n = 2 "
                        "mechanism: -hbar^2 (rho - tau)^2 / (16 A cosh^2) wells that deepen "
                        "with the spin)")
    merged = _truncate(_merge(entries, settings), levels)
    unconverged.sort(key=lambda lv: lv.energy)
    return Spectrum(merged, unconverged, blocks, model, 3, sectors, info, bounded, warnings)
