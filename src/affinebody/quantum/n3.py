"""The n = 3 quantum affine body: every SO(3) x SO(3) sector (spin j, vorticity j') of the
two-polar reduction as a Galerkin eigenproblem (``quantum.sectors = "all"``; paper, last
section; reduction.py for the operator; covariants3.py for the angular part; channels3.py for
the chamber quadratures and the dedicated bases of the sectors (0, 0) and (1, 1); spectra.py
for the result types and the n = 2 solvers).

General sectors. A state of the sector is psi_c(phi) = <c, Psi(phi)>, Psi a covariant, f(x) =
Psi(diag x) its values on the Weyl chamber, in the M-fixed subspace of V_j (x) V_j'
(coordinates f_r, r = covariants3.fixed_dimension(j, j')). The weak form of H on the sector is

    int [ (hbar^2/2) sum_ab G^ab d_a f . d_b f + V |f|^2
          + hbar^2 sum_{a<b} ( c_+ |(K_ab (x) 1 + 1 (x) K_ab) f|^2
                             + c_- |(K_ab (x) 1 - 1 (x) K_ab) f|^2 )
          + hbar^2 (c_rho j(j+1) + c_tau j'(j'+1)) |f|^2 ] J dx,

the quadratic form of U_sector of reduction.py with rho_ab = (hbar/i) K_ab (x) 1,
tau_ab = (hbar/i) 1 (x) K_ab (covariants3.rotation_generators; -K^2 summed is the Casimir).
Coefficients as in reduction.py: d'Alembert (x = Q, J = prod |Q_a^2 - Q_b^2|, G = Id/I,
c_+- = 1/(4 I (Q_a -+ Q_b)^2)); affine models (x = q, J = prod sinh(q_a - q_b),
G = Id/M - B/(M(M + 3B)), c_+ = 1/(16 M sinh^2((q_a - q_b)/2)),
c_- = -1/(16 M cosh^2((q_a - q_b)/2)), af-is c_tau = 1/(2 I~), is-af c_rho = 1/(2 I~)).
The combination that multiplies the singular c_+ vanishes on the wall x_a = x_b for every
restricted covariant (the joint rotation fixes diag x there), so each integrand is bounded.

Bases (complete: covariants3 proves each covariant module free over the invariants):
* d'Alembert: g_i(Q/b) e^{-|Q|^2/2b^2} p2^a e3^b p4^c (Q/b), g_i the generators of the
  SO(3) x SO(3) covariants of phi, total degree <= ``degree``: exact for the R^9 oscillator up
  to that degree.
* affine: phi = U exp(S) (polar), and a covariant is (D^j(U) (x) 1) chi(S) with chi a covariant
  of the symmetric S under the diagonal SO(3); at phi = diag(e^q), S = diag(q). So g_i are the
  generators of those ("symmetric" model; walls q_a = q_b only, as on GL+(3)) at
  (q - centre/3)/b, times the scalar front of :func:`channel_candidates` (prod sqrt((q_a -
  q_b) / sinh(q_a - q_b)), Gaussians in the traceless part y and in sigma) and S3 invariants
  of (y, sigma), total degree <= ``degree``. For (1, 1) this is the dedicated spin-1 basis.

Honesty as in spectra.py: every sector is solved with the main basis and a nested smaller one
(and, for the affine models, a basis 1.1 times wider); levels whose spread exceeds the
tolerance are reported as unconverged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
from scipy import linalg, special

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.bases import (
    Basis,
    solve_block,
    sqrt_x_over_sinh,
    sqrt_x_over_sinh_derivative_ratio,
)
from affinebody.quantum.bounds import haar3_shell_bounds, lebesgue3_shell_bounds
from affinebody.quantum.channels3 import ChamberQuadrature, Grid3, setup3
from affinebody.quantum.intervals import Unsupported
from affinebody.quantum.levels import LevelCollector, Sector, Spectrum

PAIRS = ((0, 1), (0, 2), (1, 2))
#: shells max(j, j') explored by default for n = 3 (the generators of (6, 6) have degree 18)
MAX_SHELL = 6
#: affine models: shells beyond the last searched whose sectors are bounded one by one before
#: the uniform tail bound takes over (the rotor sectors' bounds grow slowly with the spin)
BOUND_SHELLS = 6


# ---------------------------------------------------------------- general sectors (j, j')
@dataclass(frozen=True)
class SectorAlgebra:
    """The fixed angular data of a sector: M-fixed coordinates E [m, r] of V_j (x) V_j' and the
    r x r forms N_plus[g], N_minus[g] = E^T A^T A E of A = K_g (x) 1 +- 1 (x) K_g."""

    j: int
    jp: int
    E: np.ndarray
    N_plus: np.ndarray
    N_minus: np.ndarray
    generators: tuple  # ((degree, coefficients [monomials, m]), ...)

    @property
    def rank(self) -> int:
        return self.E.shape[1]


@cache
def sector_algebra(j: int, jp: int, model: str = "matrix") -> SectorAlgebra:
    """The angular data of (j, j'); ``model`` picks the covariants (covariants3.module_generators:
    "matrix" for d'Alembert on R^{3x3}, "symmetric" for the affine models on GL+(3))."""
    E = cov.fixed_subspace(j, jp)
    plus, minus = cov.fixed_forms(j, jp)
    gens = cov.module_generators(j, jp, model) if E.shape[1] else ()
    return SectorAlgebra(j, jp, E, plus, minus, gens)


def generator_values(algebra: SectorAlgebra, x: np.ndarray, max_degree: int | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The module generators (those of degree <= max_degree) at points x [P, 3]: values
    [P, r, G], gradients d/dx [P, r, 3, G] (M-fixed coordinates) and their degrees [G]."""
    P = x.shape[0]
    gens = [(d, c) for d, c in algebra.generators if max_degree is None or d <= max_degree]
    if not gens:
        return np.zeros((P, algebra.rank, 0)), np.zeros((P, algebra.rank, 3, 0)), np.zeros(0, int)
    top = max(d for d, _ in gens)
    powers = np.ones((top + 1,) + x.shape)
    for k in range(1, top + 1):
        powers[k] = powers[k - 1] * x
    vals, grads = [], []
    cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for degree, coeffs in gens:
        if degree not in cache:
            exps = np.array(cov.monomials(degree))  # [nm, 3]
            factors = [powers[exps[:, a], :, a].T for a in range(3)]  # [P, nm] each
            mono = factors[0] * factors[1] * factors[2]
            dmono = np.zeros((P, len(exps), 3))
            for a in range(3):
                lowered = powers[np.maximum(exps[:, a] - 1, 0), :, a].T * exps[:, a]
                others = [factors[b] for b in range(3) if b != a]
                dmono[:, :, a] = lowered * others[0] * others[1]
            cache[degree] = (mono, dmono)
        mono, dmono = cache[degree]
        vals.append(mono @ coeffs)  # coefficients already in the M-fixed coordinates
        grads.append(np.einsum("pna,nr->pra", dmono, coeffs, optimize=True))
    return np.stack(vals, -1), np.stack(grads, -1), np.array([d for d, _ in gens])


@dataclass(frozen=True)
class Coefficients:
    """The reduced Hamiltonian's coefficients at the nodes (see the module docstring)."""

    G: np.ndarray  # [3, 3]
    c_plus: np.ndarray  # [P, 3] times J (pairs), i.e. the weight of |A_+ f|^2
    c_minus: np.ndarray  # [P, 3]
    casimir: float  # hbar^2 (c_rho j(j+1) + c_tau j'(j'+1))


def sector_coefficients(kind: str, x: np.ndarray, weights: np.ndarray, hbar: float, inertia,
                        j: int, jp: int) -> Coefficients:
    """Weights of the centrifugal forms (already multiplied by hbar^2 and the measure weights)."""
    cp = np.zeros((x.shape[0], 3))
    cm = np.zeros((x.shape[0], 3))
    if kind == "lebesgue3":
        I_ = float(inertia)
        G = np.eye(3) / I_
        for g, (a, b) in enumerate(PAIRS):
            cp[:, g] = hbar**2 * weights / (4 * I_ * (x[:, a] - x[:, b]) ** 2)
            cm[:, g] = hbar**2 * weights / (4 * I_ * (x[:, a] + x[:, b]) ** 2)
        casimir = 0.0
    else:
        M = inertia.M
        G = np.eye(3) / M - inertia.B / (M * (M + 3 * inertia.B)) * np.ones((3, 3))
        for g, (a, b) in enumerate(PAIRS):
            h = 0.5 * (x[:, a] - x[:, b])
            cp[:, g] = hbar**2 * weights / (16 * M * np.sinh(h) ** 2)
            cm[:, g] = -hbar**2 * weights / (16 * M * np.cosh(h) ** 2)
        c = 0.5 * inertia.inv_I_tilde
        casimir = hbar**2 * c * {"af-is": jp * (jp + 1), "is-af": j * (j + 1)}.get(
            inertia.model, 0)
    return Coefficients(G, cp, cm, casimir)


def sector_forms(kind: str, algebra: SectorAlgebra, potential_values: np.ndarray, hbar: float,
                 inertia, x: np.ndarray, weights: np.ndarray, vals: np.ndarray,
                 grads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, S) of the weak form for functions with values [P, r, K] and gradients [P, r, 3, K]
    at nodes x [P, 3] with quadrature weights (measure J included)."""
    co = sector_coefficients(kind, x, weights, hbar, inertia, algebra.j, algebra.jp)
    P, r, K = vals.shape
    flat = vals.reshape(P * r, K)
    S = flat.T @ (np.repeat(weights, r)[:, None] * flat)
    # the multiplicative part as one r x r matrix per node: potential, Casimir, centrifugal
    U = np.einsum("pg,grs->prs", co.c_plus, algebra.N_plus)
    U += np.einsum("pg,grs->prs", co.c_minus, algebra.N_minus)
    U += (weights * (potential_values + co.casimir))[:, None, None] * np.eye(r)
    H = np.matmul(U, vals).reshape(P * r, K).T @ flat
    Gg = np.matmul(co.G, grads) * weights[:, None, None, None]  # G acts on the gradient index
    H += (hbar**2 / 2) * Gg.reshape(-1, K).T @ grads.reshape(-1, K)
    return 0.5 * (H + H.T), 0.5 * (S + S.T)


def invariant_monomials(kind: str, degree: int) -> list[tuple[int, ...]]:
    """Exponents of the scalar factors: d'Alembert (p2, e3, p4) with weights (2, 3, 4);
    affine (t, p2, p3) with weights (1, 2, 3); total weight <= degree, ascending."""
    weights = (2, 3, 4) if kind == "lebesgue3" else (1, 2, 3)
    r = range(degree + 1)
    out = [(a, b, c) for a in r for b in r for c in r
           if weights[0] * a + weights[1] * b + weights[2] * c <= degree]
    return sorted(out, key=lambda e: (sum(w * k for w, k in zip(weights, e, strict=True)), e))


def scalar_factors(kind: str, x: np.ndarray, scale: float, scale_sigma: float, centre: float
                   ) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """(front value [P], front gradient [P, 3], [(invariant value, gradient)] x 3) at x."""
    if kind == "lebesgue3":
        y = x / scale
        front = np.exp(-0.5 * np.sum(y * y, -1))
        dfront = -x / scale**2 * front[:, None]
        p2 = np.sum(y * y, -1)
        e3 = np.prod(y, -1)
        p4 = np.sum(y**4, -1)
        de3 = np.stack([y[:, 1] * y[:, 2], y[:, 0] * y[:, 2], y[:, 0] * y[:, 1]], -1)
        invs = [(p2, 2 * y / scale), (e3, de3 / scale), (p4, 4 * y**3 / scale)]
        return front, dfront, invs
    P = x.shape[0]
    centred = np.eye(3) - 1 / 3  # dy/dq
    y = (x - x.mean(-1, keepdims=True)) / scale
    t = (x.sum(-1) - centre) / scale_sigma
    dt = np.ones((P, 3)) / scale_sigma
    p2 = np.sum(y * y, -1)
    dp2 = 2 * y @ centred / scale
    p3 = np.sum(y**3, -1)
    dp3 = 3 * y**2 @ centred / scale
    front = np.exp(-0.5 * (p2 + t * t))
    dfront = front[:, None] * (-0.5 * dp2 - t[:, None] * dt)
    for a, b in PAIRS:
        d = x[:, a] - x[:, b]
        g = sqrt_x_over_sinh(d)
        dlog = sqrt_x_over_sinh_derivative_ratio(d)
        grad = np.zeros((P, 3))
        grad[:, a], grad[:, b] = dlog, -dlog
        dfront = dfront * g[:, None] + front[:, None] * g[:, None] * grad
        front = front * g
    return front, dfront, [(t, dt), (p2, dp2), (p3, dp3)]


def sector_candidates(kind: str, algebra: SectorAlgebra, x: np.ndarray, degree: int,
                      scale: float, scale_sigma: float = 1.0, centre: float = 0.0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate basis functions at x: values [P, r, K], gradients [P, r, 3, K], parity under
    phi -> -phi [K] ((-1)^degree; d'Alembert only, +1 otherwise) and the level [K] of each (the
    degree it enters the basis at): the candidates of ``degree - k`` are those of level <=
    degree - k, so smaller bases are nested in larger ones."""
    if kind == "lebesgue3":
        gv, gg, gdeg = generator_values(algebra, x / scale, degree)
        gg = gg / scale
    else:  # covariants of S = log of the polar factor, at diag(q) shifted by a multiple of Id
        gv, gg, gdeg = generator_values(algebra, (x - centre / 3) / scale, degree)
        gg = gg / scale
    front, dfront, invs = scalar_factors(kind, x, scale, scale_sigma, centre)
    weights = np.array((2, 3, 4) if kind == "lebesgue3" else (1, 2, 3))
    pairs = [(i, e) for i, gd in enumerate(gdeg) if gd <= degree
             for e in invariant_monomials(kind, degree - gd)]  # total degree <= degree
    P = x.shape[0]
    if not pairs:
        return (np.zeros((P, algebra.rank, 0)), np.zeros((P, algebra.rank, 3, 0)), np.zeros(0),
                np.zeros(0, int))
    exps = sorted({e for _, e in pairs})
    column = {e: k for k, e in enumerate(exps)}
    # the scalar factors front * prod inv^e and their gradients, once per exponent
    sv = np.empty((P, len(exps)))
    sg = np.empty((P, 3, len(exps)))
    for k, e in enumerate(exps):
        s, ds = front.copy(), dfront.copy()
        for (v, dv), n in zip(invs, e, strict=True):
            if n:
                ds = ds * v[:, None] ** n + s[:, None] * n * v[:, None] ** (n - 1) * dv
                s = s * v**n
        sv[:, k], sg[:, :, k] = s, ds
    gi = np.array([i for i, _ in pairs])
    si = np.array([column[e] for _, e in pairs])
    vals = gv[:, :, gi] * sv[:, None, si]
    grads = gg[:, :, :, gi] * sv[:, None, None, si] + gv[:, :, None, gi] * sg[:, None, :, si]
    level = gdeg[gi] + np.array([int(weights @ np.array(e)) for _, e in pairs])
    parity = (-1) ** level if kind == "lebesgue3" else np.ones(len(pairs), int)
    return vals, grads, parity, level


@dataclass(frozen=True)
class SectorBasis:
    """The orthonormal basis of a sector as a recipe: the candidates (``sector_candidates`` with
    ``candidate_args`` = (degree, scale, scale_sigma, centre), ordered by level, those in
    ``keep``) times ``transform`` [kept, K] (upper triangular, so the first k functions span
    the nested basis of the first k candidates). :meth:`values` evaluates it on the nodes on
    demand: a spectrum keeps one basis per sector, too large to hold as arrays."""

    kind: str
    j: int
    jp: int
    nodes: np.ndarray
    weights: np.ndarray
    candidate_args: tuple
    keep: np.ndarray
    transform: np.ndarray
    parity: np.ndarray
    levels: np.ndarray  # [K] the level of each function, ascending (nested smaller bases)

    def truncated(self, count: int) -> SectorBasis:
        """The nested basis of the first ``count`` functions."""
        return replace(self, transform=self.transform[:, :count], parity=self.parity[:count],
                       levels=self.levels[:count])

    def values(self, chunk: int = 8192) -> np.ndarray:
        """Basis functions at the nodes, [P, r, K], orthonormal under the weights."""
        algebra = sector_algebra(self.j, self.jp, _model(self.kind))
        degree, scale, scale_sigma, centre = self.candidate_args
        out = []
        for i in range(0, len(self.nodes), chunk):
            cv = _ordered_candidates(self.kind, algebra, self.nodes[i:i + chunk], degree, scale,
                                     scale_sigma, centre)[0]
            out.append(cv[..., self.keep] @ self.transform)
        return np.concatenate(out)


def _model(kind: str) -> str:
    return "matrix" if kind == "lebesgue3" else "symmetric"


def _ordered_candidates(kind, algebra, x, degree, scale, scale_sigma, centre):
    vals, grads, parity, level = sector_candidates(kind, algebra, x, degree, scale, scale_sigma,
                                                   centre)
    order = np.argsort(level, kind="stable")
    return vals[..., order], grads[..., order], parity[order], level[order]


def sector_block(kind: str, potential, hbar: float, inertia, grid, j: int, jp: int,
                 degree: int, scale: float, scale_sigma: float = 1.0, centre: float = 0.0,
                 chunk_floats: int = 2**22) -> tuple[np.ndarray, SectorBasis]:
    """Galerkin Hamiltonian of the sector (j, j') in an orthonormal basis: Householder QR of
    the candidates' values under the measure in the order of their levels (chunk by chunk,
    combining the chunks' R factors), so the leading k x k block of H is the Hamiltonian of
    the nested basis of the first k functions (the parities stay separate: even and odd
    functions are orthogonal under the measure when phi -> -phi is a symmetry); then the forms
    accumulated over chunks of nodes, and a Cholesky finish (lower-triangular, so the nesting
    is kept). Memory is bounded by ``chunk_floats`` and the K x K matrices."""
    algebra = sector_algebra(j, jp, _model(kind))
    x, w = grid.nodes, grid.weights
    args = (degree, scale, scale_sigma, centre)
    _, _, parity, level = _ordered_candidates(kind, algebra, x[:1], *args)
    r, K = algebra.rank, len(level)
    chunk = max(64, chunk_floats // max(1, 4 * r * K))
    if K == 0:
        empty = np.zeros((0, 0))
        return empty, SectorBasis(kind, j, jp, x, w, args, np.zeros(0, bool), empty, parity,
                                  level)
    factors = []
    for i in range(0, len(x), chunk):
        cv = _ordered_candidates(kind, algebra, x[i:i + chunk], *args)[0]
        factors.append(np.linalg.qr((np.sqrt(w[i:i + chunk])[:, None, None] * cv)
                                    .reshape(-1, K), mode="r"))
    R = np.linalg.qr(np.vstack(factors), mode="r")
    keep = np.abs(np.diag(R)) > 1e-10 * np.max(np.abs(np.diag(R)))
    T = linalg.solve_triangular(R[np.ix_(keep, keep)], np.eye(int(keep.sum())))
    Q = x if kind == "lebesgue3" else np.exp(x)
    V = np.asarray(potential(Q), float)
    H = np.zeros((len(T), len(T)))
    S = np.zeros_like(H)
    for i in range(0, len(x), chunk):
        sl = slice(i, i + chunk)
        cv, cg, *_ = _ordered_candidates(kind, algebra, x[sl], *args)
        if not keep.all():
            cv, cg = cv[..., keep], cg[..., keep]
        h, s = sector_forms(kind, algebra, V[sl], hbar, inertia, x[sl], w[sl], cv @ T, cg @ T)
        H += h
        S += s
    Linv = linalg.solve_triangular(np.linalg.cholesky(S), np.eye(len(S)), lower=True)
    H = Linv @ H @ Linv.T
    basis = SectorBasis(kind, j, jp, x, w, args, keep, T @ Linv.T, parity[keep], level[keep])
    return 0.5 * (H + H.T), basis


def sector_dimension(j: int, jp: int) -> int:
    """States per level of the sector: (2j + 1)(2j' + 1)."""
    return (2 * j + 1) * (2 * jp + 1)


def sectors_by_shell(max_spin: int) -> list[list[tuple[int, int]]]:
    """Sectors (j, j') with a non-empty module, grouped by shell max(j, j')."""
    return [[(j, jp) for j in range(L + 1) for jp in range(L + 1) if max(j, jp) == L
             and cov.fixed_dimension(j, jp) > 0] for L in range(max_spin + 1)]


#: lowest polynomial degree carrying the sector (R^9 oscillator: its lowest shell N)
lowest_degree = cov.lowest_degree


# ------------------------------------------- d'Alembert: hyperspherical harmonics x radial
def angular_candidates(algebra: SectorAlgebra, omega: np.ndarray, degree: int,
                       gradients: bool = True) -> tuple[np.ndarray, np.ndarray | None,
                                                        np.ndarray]:
    """The module generators times e3^b p4^c (no power of p2 = |Q|^2, which is 1 on the
    sphere), homogeneous of degree L <= ``degree``, at unit vectors omega [P, 3]: values
    [P, r, K], tangential gradients [P, r, 3, K] (the gradient on R^3 minus L f omega, by
    Euler's identity; None unless ``gradients``) and L [K], ascending."""
    gv, gg, gdeg = generator_values(algebra, omega, degree)
    e3 = np.prod(omega, -1)
    de3 = np.stack([omega[:, 1] * omega[:, 2], omega[:, 0] * omega[:, 2],
                    omega[:, 0] * omega[:, 1]], -1)
    p4 = np.sum(omega**4, -1)
    dp4 = 4 * omega**3
    vals, grads, deg = [], [], []
    for i, gd in enumerate(gdeg):
        for b in range((degree - gd) // 3 + 1):
            for c in range((degree - gd - 3 * b) // 4 + 1):
                s = e3**b * p4**c
                L = int(gd + 3 * b + 4 * c)
                v = gv[:, :, i] * s[:, None]
                vals.append(v)
                deg.append(L)
                if gradients:
                    ds = (b * e3 ** max(b - 1, 0) * p4**c)[:, None] * de3 + (
                        c * p4 ** max(c - 1, 0) * e3**b)[:, None] * dp4
                    g = gg[:, :, :, i] * s[:, None, None] + gv[:, :, None, i] * ds[:, None, :]
                    grads.append(g - L * v[:, :, None] * omega[:, None, :])
    P, r = omega.shape[0], algebra.rank
    if not deg:
        return np.zeros((P, r, 0)), np.zeros((P, r, 3, 0)), np.zeros(0, int)
    order = np.argsort(deg, kind="stable")
    return (np.stack(vals, -1)[..., order],
            np.stack(grads, -1)[..., order] if gradients else None, np.array(deg)[order])


def laguerre_table(count: int, a: float, t: np.ndarray) -> np.ndarray:
    """Generalised Laguerre polynomials L_k^(a)(t), k < ``count``, [len(t), count], by the
    three-term recurrence (k + 1) L_(k+1) = (2k + 1 + a - t) L_k - (k + a) L_(k-1)."""
    out = np.empty((len(t), max(count, 1)))
    out[:, 0] = 1.0
    if count > 1:
        out[:, 1] = 1.0 + a - t
    for k in range(1, count - 1):
        out[:, k + 1] = ((2 * k + 1 + a - t) * out[:, k] - (k + a) * out[:, k - 1]) / (k + 1)
    return out[:, :count]


def radial_functions(L: int, count: int, scale: float, rho: np.ndarray,
                     derivative: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
    """u_k(rho) = c_k t^(L/2) L_k^(a)(t) e^(-t/2), t = rho^2/b^2, a = L + 7/2, k < ``count``:
    orthonormal under rho^8 drho (c_k^2 = 2 k! / (b^9 Gamma(k + a + 1))). Values and (if
    ``derivative``) derivatives d/drho, [len(rho), count]."""
    a = L + 3.5
    t = (rho / scale) ** 2
    k = np.arange(count)
    log_c = 0.5 * (np.log(2.0) + special.gammaln(k + 1) - 9 * np.log(scale)
                   - special.gammaln(k + a + 1))
    with np.errstate(divide="ignore"):  # t = 0: t^(L/2) = 0 for L > 0, 1 for L = 0
        power = 0.5 * L * np.log(t) if L else np.zeros_like(t)
    front = np.exp(power[:, None] - 0.5 * t[:, None] + log_c[None, :])
    lag = laguerre_table(count, a, t)
    if not derivative:
        return front * lag, None
    dlag = np.zeros_like(lag)  # d/dt L_k^(a) = -L_(k-1)^(a+1)
    dlag[:, 1:] = -laguerre_table(count - 1, a + 1, t)
    dt = (L / (2 * t))[:, None] * lag - 0.5 * lag + dlag  # d/dt of t^(L/2) e^(-t/2) L_k / front
    return front * lag, front * dt * (2 * rho / scale**2)[:, None]


@dataclass(frozen=True)
class HarmonicBasis:
    """d'Alembert sector (j, j') in the product basis Y_mu(omega) u_k^(L_mu)(rho): Y_mu the
    sector's harmonics (restricted covariant harmonic polynomials of degree L_mu <=
    ``degree``, orthonormal on the chamber's sphere: the candidates of
    :func:`angular_candidates` orthonormalised in the order of their degree, which removes
    the parts of lower degree), u_k the radial functions of :func:`radial_functions`
    (k < ``radial``). ``angular`` [K_candidates, mu] maps the candidates to Y; ``index``
    [(mu, k)] lists the basis functions in the solver's order (``levels``: the nested check
    basis first). :meth:`values` evaluates the basis at ``nodes`` (any points of the
    chamber), as :class:`SectorBasis` does."""

    j: int
    jp: int
    nodes: np.ndarray
    weights: np.ndarray
    degree: int
    radial: int
    scale: float
    angular: np.ndarray
    harmonic_degree: np.ndarray  # [mu]
    index: np.ndarray  # [K, 2] (mu, k)
    parity: np.ndarray
    levels: np.ndarray

    @property
    def candidate_args(self) -> tuple:
        """(degree, scale, scale_sigma, centre) as for :class:`SectorBasis`: the angular
        degree (the radial functions are not polynomials of that degree)."""
        return (self.degree, self.scale, 1.0, 0.0)

    def truncated(self, count: int) -> HarmonicBasis:
        return replace(self, index=self.index[:count], parity=self.parity[:count],
                       levels=self.levels[:count])

    def values(self, chunk: int = 8192) -> np.ndarray:
        """Basis functions at the nodes, [P, r, K]."""
        algebra = sector_algebra(self.j, self.jp, "matrix")
        out = []
        for i in range(0, len(self.nodes), chunk):
            Q = self.nodes[i:i + chunk]
            rho = np.linalg.norm(Q, axis=-1)
            omega = Q / np.where(rho > 0, rho, 1.0)[:, None]
            Y = angular_candidates(algebra, omega, self.degree, gradients=False)[0] \
                @ self.angular
            radial = np.zeros((len(Q), len(self.index)))
            for L in np.unique(self.harmonic_degree):
                u = radial_functions(int(L), self.radial, self.scale, np.maximum(rho, 1e-300),
                                     derivative=False)[0]
                cols = self.harmonic_degree[self.index[:, 0]] == L
                radial[:, cols] = u[:, self.index[cols, 1]]
            out.append(Y[:, :, self.index[:, 0]] * radial[:, None, :])
        return np.concatenate(out)

    def combination(self, coeff: np.ndarray, nodes: np.ndarray, chunk: int = 8192
                    ) -> np.ndarray:
        """sum_K coeff_K f_K at ``nodes``, [P, r]: as ``values() @ coeff`` but summing the
        radial functions of each harmonic first (sum_mu Y_mu(omega) sum_k c_mu,k u_k(rho)),
        without the [P, r, K] table."""
        algebra = sector_algebra(self.j, self.jp, "matrix")
        nY = self.angular.shape[1]
        C = np.zeros((nY, self.radial))
        C[self.index[:, 0], self.index[:, 1]] = coeff
        out = []
        for i in range(0, len(nodes), chunk):
            Q = nodes[i:i + chunk]
            rho = np.linalg.norm(Q, axis=-1)
            omega = Q / np.where(rho > 0, rho, 1.0)[:, None]
            Y = angular_candidates(algebra, omega, self.degree, gradients=False)[0] \
                @ self.angular
            radial = np.zeros((len(Q), nY))  # [P, mu]: sum_k c_mu,k u_k^(L_mu)(rho)
            for L in np.unique(self.harmonic_degree):
                mus = np.flatnonzero(self.harmonic_degree == L)
                u = radial_functions(int(L), self.radial, self.scale, np.maximum(rho, 1e-300),
                                     derivative=False)[0]
                radial[:, mus] = u @ C[mus].T
            out.append(np.einsum("prm,pm->pr", Y, radial))
        return np.concatenate(out)


def sphere_harmonics(algebra: SectorAlgebra, omega: np.ndarray, w: np.ndarray, degree: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(transform [K_candidates, mu], L [mu], Y [P, r, mu], tangential gradients of Y): the
    candidates orthonormalised under the sphere weights in the order of their degree
    (Householder QR; near-dependent candidates, |R_ii| < 1e-10 max, are dropped)."""
    vals, tgrads, deg = angular_candidates(algebra, omega, degree)
    P, r, K = vals.shape
    if K == 0:
        return np.zeros((0, 0)), np.zeros(0, int), vals, tgrads
    R = np.linalg.qr((np.sqrt(w)[:, None, None] * vals).reshape(P * r, K), mode="r")
    keep = np.abs(np.diag(R)) > 1e-10 * np.max(np.abs(np.diag(R)))
    T = np.zeros((K, int(keep.sum())))
    T[keep] = linalg.solve_triangular(R[np.ix_(keep, keep)], np.eye(int(keep.sum())))
    return T, deg[keep], vals @ T, tgrads @ T


def harmonic_block(potential, hbar: float, inertia: float, j: int, jp: int, degree: int,
                   radial: int, scale: float, shrink: int, n_angle: int | None = None
                   ) -> tuple[np.ndarray, HarmonicBasis]:
    """Galerkin Hamiltonian of the d'Alembert sector (j, j') (J = inertia * Id) in the
    orthonormal basis Y_mu u_k^(L_mu) of :class:`HarmonicBasis`. With f = Y(omega) u(rho),
    grad f = u' Y omega + (u / rho) grad_t Y and the centrifugal weights c_+- of degree -2,

        <f|H|f'> = (hbar^2/I) [ (1/2) S_mu,nu int u' u'' rho^8 + A_mu,nu int u u' rho^6 ]
                   + int rho^8 u u' sum_p w_p V(rho omega_p) <Y_mu, Y_nu>(omega_p),

    S and A the overlap and the angular form (1/2 |grad_t Y|^2 + centrifugal terms, hbar = I
    = 1, :func:`sector_forms` with tangential gradients) on the sphere; for harmonics of
    degree L, A = L (L + 7) / 2 (the Laplacian of S^8), which the tests check. Radial
    integrals by Gauss-Legendre in rho. The functions of angular degree <= degree - shrink
    and radial index < radial - shrink come first (the nested check basis, ``levels`` <=
    degree - shrink)."""
    algebra = sector_algebra(j, jp, "matrix")
    n_angle = n_angle or 20 + 2 * degree
    omega, w = ChamberQuadrature.sphere(n_angle)
    T, Ldeg, Y, tY = sphere_harmonics(algebra, omega, w, degree)
    nY = len(Ldeg)
    rho_max = scale * math.sqrt(2 * (2 * radial + degree) + 80)
    n_rho = 2 * radial + degree + 60
    xr, wr = special.roots_legendre(n_rho)
    rho, w_rho = rho_max * (xr + 1) / 2, rho_max * wr / 2
    if nY == 0:
        empty = np.zeros((0, 0))
        return empty, HarmonicBasis(j, jp, np.zeros((0, 3)), np.zeros(0), degree, radial, scale,
                                    T, Ldeg, np.zeros((0, 2), int), np.zeros(0, int),
                                    np.zeros(0, int))
    A, S = sector_forms("lebesgue3", algebra, np.zeros(len(omega)), 1.0, 1.0, omega, w, Y, tY)
    Q = (rho[:, None, None] * omega[None]).reshape(-1, 3)
    Vq = np.asarray(potential(Q), float).reshape(len(rho), len(omega))
    radial_V = np.allclose(Vq, Vq[:, :1], rtol=1e-14, atol=1e-14 * np.max(np.abs(Vq)))
    if radial_V:
        M = Vq[:, 0, None, None] * S[None]
    else:
        YY = np.einsum("prm,prn->pmn", Y, Y, optimize=True).reshape(len(omega), nY * nY)
        M = ((Vq * w[None, :]) @ YY).reshape(len(rho), nY, nY)
    U = np.empty((len(rho), nY, radial))
    dU = np.empty_like(U)
    for L in np.unique(Ldeg):
        u, du = radial_functions(int(L), radial, scale, rho)
        U[:, Ldeg == L], dU[:, Ldeg == L] = u[:, None], du[:, None]
    w8, w6 = w_rho * rho**8, w_rho * rho**6
    c = hbar**2 / inertia
    H = c * (0.5 * np.einsum("mn,imk,inl->mknl", S, w8[:, None, None] * dU, dU, optimize=True)
             + np.einsum("mn,imk,inl->mknl", A, w6[:, None, None] * U, U, optimize=True))
    H += np.einsum("imk,imn,inl->mknl", w8[:, None, None] * U, M, U, optimize=True)
    H = H.reshape(nY * radial, nY * radial)
    mu, k = np.divmod(np.arange(nY * radial), radial)
    level = np.where(k < radial - shrink, Ldeg[mu], np.maximum(Ldeg[mu], degree - shrink + 1))
    order = np.lexsort((k, mu, level))
    H = H[np.ix_(order, order)]
    index = np.stack([mu[order], k[order]], -1)
    basis = HarmonicBasis(j, jp, Q, np.repeat(w8, len(omega)) * np.tile(w, len(rho)), degree,
                          radial, scale, T, Ldeg, index, (-1) ** Ldeg[index[:, 0]],
                          level[order])
    return 0.5 * (H + H.T), basis


# -------------------------------------------------------------------------------- solver
def solve_all_sectors(model: str, potential, hbar: float, inertia_scalar: float, inertia,
                      levels: int, settings, progress=None):
    """The lowest ``levels`` states of the n = 3 body over every sector (j, j'), shell by shell
    (shell = max(j, j')).

    Stopping rule (docs/theory/two-polar.md, "Lower bounds of an n = 3 sector"): with E_K the
    ``levels``-th lowest candidate found, a sector whose certified lower bound
    (:func:`~affinebody.quantum.bounds.lebesgue3_shell_bounds`,
    :func:`~affinebody.quantum.bounds.haar3_shell_bounds`) exceeds E_K is not solved, and the
    search stops after the shell L when every sector of the shells above L has its bound above
    E_K; a sector the basis cannot hold (its lowest degree above the basis degree) must have
    its bound above E_K too. Then the list is ``certified``; otherwise (no bound for the
    potential, af-af, or a bound below E_K) the result is conditional and says why.

    d'Alembert with ``settings.radial_size``: each sector in the basis of
    :func:`harmonic_block` (harmonics of degree <= basis_size x ``radial_size`` radial
    functions); else :func:`sector_block`.

    d'Alembert and af-af are symmetric under phi -> phi^T, which swaps (j, j') and (j', j):
    one block serves both (both sectors are listed on its levels). af-is and is-af are each
    other's transpose and need every sector.

    ``progress``: optional callable receiving a one-line description of each sector as it
    starts.
    """
    setup = setup3(model, potential, hbar, inertia_scalar, inertia, settings)
    kind, degree = setup.kind, settings.basis_size
    physical = inertia_scalar if kind == "lebesgue3" else inertia
    radial = getattr(settings, "radial_size", None) if kind == "lebesgue3" else None

    def build(j, jp):
        """Block builder computing the largest basis once per scale; the nested check basis
        (smaller degree) is the leading block of its Hamiltonian."""
        cache: dict = {}

        def block(d, sc):
            if sc not in cache or cache[sc][0] < d:
                if radial:
                    cache[sc] = (d, None, harmonic_block(potential, hbar, physical, j, jp, d,
                                                         radial, sc, setup.check.check_shrink))
                else:
                    grid = setup.grid(d, sc)
                    cache[sc] = (d, grid, sector_block(kind, potential, hbar, physical, grid, j,
                                                       jp, d, sc, setup.sigma_scale(sc),
                                                       setup.centre))
            _, grid, (H, basis) = cache[sc]
            nested = basis.truncated(int(np.sum(basis.levels <= d)))
            k = len(nested.levels)
            if radial:
                grid = Grid3(basis.nodes, basis.weights)
            return H[:k, :k], Basis("grid3", (kind, grid, nested.values, nested.parity, None))
        return block

    transpose_symmetric = model in ("dalembert", "af-af")
    max_shell = min(settings.max_spin, MAX_SHELL)
    bounds, reason = None, ""
    try:
        if model == "dalembert":
            bounds = lebesgue3_shell_bounds(potential, hbar, inertia_scalar, max_shell,
                                            setup.scale)
        else:
            bounds = haar3_shell_bounds(potential, hbar, inertia, max_shell, setup.centre,
                                        setup.scale_sigma, setup.scale,
                                        enumerate_to=max_shell + BOUND_SHELLS)
    except Unsupported as err:
        reason = str(err)

    found = LevelCollector(settings)
    shell_minima: list[float] = []
    unresolved: list[tuple[int, int]] = []  # sectors the basis cannot hold
    certified, searched, pruned = False, -1, 0

    def above(key) -> bool:
        return (bounds is not None and found.state_count() >= levels
                and bounds.of(key) > found.kth_energy(levels))

    for shell in sectors_by_shell(max_shell):
        shell_min = np.inf
        for j, jp in shell:
            if transpose_symmetric and j > jp:
                continue
            if above((j, jp)) and (not transpose_symmetric or above((jp, j))):
                pruned += 1  # no level of this sector can be among the lowest: not solved
                continue
            if kind == "lebesgue3" and lowest_degree(j, jp) > degree:
                unresolved.append((j, jp))  # no covariant polynomial of the basis degree
                continue
            if progress is not None:
                progress(f"n = 3 {model}: sector (j, j') = ({j}, {jp}), shell {max(j, jp)}")
            E, vec, err, basis = solve_block(build(j, jp), degree, setup.scale, levels + 4,
                                             setup.check)
            if len(E) == 0:
                unresolved.append((j, jp))
                continue
            twins = [(j, jp)] + ([(jp, j)] if transpose_symmetric and j != jp else [])
            found.record_each(
                ("sector", j, jp),
                lambda p, twins=twins: tuple(
                    Sector(a, c, p if setup.parity_symmetric else None, sector_dimension(a, c))
                    for a, c in twins),
                basis, E, vec, err, basis.factors[3])
            shell_min = min(shell_min, float(E[0]))
        shell_minima.append(shell_min)
        searched = max(max(key) for key in shell)
        if (bounds is not None and model != "af-af" and found.state_count() >= levels
                and bounds.beyond(searched) > found.kth_energy(levels)
                and all(above(key) for key in unresolved)):
            certified = True
            break
    info = setup.info(settings)
    if radial:
        info["radial_size"] = radial
    info["shells_searched"] = searched
    info["sectors_pruned"] = pruned
    warnings = []
    bounded = True
    missing = [key for key in unresolved if not above(key)]
    if model == "af-af":
        bounded = False
        warnings.append("af-af: the kinetic energy (72) is indefinite; every sector is bounded "
                        "below but their sum is not (the wells -hbar^2 (rho - tau)^2 / "
                        "(16 A cosh^2) deepen with the spin); shells explored up to "
                        f"max(j, j') = {max_shell}, lowest level per shell: "
                        + ", ".join(f"{e:.4g}" for e in shell_minima if np.isfinite(e)))
        certificate = "none: af-af is unbounded below"
    elif certified:
        certificate = (f"{bounds.method}; every sector beyond shell {searched} and every sector "
                       f"not solved has no level below "
                       f"{min([bounds.beyond(searched)] + [bounds.of(k) for k in unresolved]):.6g}"
                       f" > the {levels}-th candidate {found.kth_energy(levels):.6g}")
    else:
        if reason:
            why = reason
        elif missing:
            why = (f"the sectors {', '.join(map(str, missing))} lie above the basis degree "
                   f"{degree} and their certified bound does not exceed the {levels}-th level "
                   f"(raise quantum.basis_size)")
        else:
            why = "the bound of the sectors not searched does not exceed the K-th level"
        beyond = "" if bounds is None else (
            f" (certified lower bound beyond shell {searched}: {bounds.beyond(searched):.6g})")
        certificate = (f"conditional: {why}; searched every sector up to max(j, j') = "
                       f"{max_shell}{beyond}")
        warnings.append(f"the {levels} lowest states are conditional: {why}; only sectors up "
                        f"to max(j, j') = {max_shell} were searched (at most {MAX_SHELL} for "
                        f"n = 3)")
    merged, unconverged = found.levels(levels)
    return Spectrum(merged, unconverged, found.blocks, model, 3, "all", info,
                    bounded, warnings, certified=certified, certificate=certificate,
                    requested=levels)


__all__ = ["SectorAlgebra", "sector_algebra", "generator_values", "sector_coefficients",
           "sector_forms", "sector_candidates", "SectorBasis", "sector_block", "sector_dimension",
           "sectors_by_shell", "lowest_degree", "MAX_SHELL", "BOUND_SHELLS", "solve_all_sectors",
           "angular_candidates", "laguerre_table", "radial_functions", "HarmonicBasis",
           "sphere_harmonics",
           "harmonic_block",
           "Coefficients", "invariant_monomials", "scalar_factors",
]
