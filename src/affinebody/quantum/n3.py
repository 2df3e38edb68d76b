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

from dataclasses import dataclass, replace
from functools import cache

import numpy as np
from scipy import linalg

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.bases import (
    Basis,
    solve_block,
    sqrt_x_over_sinh,
    sqrt_x_over_sinh_derivative_ratio,
)
from affinebody.quantum.channels3 import setup3
from affinebody.quantum.levels import LevelCollector, Sector, Spectrum, shell_complete

PAIRS = ((0, 1), (0, 2), (1, 2))
#: shells max(j, j') explored by default for n = 3 (the generators of (6, 6) have degree 18)
MAX_SHELL = 6


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
    Kj, Kjp = cov.rotation_generators(j), cov.rotation_generators(jp)
    Ij, Ijp = np.eye(2 * j + 1), np.eye(2 * jp + 1)
    E = cov.fixed_subspace(j, jp)
    plus, minus = [], []
    for g in range(3):
        for sign, out in ((1.0, plus), (-1.0, minus)):
            A = (np.kron(Kj[g], Ijp) + sign * np.kron(Ij, Kjp[g])) @ E
            out.append(A.T @ A)
    gens = cov.module_generators(j, jp, model) if E.shape[1] else ()
    return SectorAlgebra(j, jp, E, np.array(plus), np.array(minus), gens)


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


def lowest_degree(j: int, jp: int) -> int:
    """Lowest polynomial degree carrying the sector (R^9 oscillator: its lowest shell N)."""
    return next(d for d in range(4 * (j + jp) + 1) if cov.polynomial_multiplicity(j, jp, d))


# -------------------------------------------------------------------------------- solver
def solve_all_sectors(model: str, potential, hbar: float, inertia_scalar: float, inertia,
                      levels: int, settings, progress=None):
    """The lowest ``levels`` states of the n = 3 body over every sector (j, j'), shell by shell
    (shell = max(j, j')), stopping when a whole shell lies above the levels found.

    d'Alembert and af-af are symmetric under phi -> phi^T, which swaps (j, j') and (j', j):
    one block serves both (both sectors are listed on its levels). af-is and is-af are each
    other's transpose and need every sector.

    ``progress``: optional callable receiving a one-line description of each sector as it
    starts.
    """
    setup = setup3(model, potential, hbar, inertia_scalar, inertia, settings)
    kind, degree = setup.kind, settings.basis_size
    physical = inertia_scalar if kind == "lebesgue3" else inertia

    def build(j, jp):
        """Block builder computing the largest basis once per scale; the nested check basis
        (smaller degree) is the leading block of its Hamiltonian."""
        cache: dict = {}

        def block(d, sc):
            if sc not in cache or cache[sc][0] < d:
                grid = setup.grid(d, sc)
                cache[sc] = (d, grid, sector_block(kind, potential, hbar, physical, grid, j, jp,
                                                   d, sc, setup.sigma_scale(sc), setup.centre))
            _, grid, (H, basis) = cache[sc]
            nested = basis.truncated(int(np.sum(basis.levels <= d)))
            k = len(nested.levels)
            return H[:k, :k], Basis("grid3", (kind, grid, nested.values, nested.parity, None))
        return block

    transpose_symmetric = model in ("dalembert", "af-af")
    max_shell = min(settings.max_spin, MAX_SHELL)
    found = LevelCollector(settings)
    shell_minima: list[float] = []
    finished = False
    for shell in sectors_by_shell(max_shell):
        shell_min = np.inf
        for j, jp in shell:
            if transpose_symmetric and j > jp:
                continue
            if kind == "lebesgue3" and lowest_degree(j, jp) > degree:
                continue  # no covariant polynomial of the basis degree: not resolved
            if progress is not None:
                progress(f"n = 3 {model}: sector (j, j') = ({j}, {jp}), shell {max(j, jp)}")
            E, vec, err, basis = solve_block(build(j, jp), degree, setup.scale, levels + 4,
                                             setup.check)
            if len(E) == 0:
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
        if model != "af-af" and shell_complete(found.known(), levels, shell_min):
            finished = True
            break
    warnings = []
    bounded = True
    if model == "af-af":
        bounded = False
        warnings.append("af-af: the kinetic energy (72) is indefinite; every sector is bounded "
                        "below but their sum is not (the wells -hbar^2 (rho - tau)^2 / "
                        "(16 A cosh^2) deepen with the spin); shells explored up to "
                        f"max(j, j') = {max_shell}, lowest level per shell: "
                        + ", ".join(f"{e:.4g}" for e in shell_minima if np.isfinite(e)))
    elif not finished:
        warnings.append(f"the sector search stopped at max(j, j') = {max_shell} before the "
                        f"{levels} lowest states were certain: raise quantum.max_spin "
                        f"(at most {MAX_SHELL} for n = 3)")
    merged, unconverged = found.levels(levels)
    certificate = ("conditional: no lower bound of the (j, j') blocks is implemented for n = 3; "
                   + (f"the search stopped after shell {shell}, whose lowest level lies above "
                      f"the {levels}-th candidate (a heuristic: it assumes the lowest level per "
                      f"shell rises with the shell)" if finished else
                      f"searched every sector up to max(j, j') = {max_shell}"))
    return Spectrum(merged, unconverged, found.blocks, model, 3, "all", setup.info(settings),
                    bounded, warnings, certified=False, certificate=certificate,
                    requested=levels)




__all__ = ["SectorAlgebra", "sector_algebra", "generator_values", "sector_coefficients",
           "sector_forms", "sector_candidates", "SectorBasis", "sector_block", "sector_dimension",
           "sectors_by_shell", "lowest_degree", "MAX_SHELL", "solve_all_sectors"]
