"""n = 3, the dedicated bases of the two lowest SO(3) x SO(3) sectors, scalar (0, 0) and
spin = vorticity = 1 (1, 1) (``quantum.sectors = "scalar"``, ``"spin1"``, ``"scalar+spin1"``), and
the quadratures of the Weyl chamber shared with :mod:`affinebody.quantum.n3` (paper, last
section; reduction.py for the operator; spectra.py for the result types).

Quadratures: Q_1 > Q_2 > |Q_3| with prod |Q_a^2 - Q_b^2| (d'Alembert, :class:`ChamberQuadrature`)
and q_1 > q_2 > q_3 with prod sinh(q_a - q_b) (affine models, :func:`haar3_grid`).

Dedicated sectors:

* d'Alembert, the scalar sector (spin = vorticity = 0): functions of Q invariant under the
  Weyl group (permutations and even sign changes of Q). Basis: Gaussian times invariant
  polynomials in p2 = sum Q^2, e3 = Q1 Q2 Q3, p4 = sum Q^4, orthonormalised under
  prod (Q_a^2 - Q_b^2) dQ on the chamber Q_1 > Q_2 > |Q_3| by an Arnoldi process on a
  quadrature grid (radial Gauss-Legendre x Duffy-mapped triangle). Contains every oscillator
  eigenfunction of degree <= the basis degree, so the oscillator is exact.
* scalar and spin = vorticity = 1, d'Alembert and the affine models (:func:`channel3_block`):
  Weyl-invariant (resp. equivariant) polynomials times a Gaussian, orthonormalised by QR on
  the chamber grid; for the affine models times g(q) = prod sqrt((q_a - q_b) /
  sinh(q_a - q_b)).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from itertools import product

import numpy as np
from scipy import linalg, special

from affinebody.quantum.bases import (
    Basis,
    centre_runs_away,
    lowest_sum,
    runaway_message,
    solve_block,
    sqrt_x_over_sinh,
    sqrt_x_over_sinh_derivative_ratio,
    variational_parameters,
    variational_scales,
)
from affinebody.quantum.levels import (
    AffineInertia,
    LevelCollector,
    Potential,
    Sector,
    Settings,
    Spectrum,
)

_N3_PARTIAL = ("n = 3: only the (spin, vorticity) sectors {sectors} are computed; states of the "
               "other SO(3) x SO(3) sectors (j, j') are not in this list")


# ------------------------------------------------------- quadratures and the scalar basis
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
        omega, w_ang = cls.sphere(n_angle)
        Q = (rho[:, None, None] * omega[None, :, :]).reshape(-1, 3)
        # int f(Q) J(Q) dQ = int rho^8 drho int_sphere f J(omega) dOmega (J of degree 6)
        return cls(Q, (w_rho[:, None] * rho[:, None] ** 8 * w_ang[None, :]).ravel())

    @classmethod
    def polar(cls, rho_max: float, n_rho: int, n_angle: int) -> ChamberQuadrature:
        """The same integral with the chamber's spherical triangle in polar angles about e_3,
        omega = (sin t cos p, sin t sin p, cos t): Q_1 > Q_2 > |Q_3| is 0 < p < pi/4,
        |cos t| < sin t sin p; Gauss-Legendre in p and in t (per p), so an integrand smooth on
        the sphere converges exponentially (the Duffy map of :meth:`sphere` divides by |y|)."""
        xr, wr = special.roots_legendre(n_rho)
        rho, w_rho = rho_max * (xr + 1) / 2, rho_max * wr / 2
        x, w = special.roots_legendre(n_angle)
        p, wp = np.pi / 8 * (x + 1), np.pi / 8 * w
        half = np.pi / 2 - np.arctan2(1.0, np.sin(p))  # t in pi/2 +- half
        t = np.pi / 2 + half[:, None] * x[None]
        wa = wp[:, None] * half[:, None] * w[None] * np.sin(t)
        P = np.broadcast_to(p[:, None], t.shape)
        omega = np.stack([np.sin(t) * np.cos(P), np.sin(t) * np.sin(P), np.cos(t)], -1)
        omega, wa = omega.reshape(-1, 3), wa.ravel()
        J = (omega[:, 0] ** 2 - omega[:, 1] ** 2) * (omega[:, 0] ** 2 - omega[:, 2] ** 2) * (
            omega[:, 1] ** 2 - omega[:, 2] ** 2)
        Q = (rho[:, None, None] * omega[None, :, :]).reshape(-1, 3)
        return cls(Q, (w_rho[:, None] * rho[:, None] ** 8 * (wa * J)[None, :]).ravel())

    @staticmethod
    def sphere(n_angle: int = 28) -> tuple[np.ndarray, np.ndarray]:
        """Nodes omega [P, 3] on the unit sphere of the chamber and weights with J(omega) =
        prod(omega_a^2 - omega_b^2) included: int over the chamber of f(Q) J(Q) dQ =
        int_0^inf rho^8 drho sum_p w_p f(rho omega_p) (dQ = rho^2 drho dOmega, J of degree 6)."""
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
        omega = y / ny[:, None]
        J = (omega[:, 0] ** 2 - omega[:, 1] ** 2) * (omega[:, 0] ** 2 - omega[:, 2] ** 2) * (
            omega[:, 1] ** 2 - omega[:, 2] ** 2)
        return omega, w_ang * J


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
class ScalarBasis3:
    """Weyl-invariant polynomials of degree <= ``degree`` times e^{-|Q|^2/2b^2}, orthonormal
    under prod (Q_a^2 - Q_b^2) dQ on the chamber (Arnoldi on a quadrature grid).

    ``recipe[j - 1] = (parent, generator, c, norm)``: phi_j = (g phi_parent -
    sum_{i < j} c_i phi_i) / norm with ``c`` [j] the Gram-Schmidt coefficients over every
    earlier function, replayable at any points. ``parity`` of phi_j under Q_3 -> -Q_3
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
        """Values [..., K] of the basis at points ``Q`` [..., 3]; with ``with_gradient`` also
        their gradients [..., 3, K] (replaying :attr:`recipe`)."""
        values, grads = self._replay(np.asarray(Q, float), with_gradient)
        lead, K = np.shape(Q)[:-1], len(values)
        if with_gradient:
            return (values.T.reshape(lead + (K,)),
                    grads.transpose(2, 1, 0).reshape(lead + (3, K)))
        return values.T.reshape(lead + (K,))

    def _replay(self, Q: np.ndarray, with_gradient: bool):
        """Values [K, P] and gradients [K, 3, P] (None without ``with_gradient``) at the points
        ``Q`` [..., 3] flattened to [P, 3], one row per function: each step subtracts its
        coefficients times the rows before it as one matrix-vector product."""
        Q = Q.reshape(-1, 3)
        points, K = len(Q), len(self.recipe) + 1
        gens = self._generators(Q, self.scale)
        values = np.empty((K, points))
        values[0] = np.exp(-0.5 * np.sum(Q * Q, axis=-1) / self.scale**2) / self.norm0
        grads = None
        if with_gradient:
            grads = np.empty((K, 3, points))
            grads[0] = (-Q.T / self.scale**2) * values[0]
        for j, (parent, gen, coeffs, norm) in enumerate(self.recipe, start=1):
            g, dg = gens[gen]
            values[j] = (g * values[parent] - coeffs @ values[:j]) / norm
            if with_gradient:
                d = dg.T * values[parent] + g * grads[parent]
                grads[j] = (d - (coeffs @ grads[:j].reshape(j, -1)).reshape(3, points)) / norm
        return values, grads

    @classmethod
    def build(cls, degree: int, scale: float, quad: ChamberQuadrature) -> ScalarBasis3:
        Q, w = quad.nodes, quad.weights
        gens = cls._generators(Q, scale)
        r2 = np.sum(Q * Q, axis=-1) / scale**2
        f0 = np.exp(-0.5 * r2)
        norm0 = math.sqrt(float(np.sum(w * f0 * f0)))
        monomials = sorted(
            ((i, j, k) for i in range(degree // 2 + 1) for j in range(degree // 3 + 1)
             for k in range(degree // 4 + 1) if 2 * i + 3 * j + 4 * k <= degree and (i, j, k)
             != (0, 0, 0)),
            key=lambda e: (2 * e[0] + 3 * e[1] + 4 * e[2], e[1], e[2]))
        vals = np.empty((len(monomials) + 1, len(Q)))  # row k: the k-th orthonormal function
        vals[0] = f0 / norm0
        parity = [1]
        recipe = []
        index = {(0, 0, 0): 0}
        for k, mono in enumerate(monomials, start=1):
            gen = next(a for a in range(3) if mono[a] > 0)
            parent_mono = tuple(e - (a == gen) for a, e in enumerate(mono))
            parent = index[parent_mono]
            v = gens[gen][0] * vals[parent]
            coeffs = np.zeros(k)
            for _ in range(2):  # classical Gram-Schmidt, twice
                c = vals[:k] @ (w * v)
                v = v - c @ vals[:k]
                coeffs += c
            norm = math.sqrt(float(np.sum(w * v * v)))
            index[mono] = k
            vals[k] = v / norm
            parity.append((-1) ** mono[1])
            recipe.append((parent, gen, coeffs, norm))
        return cls(degree, scale, tuple(recipe), np.array(parity), norm0)


# ----------------------------- dedicated channels: scalar (0, 0) and spin = vorticity = 1
def scalar3_block(potential: Potential, hbar: float, inertia: float, degree: int, scale: float,
                  quad: ChamberQuadrature | None = None) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of the n = 3 d'Alembert scalar sector (spin = vorticity = 0):
    H = -(hbar^2/2I)(1/J_L) sum_a d_a J_L d_a + V (docs/theory/two-polar.md), weak form
    int [(hbar^2/2I) grad f . grad g + V f g] J_L dQ on the chamber (natural boundary)."""
    quad = quad or ChamberQuadrature.build(scale * (8.0 + 0.75 * math.sqrt(degree + 1)),
                                           n_rho=40 + 2 * degree, n_angle=16 + degree)
    basis = ScalarBasis3.build(degree, scale, quad)
    F, dF = basis._replay(quad.nodes, with_gradient=True)  # [K, P], [K, 3, P]
    w = quad.weights
    V = np.asarray(potential(quad.nodes), float)
    H = F @ (F * (w * V)).T
    # sum_p w_p grad f_i . grad f_j as one product of [K, 3P] matrices
    H += (hbar**2 / (2 * inertia)) * (dF.reshape(len(dF), -1)
                                      @ (dF * w).reshape(len(dF), -1).T)
    return 0.5 * (H + H.T), Basis("scalar3", (basis,))


def channel_candidates(kind: str, x: np.ndarray, degree: int, scale: float,
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
                               * sqrt_x_over_sinh_derivative_ratio(v))
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
    The candidates of :func:`channel_candidates` are orthonormalised (QR) under the measure.
    """
    x, w = grid.nodes, grid.weights
    vals, grads, parity = channel_candidates(kind, x, degree, scale, scale_sigma, centre, spin1)
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


def auto_scale_scalar3(potential: Potential, hbar: float, inertia: float) -> float:
    quad = ChamberQuadrature.build(12.0, 40, 16)

    def energy(logb):
        b = float(np.exp(np.clip(logb[0], -2.4, 0.4)))
        H, _ = scalar3_block(potential, hbar, inertia, 4, b, quad)
        return lowest_sum(H, 2)
    return float(np.exp(np.clip(variational_parameters(energy, np.array([-0.5]))[0], -2.4, 0.4)))


def auto_scale_haar3(potential: Potential, hbar: float, inertia: AffineInertia,
                     given: tuple[float | None, float | None, float | None] = (None,) * 3
                     ) -> tuple[float, float, float]:
    """(scale, scale_sigma, centre) of the n = 3 affine basis minimising the sum of the two
    lowest scalar levels in a small basis, over those of the three that ``given`` leaves None
    (clipped: a continuous spectrum drives the scales to the clip, where the honesty check
    flags the pseudo-levels; a centre with no minimum, V not confining det phi, is refused by
    :func:`setup3`, :func:`~affinebody.quantum.bases.centre_runs_away`)."""
    sig = np.linspace(-12, 12, 241)
    line = np.asarray(potential(np.exp(np.stack([sig / 3] * 3, axis=-1))), float)
    centre0 = float(sig[np.argmin(np.where(np.isfinite(line), line, np.inf))])
    return variational_scales(_haar3_objective(potential, hbar, inertia), (-0.5, -0.5, centre0),
                              given, (-3, 1.5))


def _haar3_objective(potential: Potential, hbar: float, inertia: AffineInertia):
    """What :func:`auto_scale_haar3` minimises: the sum of the two lowest scalar levels in the
    basis of degree 4 at (scale, scale_sigma, centre)."""
    def energy(b, bs, c):
        grid = haar3_grid(b, bs, c, 24, 10, 12)
        H, _ = channel3_block("haar3", potential, hbar, inertia, grid, 4, b, bs, c)
        return lowest_sum(H, 2)
    return energy


# -------------------------------------------------------------------------------- solvers
@dataclass(frozen=True)
class Setup3:
    """The discretisation every n = 3 solver shares: basis scales (variational unless given),
    the quadrature grid, whether phi -> -phi is a symmetry, and the convergence checks.

    d'Alembert: one chamber grid for every degree (the polynomial degree is the check: a
    Gaussian of another width is a poor polynomial basis, so no widened basis). Affine: a Haar
    grid per (degree, scale) and a basis 1.1 times wider as the second check (1.3 leaves the
    polynomial space too far for 1e-7; 1.1 still moves every pseudo-level of a continuous
    spectrum by far more)."""

    kind: str
    scale: float
    scale_sigma: float
    centre: float
    chamber: ChamberQuadrature | None
    parity_symmetric: bool
    check: Settings

    def grid(self, degree: int, scale: float):
        if self.chamber is not None:
            return self.chamber
        return haar3_grid(scale, self.sigma_scale(scale), self.centre, 20 + 2 * degree,
                          10 + degree, 6 + degree)

    def sigma_scale(self, scale: float) -> float:
        """The sigma scale that goes with ``scale`` (both widen together)."""
        return self.scale_sigma * scale / self.scale

    def info(self, settings: Settings) -> dict:
        out = {"basis_size": settings.basis_size, "scale": self.scale}
        if self.kind == "haar3":
            out.update(scale_sigma=self.scale_sigma, centre=self.centre)
        return out


def setup3(model: str, potential: Potential, hbar: float, inertia_scalar: float,
           inertia: AffineInertia, settings: Settings) -> Setup3:
    """:class:`Setup3` for ``model`` (d'Alembert with J = inertia_scalar * Id, or an affine
    model with ``inertia``)."""
    degree = settings.basis_size
    if model == "dalembert":
        b = settings.scale or auto_scale_scalar3(potential, hbar, inertia_scalar)
        quad = ChamberQuadrature.build(b * (8.0 + 0.75 * math.sqrt(degree + 1)),
                                       n_rho=40 + 2 * degree, n_angle=16 + degree)
        # parity under phi -> -phi is a symmetry iff V(Q1, Q2, -Q3) = V(Q)
        flip = quad.nodes * np.array([1.0, 1.0, -1.0])
        symmetric = bool(np.allclose(potential(flip), potential(quad.nodes), rtol=1e-12,
                                     atol=1e-12))
        return Setup3("lebesgue3", b, 1.0, 0.0, quad, symmetric,
                      replace(settings, check_widen=1.0))
    b, bs, c0 = settings.scale, settings.scale_sigma, settings.centre
    if b is None or bs is None or c0 is None:
        b, bs, c0 = auto_scale_haar3(potential, hbar, inertia, (b, bs, c0))
    if settings.centre is None and centre_runs_away(_haar3_objective(potential, hbar, inertia),
                                                    b, bs, c0):
        # V does not confine det phi: every level a basis finds is a pseudo-level, so say so
        # now rather than after the search over every sector (README's potential with af-is:
        # over 12 min of CPU, then 'not converged')
        raise ValueError(runaway_message(model, b, bs, c0, n=3))
    # -phi is not in GL+(3): no parity
    return Setup3("haar3", b, bs, c0, None, False,
                  replace(settings, check_widen=min(settings.check_widen, 1.1)))


def solve_dalembert_scalar(potential: Potential, hbar: float, inertia: float, levels: int,
                           settings: Settings) -> Spectrum:
    """n = 3 d'Alembert, the scalar sector only (``sectors="scalar"``), in the Weyl-invariant
    Arnoldi basis of :func:`scalar3_block`; J = inertia * Id."""
    setup = setup3("dalembert", potential, hbar, inertia, None, settings)
    E, vec, err, basis = solve_block(
        lambda d, s: scalar3_block(potential, hbar, inertia, d, s, setup.chamber),
        settings.basis_size, setup.scale, levels + 4, setup.check)
    found = LevelCollector(settings)
    found.record_each(("scalar",), lambda p: (Sector(0, 0, p if setup.parity_symmetric
                                                     else None),),
                      basis, E, vec, err, basis.factors[0].parity)
    merged, unconverged = found.levels(None)  # one block: every level it resolves
    return Spectrum(merged, unconverged, found.blocks, "dalembert", 3, "scalar",
                    setup.info(settings), True, [_N3_PARTIAL.format(sectors="(0, 0)")],
                    certified=False, certificate="partial: the (0, 0) sector only",
                    requested=levels)


def solve_channels(model: str, potential: Potential, hbar: float, inertia_scalar: float,
                   inertia: AffineInertia, levels: int, settings: Settings, sectors: str
                   ) -> Spectrum:
    """n = 3: the scalar and/or spin = vorticity = 1 sectors (``sectors`` "scalar", "spin1",
    "scalar+spin1") in the dedicated bases of :func:`channel3_block`."""
    setup = setup3(model, potential, hbar, inertia_scalar, inertia, settings)
    physical = inertia_scalar if setup.kind == "lebesgue3" else inertia
    found = LevelCollector(settings)
    for spin1 in {"scalar": (False,), "spin1": (True,), "scalar+spin1": (False, True)}[sectors]:
        def block(d, sc, spin1=spin1):
            return channel3_block(setup.kind, potential, hbar, physical, setup.grid(d, sc), d,
                                  sc, setup.sigma_scale(sc), setup.centre, spin1=spin1)
        E, vec, err, basis = solve_block(block, settings.basis_size, setup.scale, levels + 4,
                                         setup.check)
        j = 1 if spin1 else 0
        found.record_each(("spin1" if spin1 else "scalar",),
                          lambda p, j=j: (Sector(j, j, p if setup.parity_symmetric else None,
                                                 (2 * j + 1) ** 2),),
                          basis, E, vec, err, basis.factors[3])
    label = {"scalar": "(0, 0)", "spin1": "(1, 1)", "scalar+spin1": "(0, 0) and (1, 1)"}
    warnings = [_N3_PARTIAL.format(sectors=label[sectors])]
    bounded = True
    if model == "af-af":
        bounded = False
        warnings.append("af-af: the kinetic energy (72) is indefinite; the sectors computed are "
                        "bounded below but the sum over all sectors (j, j') is not (the n = 2 "
                        "mechanism: -hbar^2 (rho - tau)^2 / (16 A cosh^2) wells that deepen "
                        "with the spin)")
    merged, unconverged = found.levels(levels)
    return Spectrum(merged, unconverged, found.blocks, model, 3, sectors,
                    setup.info(settings), bounded, warnings, certified=False,
                    certificate=f"partial: the sectors {sectors} only", requested=levels)


__all__ = ["ChamberQuadrature", "Grid3", "haar3_grid", "Jet", "ScalarBasis3", "scalar3_block",
           "channel3_block", "channel3_forms", "auto_scale_scalar3", "auto_scale_haar3",
           "Setup3", "setup3", "solve_dalembert_scalar", "solve_channels",
           "channel_candidates",
]
