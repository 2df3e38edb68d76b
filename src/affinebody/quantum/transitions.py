"""Transition matrix elements <f|O|i> between computed eigenstates and reduced transition
probabilities (paper, introduction and last section: "What are the corresponding quantum
transition probabilities?"; docs/quantum-transitions.md).

A level holds several states: the sectors of its eigenvectors (n = 2: the characters
e^{i(s alpha - v beta)} of L = R(alpha), R = R(beta) in phi = L diag(Q) R^T, one state each;
n = 3: the SO(3) x SO(3) multiplets (j, j'), (2j + 1)(2j' + 1) states each) and, where levels
of different blocks coincide, every such eigenvector. The *reduced strength*

    B(I -> F) = (1 / d_I) sum_{i in I} sum_{f in F} |<f|O|i>|^2,

(d_I the multiplicity of I) does not depend on the basis chosen inside the degenerate levels.

How an element is computed. A state of sector (s, v) is e^{i(s alpha - v beta)} a(y) with a
the reduced amplitude of :func:`affinebody.quantum.densities.joint_density` on the reduced
coordinates y ((|z|, |w|) for d'Alembert, (x, sigma) for the affine models, n = 2), normalised
under the reduced measure mu(y). Then

    <f|O|i> = int a_f(y) a_i(y) O_{Delta}(y) mu(y) dy,
    O_{Delta}(y) = (1/4 pi^2) int int O(phi(y, alpha, beta)) e^{-i(Ds alpha - Dv beta)},

with (Ds, Dv) = (s_f - s_i, v_f - v_i): the angular Fourier coefficient of the operator. That
is the selection rule, read off the operator itself: an element is nonzero only for the
(Ds, Dv) where O_Delta does not vanish (components of phi: (+-1, +-1); G =
phi^T phi = R diag(Q^2) R^T: Ds = 0, Dv in {0, +-2}; C = phi phi^T: Dv = 0, Ds in {0, +-2};
invariants: (0, 0)). The angular integrals are done by the trapezoidal rule on N x N angles,
N from the operator's bandwidth (exact for trigonometric polynomials of degree < N - |Delta|),
and checked on a second grid (:func:`converged_elements`; any smooth operator), the reduced
integral by Gauss-Legendre over the box where the states live.

n = 3. A state of the multiplet (j, j') is psi_c = sqrt(d) c^T Psi, Psi(L diag Q R^T) =
(D^j(L) (x) D^j'(R)) F(Q), F = Psi(diag Q) in V_j (x) V_j' (covariants3), c a unit vector,
d = (2j + 1)(2j' + 1). An operator in the invariants is a scalar of SO(3) x SO(3) (Dj = Dj' = 0,
the same element for each state of the multiplet). An operator with components is any
polynomial of degree <= 4 in the components of phi, G, C whose coefficients are expressions in
the invariants (e.g. phi11*phi22, G11 - trG/3, exp(-trG)*C13) is expanded in Wigner D
functions of L and R by quantum.tensor_operators3 (docs/quantum-transitions.md, "n = 3: any
polynomial expression"): radial functions r_t(Q) times constant tensors of ranks (l, l'); any
other expression is projected numerically on the ranks the levels can couple, at the nodes of
a chamber rule (:func:`project_levels`; "Operators that are not polynomials"). The angular
integrals are exact: int D^j_{ab} D^j'_{cd} D^l_{pq} = w[a, c, p] w[b, d, q] with w the
invariant vector of V_j (x) V_j' (x) V_l, and the strength summed over both multiplets is
d_F d_I |M|^2 with M of :func:`multiplet_matrix` (a Frobenius norm:
no Wigner-Eckart bookkeeping assumed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from affinebody._checks import require_x64
from affinebody.expressions import compile_expression
from affinebody.quantum import covariants3 as cov
from affinebody.quantum import tensor_operators3 as tops
from affinebody.quantum.channels3 import ChamberQuadrature, haar3_grid
from affinebody.quantum.densities import joint_density, measure
from affinebody.quantum.intervals import invariant_names, invariant_values
from affinebody.quantum.levels import Level, Sector, Settings, Spectrum, same_level

#: angular grid per angle (n = 2): the least, the most, and the samples of the bandwidth probe
ANGLES = 16
MAX_ANGLES = 160
PROBE2 = 256
#: the numerical projection of an operator on the angles (n = 2: two trapezoid grids; n = 3: two
#: chamber rules with two Euler-angle grids) must give elements that agree to this, relative to
#: the largest element, else the operator is refused
PROJECTION_TOLERANCE = 1e-10
#: n = 3 chamber rules of the numerical projection, (coarse, fine): (radial nodes, angle nodes)
#: of ChamberQuadrature.polar (d'Alembert), (r, angle, sigma nodes) of haar3_grid (affine)
RULES3 = {"lebesgue3": ((28, 12), (36, 16)), "haar3": ((24, 12, 24), (32, 16, 32))}
#: n = 3: the fine grid's Euler-angle rank exceeds the coarse one's by this on each side; while
#: the two grids disagree both are raised by it, at most RETRIES times
RANK_STEP = 2
RETRIES = 2
#: n = 3: shells of |Q| (quantiles of the nodes where the states live), each with its own
#: bandwidth and Euler-angle ranks, when one bandwidth for all would need more evaluations
#: than SHELL_WORK
SHELLS = 6
SHELL_WORK = 5e7
#: n = 3: most evaluations of the operator on the fine grid, and most angular components
#: computed (nodes x components; they are held a chunk of nodes at a time)
MAX_PROJECTION = 4e8
MAX_COEFFICIENTS = 3e8
#: Gauss-Legendre nodes per reduced coordinate (n = 2)
NODES2 = 96
#: elements of a non-vanishing harmonic are computed; below this fraction of the operator's
#: largest harmonic a harmonic counts as absent (the selection rule)
HARMONIC_FLOOR = 1e-12
#: the eigenvectors must be orthonormal under the quadrature to this (else the quadrature
#: does not resolve the states and no element is reported)
ORTHONORMALITY = 1e-8
#: a request over more states than this is refused before any work
MAX_STATES = 2000


def component_names(n: int) -> tuple[str, ...]:
    """Matrix components an operator may use besides the invariants: n = 2 phi11..phi22, G11..
    G22 (G = phi^T phi, the Green tensor), C11..C22 (C = phi phi^T, the Cauchy tensor);
    n = 3 phi11..phi33, G11..G33, C11..C33."""
    return tuple(f"{m}{a}{b}" for m in ("phi", "G", "C") for a in range(1, n + 1)
                 for b in range(1, n + 1))


def operator_names(n: int) -> tuple[str, ...]:
    """Every variable of an operator expression (docs/quantum-transitions.md)."""
    return invariant_names(n) + component_names(n)


@dataclass(frozen=True)
class Operator:
    """A configuration operator O(phi) given as an expression (``text``) in
    :func:`operator_names`; ``angular`` when it uses matrix components (not only invariants).

    n = 3, ``method``: "auto" takes the exact expansion in Wigner D functions
    (tensor_operators3.expand, ``expansion``) when the operator is a polynomial of degree <= 4
    in the components, and the numerical projection (:func:`project_levels`) otherwise
    (``expansion`` None); "quadrature" always the numerical projection."""

    text: str
    n: int
    field: str = "--operator"
    method: str = "auto"

    def __post_init__(self):
        require_x64()  # the expression is evaluated by JAX
        if self.method not in ("auto", "quadrature"):
            raise ValueError(f"Operator.method must be 'auto' or 'quadrature' (got "
                             f"{self.method!r})")
        expr = compile_expression(self.text, operator_names(self.n), field=self.field)
        object.__setattr__(self, "expression", expr)
        expansion = None
        if self.n == 3 and self.angular and self.method == "auto":
            try:  # not a polynomial in the components: the numerical projection
                expansion = tops.expand(expr, expr.used, self.text, self.field)
            except ValueError:
                expansion = None
        object.__setattr__(self, "expansion", expansion)

    def radial(self, Q: np.ndarray) -> np.ndarray:
        """n = 3, an operator with components: the radial functions r_t(Q) [P, terms] of its
        expansion in Wigner D functions (quantum.tensor_operators3) at Q [P, 3]."""
        if self.expansion is None:
            raise ValueError(f"{self.field}: {self.text!r} has no finite expansion in Wigner D "
                             f"functions (use transitions / level_matrix: numerical projection)")
        try:
            return self.expansion.radial(self.expression, Q)
        except ValueError as err:
            raise ValueError(f"{self.field}: {self.text!r} {err}") from None

    @property
    def angular(self) -> bool:
        return bool(set(self.expression.used) & set(component_names(self.n)))

    def __call__(self, Q: np.ndarray, alpha: np.ndarray | None = None,
                 beta: np.ndarray | None = None) -> np.ndarray:
        """O at phi = R(alpha) diag(Q) R(beta)^T (n = 2; Q [..., n] broadcast with the angles)."""
        values = invariant_values(Q)
        used = self.expression.used
        if self.angular:  # phi = R(alpha) diag(Q) R(beta)^T, G = phi^T phi, C = phi phi^T
            ca, sa, cb, sb = np.cos(alpha), np.sin(alpha), np.cos(beta), np.sin(beta)
            Q1, Q2 = Q[..., 0], Q[..., 1]
            P1, P2 = Q1 * Q1, Q2 * Q2
            recipes = {
                "phi11": lambda: Q1 * ca * cb + Q2 * sa * sb,
                "phi12": lambda: Q1 * ca * sb - Q2 * sa * cb,
                "phi21": lambda: Q1 * sa * cb - Q2 * ca * sb,
                "phi22": lambda: Q1 * sa * sb + Q2 * ca * cb,
                "G11": lambda: P1 * cb * cb + P2 * sb * sb,
                "G12": lambda: (P1 - P2) * cb * sb,
                "G21": lambda: (P1 - P2) * cb * sb,
                "G22": lambda: P1 * sb * sb + P2 * cb * cb,
                "C11": lambda: P1 * ca * ca + P2 * sa * sa,
                "C12": lambda: (P1 - P2) * ca * sa,
                "C21": lambda: (P1 - P2) * ca * sa,
                "C22": lambda: P1 * sa * sa + P2 * ca * ca,
            }
            for name in set(self.expression.used) & set(recipes):
                values[name] = recipes[name]()
        shape = np.broadcast_shapes(*(np.shape(values[k]) for k in used)) if used else ()
        out = np.asarray(self.expression(**{k: values[k] for k in used}), float)
        out = np.broadcast_to(out, shape if used else out.shape)
        if not np.all(np.isfinite(out)):
            raise ValueError(f"{self.field}: {self.text!r} is not finite where the states live "
                             f"(e.g. log of 0); use an operator that is finite on the body")
        return out


# ------------------------------------------------------------------ states of a level
@dataclass(frozen=True)
class Component:
    """One eigenvector of a level: its sectors (states) and its reduced amplitude."""

    sectors: tuple[Sector, ...]
    joint: object  # densities.Joint
    #: n = 3: the coordinates E [(2j + 1)(2j' + 1), r] in V_j (x) V_j' (harmonic bases of
    #: covariants3) of the amplitude's r M-fixed components, (j, j') = sectors[0]
    frame: np.ndarray | None = None

    @property
    def states(self) -> int:
        return sum(s.dimension for s in self.sectors)


def level_components(spectrum: Spectrum, level: Level, merge: float | None = None,
                     sector: Sector | None = None) -> list[Component]:
    """Every eigenvector of the solved blocks whose energy is ``level``'s (within the merge
    tolerance of :class:`~affinebody.quantum.levels.Settings`, error estimate within the
    level's): the level's states. Their state count must be the level's multiplicity.
    ``sector``: only the blocks holding it (their states of that sector must be the level's)."""
    merge = Settings().merge if merge is None else merge
    out = []
    for key, block in spectrum.blocks.items():
        if sector is not None and sector not in block.sectors:
            continue
        for i, E in enumerate(block.energies):
            # the merged entries of the level (an unconverged candidate at the same energy has
            # an error estimate above the level's, the largest of its entries)
            if same_level(E, level.energy, merge) and block.errors[i] <= level.error:
                one = Level(float(E), 1, block.sectors, float(block.errors[i]), key, i)
                out.append(Component(block.sectors, joint_density(spectrum, one),
                                     angular_frame(key, block.sectors[0])
                                     if spectrum.n == 3 else None))
    if sector is None:
        found, expected = sum(c.states for c in out), level.multiplicity
    else:
        found = sum(s.dimension for c in out for s in c.sectors if s == sector)
        expected = sum(s.dimension for s in level.sectors if s == sector)
    if found != expected:
        raise ValueError(f"transitions: the level at {level.energy:.9g} has {expected} states"
                         f"{'' if sector is None else ' of the sector'} but {found} eigenvector "
                         f"states were found at its energy")
    return out


def angular_frame(key: tuple, sector: Sector) -> np.ndarray:
    """n = 3: the M-fixed coordinates of a block's amplitude in V_j (x) V_j' (covariants3):
    the dedicated spin = vorticity = 1 channel (channels3, blocks "spin1") has f_a = Psi_aa
    (the covariant Psi(phi) = phi and its multiples: diagonal coordinates; V_1 in its harmonic
    basis is R^3 with D^1(L) = L); every other sector those of covariants3.fixed_subspace."""
    if key[0] == "spin1":
        E = np.zeros((9, 3))
        E[[0, 4, 8], [0, 1, 2]] = 1.0
        return E
    return cov.fixed_subspace(sector.spin, sector.vorticity)


def invariants_at(model: str, y: np.ndarray) -> np.ndarray:
    """Signed singular values Q [..., n] at the reduced coordinates y of ``model``'s joint
    density (densities.Joint): (|z|, |w|) -> (|z| + |w|, |z| - |w|); (x, sigma) -> exp((sigma
    +- x)/2); Q (lebesgue3); q -> exp(q) (haar3)."""
    if model == "lebesgue2":
        return np.stack([y[..., 0] + y[..., 1], y[..., 0] - y[..., 1]], -1)
    if model == "haar2":
        return np.exp(np.stack([(y[..., 1] + y[..., 0]) / 2, (y[..., 1] - y[..., 0]) / 2], -1))
    if model == "lebesgue3":
        return y
    return np.exp(y)


def reduced_quadrature(components: list[Component]) -> tuple[np.ndarray, np.ndarray]:
    """Nodes y [P, d] and weights [P] (the reduced measure included) covering every component:
    n = 2 a Gauss-Legendre product rule over the union of their boxes; n = 3 the chamber
    quadrature of the joint densities (the same for every block of a spectrum)."""
    first = components[0].joint
    if first.model in ("lebesgue2", "haar2"):
        lo = np.min([c.joint.box[:, 0] for c in components], axis=0)
        hi = np.max([c.joint.box[:, 1] for c in components], axis=0)
        x, w = np.polynomial.legendre.leggauss(NODES2)
        axes = [(lo[k] + (hi[k] - lo[k]) * (x + 1) / 2, (hi[k] - lo[k]) * w / 2)
                for k in range(2)]
        Y0, Y1 = np.meshgrid(axes[0][0], axes[1][0], indexing="ij")
        y = np.stack([Y0.ravel(), Y1.ravel()], -1)
        weights = np.outer(axes[0][1], axes[1][1]).ravel()
    else:
        y, weights = first.nodes, first.weights
    return y, weights * measure(first.model, y)


def amplitudes(component: Component, y: np.ndarray) -> np.ndarray:
    """The reduced amplitude [P, r] of a component at y (r = 1 for n = 2)."""
    a = np.asarray(component.joint.amplitude(y), float)
    return a.reshape(len(y), -1)


def harmonics(operator: Operator, Q: np.ndarray, angles: int = ANGLES,
              reach: int | None = None) -> dict[tuple[int, int], np.ndarray]:
    """(Delta s, Delta v) -> O_Delta [P] at the reduced nodes (module docstring) for |Delta s|,
    |Delta v| <= ``reach`` (default angles/2 - 1), by the trapezoidal rule on ``angles`` x
    ``angles`` angles: exact for a trigonometric polynomial of degree < angles - reach (a
    polynomial in the components), else with the aliasing of the higher harmonics
    (:func:`converged_elements` compares two grids). Only the harmonics that do not vanish
    (the selection rule). An operator in the invariants only has the single harmonic (0, 0)."""
    if not operator.angular:
        return {(0, 0): np.asarray(operator(Q), float)}
    reach = angles // 2 - 1 if reach is None else reach
    t = 2 * np.pi * np.arange(angles) / angles
    A, B = t[:, None], t[None, :]  # broadcast: a component of G or C depends on one angle
    k = np.arange(-reach, reach + 1)
    E = np.exp(-1j * t[:, None] * k[None, :]) / angles  # [N, K]: the DFT of the harmonics kept
    F = np.empty((len(Q), len(k), len(k)), complex)
    step = min(len(Q), max(1, 2_000_000 // angles**2))
    for s in range(0, len(Q), step):
        part = Q[s:s + step]
        if len(part) < step:  # one shape for every chunk: the expression compiles once
            part = np.concatenate([part, np.repeat(part[-1:], step - len(part), 0)])
        values = np.broadcast_to(operator(part[:, None, None, :], A[None], B[None]),
                                 (step, angles, angles))[:len(Q) - s]  # [p, N, N]
        # F[k, l] = mean O e^{-i(k a + l b)}
        F[s:s + step] = np.swapaxes(np.swapaxes(values @ E, 1, 2) @ E, 1, 2)
    size = np.max(np.abs(F), axis=0)
    top = float(np.max(size))
    out = {}
    for a, b in zip(*np.nonzero(size > HARMONIC_FLOOR * top), strict=True):
        # the element <f|O|i> needs k = Delta s, l = -Delta v (module docstring)
        out[(int(k[a]), int(-k[b]))] = F[:, a, b]
    return out or {(0, 0): np.zeros(len(Q))}


def bandwidth2(operator: Operator, Q: np.ndarray, tolerance=tops.BAND_TOLERANCE, floor=0.0
               ) -> int | None:
    """n = 2: the largest harmonic |k| of O along alpha and along beta (the other angle fixed
    at two random values) at the nodes Q [P, 2] whose Fourier coefficient on PROBE2 samples
    exceeds ``tolerance`` of the largest and ``floor`` (tensor_operators3.fourier_reach);
    None when not resolved."""
    if not operator.angular:
        return 0
    t = 2 * np.pi * np.arange(PROBE2) / PROBE2
    fixed = np.repeat(np.random.default_rng(16).uniform(0, 2 * np.pi, 2), PROBE2)
    sweep = np.tile(t, 2)  # one call: alpha swept at two betas, then beta at two alphas
    alpha, beta = np.concatenate([sweep, fixed]), np.concatenate([fixed, sweep])
    f = np.broadcast_to(operator(Q[:, None, :], alpha[None], beta[None]), (len(Q), 4 * PROBE2))
    reach = [tops.fourier_reach(f[:, k * PROBE2:(k + 1) * PROBE2], tolerance, floor)
             for k in range(4)]
    return None if None in reach else max(reach)


def probe_nodes(Q: np.ndarray, mass: np.ndarray, values: np.ndarray,
                largest: float | None = None, scale: float | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Where the bandwidth of an operator is probed, and the absolute floor below which its
    Fourier coefficients there do not count: among the nodes holding more than 1e-11 of the
    ``largest`` mass (w times the states' |amplitude|^2; default the largest of ``mass``), the
    12 farthest out (|Q| largest) and 8 spread over the rest (the farthest 20 nodes when none
    holds that much). An aliased harmonic enters the elements weighted by the node's mass, and
    the elements are of the size of the mass-weighted mean of |O| (``scale``, by default from
    ``values``, O at each node in one orientation): the floor is BAND_TOLERANCE times that
    mean times the largest mass over the node's own (the two-grid comparison checks the
    result)."""
    largest = float(np.max(mass)) if largest is None else largest
    heavy = np.flatnonzero(mass > 1e-11 * largest)
    if len(heavy) == 0:
        heavy = np.argsort(-np.linalg.norm(Q, axis=1))[:20]
    far = heavy[np.argsort(-np.linalg.norm(Q[heavy], axis=1))[:12]]
    probe = np.unique(np.concatenate([far, heavy[:: max(1, len(heavy) // 8)]]))
    if scale is None:
        scale = float(np.sum(mass * np.abs(values)) / np.sum(mass))
    return probe, tops.BAND_TOLERANCE * scale * largest / np.maximum(mass[probe], 1e-300)


def converged_elements(operator: Operator, Q: np.ndarray, weights: np.ndarray, jobs: list
                       ) -> tuple[np.ndarray, float, dict]:
    """n = 2: the elements int a_f a_i O_Delta mu dy of ``jobs`` [(a_f, a_i, Delta), ...] with
    the harmonics of :func:`harmonics` on two grids of N x N and (N + 8) x (N + 8) angles,
    N = 2 (B + reach) + 2 (at least ANGLES), B the bandwidth of O (:func:`bandwidth2`, at the
    farthest nodes where the states live), reach the largest |Delta|: exact for an operator
    polynomial in the components. The two must agree to PROJECTION_TOLERANCE relative to the
    largest element; ValueError, one line, when they do not, when B is not resolved, or when
    N exceeds MAX_ANGLES. Returns the elements of the finer grid, their relative difference to
    the coarser one (the projection error), and its harmonics."""
    reach = max((max(abs(d[0]), abs(d[1])) for *_, d in jobs), default=0)
    mass = np.zeros(len(Q))
    for a in {id(a): a for af, ai, _ in jobs for a in (af, ai)}.values():
        mass += weights * np.sum(a * a, -1)
    alpha, beta = np.random.default_rng(7).uniform(0, 2 * np.pi, 2)
    values = np.broadcast_to(operator(Q, alpha, beta), (len(Q),))
    probe, floor = probe_nodes(Q, mass, values)
    band = bandwidth2(operator, Q[probe], floor=floor)
    name = f"{operator.field} {operator.text!r}"
    if band is None:
        raise ValueError(f"{name}: its angular harmonics do not decay by |k| = "
                         f"{PROBE2 // 2 - 2} where the states live: a kink in the angles of L "
                         f"and R (e.g. abs), or features too sharp where |Q| is largest; it "
                         f"cannot be projected")
    angles = max(ANGLES, 2 * (band + reach) + 2)
    if angles > MAX_ANGLES:
        raise ValueError(f"{name}: its projection on these levels needs {angles} x {angles} "
                         f"angles per node (harmonics up to {band}), more than the "
                         f"{MAX_ANGLES} x {MAX_ANGLES} this command is built for: ask for "
                         f"fewer levels, or a smoother operator")

    def values(H):
        return np.array([0j if d not in H else _element(af, ai, weights, H[d])
                         for af, ai, d in jobs], complex)

    coarse = values(harmonics(operator, Q, angles, reach))
    H = harmonics(operator, Q, angles + 8, reach)
    fine = values(H)
    top = float(np.max(np.abs(fine), initial=0.0))
    diff = float(np.max(np.abs(fine - coarse), initial=0.0))
    if diff > PROJECTION_TOLERANCE * top:
        raise ValueError(f"{name}: its projection on the angles does not converge (on "
                         f"{angles} and {angles + 8} angles per rotation the elements differ "
                         f"by {diff / top:.1e} of the largest, more than "
                         f"{PROJECTION_TOLERANCE:g})")
    return fine, diff / top if top > 0 else 0.0, H


def selection_rule(n: int, allowed: list[tuple[int, int]], operator: Operator | None = None,
                   projection: Projection3 | None = None) -> str:
    """The selection rule in words."""
    if n == 3 and projection is not None:
        ranks = ", ".join(f"({l}, {lp})" for l, lp in projection.ranks)
        return (f"n = 3, the operator's SO(3) x SO(3) tensor ranks (l, l') up to "
                f"({projection.lmax[0]}, {projection.lmax[1]}) (the most these levels can "
                f"couple), projected numerically at every node (Euler-angle ranks "
                f"{projection.grids[0]} and {projection.grids[1]} on L, R; elements agree to "
                f"{projection.error:.1e}): {{{ranks}}}; an element <f|O|i> vanishes unless "
                f"|j - j_f| <= l <= j + j_f and |j' - j'_f| <= l' <= j' + j'_f for one of them")
    if n == 3 and operator is not None and operator.angular:
        ranks = ", ".join(f"({l}, {lp})" for l, lp in operator.expansion.ranks)
        return (f"n = 3, the operator's SO(3) x SO(3) tensor ranks (l, l') (its expansion in "
                f"Wigner D functions of L and R, angular integrals done exactly): {{{ranks}}}; "
                f"an element <f|O|i> vanishes unless |j - j_f| <= l <= j + j_f and "
                f"|j' - j'_f| <= l' <= j' + j'_f for one of them; final levels outside these "
                f"rules have strength 0")
    if n == 3:
        return ("n = 3, an operator in the invariants is a scalar of SO(3) x SO(3): only "
                "final levels holding the initial sector (Delta j = Delta j' = 0) are reached, "
                "with the same element for every state of the multiplet")
    pairs = ", ".join(f"({s:+d}, {v:+d})" for s, v in sorted(allowed))
    return (f"n = 2: the operator's angular harmonics allow (Delta spin, Delta vorticity) in "
            f"{{{pairs}}}; every other element vanishes by the SO(2) x SO(2) symmetry and "
            f"final levels without such a sector have strength 0")


@dataclass(frozen=True)
class Transition:
    initial: int
    final: int
    E_initial: float
    E_final: float
    strength: float
    sector_final: tuple[Sector, ...]
    sector_initial: tuple[Sector, ...]
    #: a sector of the final level is reached by a harmonic of the operator
    allowed: bool

    def as_dict(self) -> dict:
        return {"initial": self.initial, "final": self.final, "E_initial": self.E_initial,
                "E_final": self.E_final, "strength": self.strength,
                "sector_final": [s.as_dict() for s in self.sector_final],
                "sector_initial": [s.as_dict() for s in self.sector_initial],
                "allowed": self.allowed}


@dataclass(frozen=True)
class TransitionTable:
    transitions: list[Transition]
    operator: str
    selection_rule: str
    #: largest |<a|b> - delta_ab| over the states compared (the quadrature's own check)
    orthonormality_error: float
    #: the largest difference of the elements between the two grids of the numerical
    #: projection, relative to the largest element (None: angular integrals done exactly)
    projection_error: float | None = None


def _element(fa: np.ndarray, fi: np.ndarray, weights: np.ndarray, O: np.ndarray) -> complex:
    return complex(np.sum(weights * O * np.sum(fa * fi, -1)))


def matrix_elements(spectrum: Spectrum, operator: Operator, initial: int, final: int
                    ) -> np.ndarray:
    """The matrix <f|O|i> [states of level ``final``, states of level ``initial``] (indices
    into ``spectrum.levels``, the converged levels ascending; n = 2 only, where each sector is
    one state; the order of states is the order of the components and their sectors)."""
    if spectrum.n != 2:
        raise ValueError("matrix_elements: n = 2 only (n = 3: use transitions)")
    ci = level_components(spectrum, spectrum.levels[initial])
    cf = level_components(spectrum, spectrum.levels[final])
    y, w = reduced_quadrature(ci + cf)
    jobs = [(amplitudes(f, y), amplitudes(i, y), (sf.spin - si.spin, sf.vorticity - si.vorticity))
            for f in cf for sf in f.sectors for i in ci for si in i.sectors]
    values = converged_elements(operator, invariants_at(ci[0].joint.model, y), w, jobs)[0]
    return values.reshape(sum(len(f.sectors) for f in cf), sum(len(i.sectors) for i in ci))


# ------------------------------------------------------- n = 3: operators with components
def sector_amplitudes(component: Component, y: np.ndarray, f: np.ndarray | None = None
                      ) -> list[tuple[Sector, np.ndarray]]:
    """n = 3: each sector of a component with its amplitude F [P, 2j + 1, 2j' + 1] = Psi(diag
    Q(y)) in V_j (x) V_j' (the transpose twin (j', j) of a block of a transpose-symmetric model
    has Psi'(phi) = swap Psi(phi^T), so F^T)."""
    f = amplitudes(component, y) if f is None else f  # f: amplitudes(component, y)
    first = component.sectors[0]
    F = (f @ component.frame.T).reshape(len(y), 2 * first.spin + 1, 2 * first.vorticity + 1)
    return [(s, F if (s.spin, s.vorticity) == (first.spin, first.vorticity)
             else F.transpose(0, 2, 1)) for s in component.sectors]


def pointwise_moments(final: Component, af: np.ndarray, initial: Component, ai: np.ndarray,
                      weights: np.ndarray) -> dict[tuple[Sector, Sector], np.ndarray]:
    """n = 3: the moments of :func:`multiplet_moments` with the nodes as terms, w_P F_f[P, b, d]
    F_i[P, b', d'] [P, b, d, b', d'] (the numerical projection: tensor_operators3.contract)."""
    small = weights[:, None, None] * af[:, :, None] * ai[:, None, :]  # [P, r_f, r_i]
    return _frame_moments(final, initial, small)


def weighted_radial(radial: np.ndarray, weights: np.ndarray, f: np.ndarray) -> np.ndarray:
    """[P, terms x r]: w r_t(Q) f_i(Q), the right factor of :func:`multiplet_moments`."""
    return ((weights[:, None] * radial)[:, :, None] * f[:, None, :]).reshape(len(f), -1)


def multiplet_moments(final: Component, af: np.ndarray, initial: Component,
                      right: np.ndarray) -> dict[tuple[Sector, Sector], np.ndarray]:
    """n = 3: the radial moments int mu r_t F_f[b, d] F_i[b', d'] [terms, b, d, b', d'] of
    every pair of sectors of two components (``right`` = :func:`weighted_radial` of the
    initial amplitude; computed in the M-fixed coordinates, then mapped by the frames)."""
    ri = initial.frame.shape[1]
    small = (af.T @ right).reshape(af.shape[1], -1, ri).transpose(1, 0, 2)  # [t, r_f, r_i]
    return _frame_moments(final, initial, small)


def _frame_moments(final: Component, initial: Component, small: np.ndarray
                   ) -> dict[tuple[Sector, Sector], np.ndarray]:
    """[t, r_f, r_i] M-fixed moments -> {(sector_f, sector_i): [t, b, d, b', d']} in V_j (x)
    V_j' (the frames of the components; a transpose twin swaps its two indices)."""
    full = np.einsum("bx,txy,cy->tbc", final.frame, small, initial.frame, optimize=True)
    f0, i0 = final.sectors[0], initial.sectors[0]
    full = full.reshape(len(full), 2 * f0.spin + 1, 2 * f0.vorticity + 1, 2 * i0.spin + 1,
                        2 * i0.vorticity + 1)
    out = {}
    for sf in final.sectors:
        for si in initial.sectors:
            m = full
            if (sf.spin, sf.vorticity) != (f0.spin, f0.vorticity):
                m = m.transpose(0, 2, 1, 3, 4)
            if (si.spin, si.vorticity) != (i0.spin, i0.vorticity):
                m = m.transpose(0, 1, 2, 4, 3)
            out[(sf, si)] = m
    return out


def multiplet_matrix(operator: Operator, final: Sector, initial: Sector, moments: np.ndarray
                     ) -> np.ndarray | None:
    """n = 3: the matrix M [d_F, d_I] with <f|O|i> = sqrt(d_F d_I) c_f^T M c_i for the states
    psi_c = sqrt(d) c^T Psi of two multiplets (c unit vectors of V_j (x) V_j'), i.e.

        M = int mu dQ int dL dR ((D(L) (x) D(R)) F_f) ((D(L) (x) D(R)) F_i)^T O(L diag Q R^T),

    done exactly in the angles by the operator's expansion in Wigner D functions
    (quantum.tensor_operators3; ``moments`` from :func:`multiplet_moments`); None when no
    rank of the operator connects the two (the selection rule)."""
    return tops.reduced_matrix(operator.expansion, moments, (final.spin, final.vorticity),
                               (initial.spin, initial.vorticity))


def _strength3(operator: Operator, ci: Component, right: np.ndarray, cf: Component, af
               ) -> tuple[float, bool]:
    """n = 3, an operator with components: sum over the states of two components of
    |<f|O|i>|^2 = sum over their sector pairs of d_F d_I |M|^2 (:func:`multiplet_matrix`)."""
    total, allowed = 0.0, False
    for (sf, si), moments in multiplet_moments(cf, af, ci, right).items():
        M = multiplet_matrix(operator, sf, si, moments)
        if M is not None:
            allowed = True
            total += sf.dimension * si.dimension * float(np.sum(M * M))
    return total, allowed


def level_matrix(spectrum: Spectrum, operator: Operator, initial: int, final: int,
                 states: LevelStates | None = None) -> np.ndarray:
    """n = 3: <f|O|i> [states of level ``final``, states of level ``initial``] in the states
    psi_(a, c) = sqrt(d) ((D^j(L) (x) D^j'(R)) F)_(a, c) of each multiplet (the standard basis
    vectors c of V_j (x) V_j', harmonic bases; multiplets in the order of the level's
    components and their sectors): the blocks sqrt(d_F d_I) M of :func:`multiplet_matrix`
    (an operator in the invariants: its element times the identity on equal multiplets).
    ``states``: the spectrum's :func:`level_states`, computed here if not given."""
    if spectrum.n != 3:
        raise ValueError("level_matrix: n = 3 only (n = 2: matrix_elements)")
    states = level_states(spectrum) if states is None else states
    if operator.angular and operator.expansion is None:  # the numerical projection
        blocks = project_levels(spectrum, operator, states, [(final, initial)]).blocks
        rows = []
        for nf, f in enumerate(states.components[final]):
            lines = []
            for sf in f.sectors:
                line = []
                for ni, i in enumerate(states.components[initial]):
                    for si in i.sectors:
                        M = blocks[(final, initial, nf, ni, sf, si)]
                        line.append(np.zeros((sf.dimension, si.dimension)) if M is None
                                    else math.sqrt(sf.dimension * si.dimension) * M)
                lines.append(np.hstack(line))
            rows.append(np.vstack(lines))
        return np.vstack(rows)
    w, Q = states.weights, states.Q
    angular = operator.angular
    radial = operator.radial(Q) if angular else np.asarray(operator(Q), float)[:, None]
    rows = []
    for f, af in zip(states.components[final], states.amplitudes[final], strict=True):
        row = []
        for i, ai in zip(states.components[initial], states.amplitudes[initial], strict=True):
            moments = multiplet_moments(f, af, i, weighted_radial(radial, w, ai))
            blocks = []
            for sf in f.sectors:
                line = []
                for si in i.sectors:
                    if angular:
                        M = multiplet_matrix(operator, sf, si, moments[(sf, si)])
                    elif (sf.spin, sf.vorticity) == (si.spin, si.vorticity):
                        mom = moments[(sf, si)][0]
                        M = np.einsum("bdbd->", mom) / sf.dimension * np.eye(sf.dimension)
                    else:
                        M = None
                    line.append(np.zeros((sf.dimension, si.dimension)) if M is None
                                else math.sqrt(sf.dimension * si.dimension) * M)
                blocks.append(np.hstack(line))
            row.append(np.vstack(blocks))
        rows.append(np.hstack(row))
    return np.vstack(rows)


@dataclass(frozen=True)
class LevelStates:
    """Every converged level's components (:func:`level_components`) and their reduced
    amplitudes at one reduced quadrature (nodes ``y``, ``weights`` with the measure, signed
    singular values ``Q``): what every table of one spectrum shares (:func:`level_states`)."""

    components: list
    y: np.ndarray
    weights: np.ndarray
    Q: np.ndarray
    amplitudes: list


def level_states(spectrum: Spectrum) -> LevelStates:
    """The :class:`LevelStates` of ``spectrum`` (pass it to :func:`transitions` and
    :func:`level_matrix` to reuse it across operators)."""
    if not spectrum.levels:
        raise ValueError("transitions: no level of the spectrum converged (raise "
                         "quantum.basis_size, or loosen quantum.tolerance)")
    components = [level_components(spectrum, lv) for lv in spectrum.levels]
    y, w = reduced_quadrature([c for cs in components for c in cs])
    Q = invariants_at(components[0][0].joint.model, y)
    return LevelStates(components, y, w, Q,
                       [[amplitudes(c, y) for c in cs] for cs in components])


def transitions(spectrum: Spectrum, operator: Operator, initial: int = 0,
                states: LevelStates | None = None) -> TransitionTable:
    """Reduced strengths B(I -> F) of ``operator`` from the level ``initial`` (0: the ground
    level) to every level F, F = I included (module docstring). Levels are indexed as
    ``spectrum.levels``: the converged levels in ascending order, the ``states`` list of
    ``affinebody spectrum --json`` (an unconverged candidate is neither an initial nor a final
    level). ``states``: the spectrum's :func:`level_states`, computed here if not given."""
    if operator.n != spectrum.n:
        raise ValueError(f"--operator is for n = {operator.n}, the spectrum is n = {spectrum.n}")
    levels = spectrum.levels
    if sum(lv.multiplicity for lv in levels) > MAX_STATES:
        raise ValueError(f"transitions: {sum(lv.multiplicity for lv in levels)} states is more "
                         f"than the {MAX_STATES} this command is built for: ask for fewer levels")
    if not levels:
        raise ValueError("transitions: no level of the spectrum converged (raise "
                         "quantum.basis_size, or loosen quantum.tolerance)")
    if not 0 <= initial < len(levels):
        raise ValueError(f"--from {initial} is not a level: the spectrum has levels 0.."
                         f"{len(levels) - 1}")
    states = level_states(spectrum) if states is None else states
    components, w, Q, amps = states.components, states.weights, states.Q, states.amplitudes
    exact3 = spectrum.n == 3 and operator.angular and operator.expansion is not None
    if exact3:
        radial = operator.radial(Q)
        rights = [weighted_radial(radial, w, a) for a in amps[initial]]
    start = components[initial]
    error = 0.0
    for k, cs in enumerate(components):  # orthonormality check against the initial states
        for ci, ai in zip(start, amps[initial], strict=True):
            for c, a in zip(cs, amps[k], strict=True):
                if spectrum.n == 2 and not set(ci.sectors) & set(c.sectors):
                    continue
                if spectrum.n == 3 and not _multiplets(ci) & _multiplets(c):
                    continue
                overlap = _element(a, ai, w, np.ones(len(w))).real
                error = max(error, abs(overlap - (1.0 if c is ci else 0.0)))
    if error > ORTHONORMALITY:
        raise ValueError(f"transitions: the eigenvectors are orthonormal only to {error:.1e} "
                         f"under the quadrature (the states are not resolved; raise "
                         f"quantum.basis_size)")
    d_initial = levels[initial].multiplicity
    totals, reached = np.zeros(len(levels)), np.zeros(len(levels), bool)
    H, projection, projection_error = {}, None, None
    if spectrum.n == 2:  # every element of every sector pair, the harmonics converged
        jobs, where = [], []
        for k, cs in enumerate(components):
            for ci, ai in zip(start, amps[initial], strict=True):
                for cf, af in zip(cs, amps[k], strict=True):
                    for si in ci.sectors:
                        for sf in cf.sectors:
                            delta = (sf.spin - si.spin, sf.vorticity - si.vorticity)
                            jobs.append((af, ai, delta))
                            where.append((k, delta))
        values, projection_error, H = converged_elements(operator, Q, w, jobs)
        for (k, delta), v in zip(where, values, strict=True):
            if delta in H:
                reached[k] = True
                totals[k] += abs(v) ** 2
    elif operator.angular and not exact3:  # n = 3, the numerical projection
        projection = project_levels(spectrum, operator, states,
                                    [(k, initial) for k in range(len(levels))])
        projection_error = projection.error
        for (k, _, _, _, sf, si), M in projection.blocks.items():
            if M is not None:
                reached[k] = True
                totals[k] += sf.dimension * si.dimension * float(np.sum(M * M))
    else:
        H = {(0, 0): None}
        for k, cs in enumerate(components):
            for n_i, (ci, ai) in enumerate(zip(start, amps[initial], strict=True)):
                for cf, af in zip(cs, amps[k], strict=True):
                    if exact3:
                        t, a = _strength3(operator, ci, rights[n_i], cf, af)
                        totals[k] += t
                        reached[k] |= a
                        continue
                    common = _multiplets(ci) & _multiplets(cf)
                    if common:
                        reached[k] = True
                        element = abs(_element(af, ai, w, np.asarray(operator(Q), float))) ** 2
                        totals[k] += element * sum(s.dimension for s in ci.sectors
                                                   if (s.spin, s.vorticity) in common)
    out = [Transition(initial, k, levels[initial].energy, lv.energy, float(totals[k]) / d_initial,
                      lv.sectors, levels[initial].sectors, bool(reached[k]))
           for k, lv in enumerate(levels)]
    rule = selection_rule(spectrum.n, sorted(H), operator, projection)
    return TransitionTable(out, operator.text, rule, error, projection_error)


# ------------------------------------------- n = 3: the numerical projection of an operator
@dataclass(frozen=True)
class Projection3:
    """n = 3, an operator without a finite expansion in Wigner D functions: the matrices M of
    :func:`multiplet_matrix` between the level pairs asked for, from its numerical projection
    on the fine grid (:func:`project_levels`). ``blocks``: (final level, initial level, final
    component, initial component, final sector, initial sector) -> M (None: forbidden);
    ``error``: the largest difference of the elements sqrt(d_F d_I) M between the coarse and
    the fine grid, relative to the largest; ``ranks``: the (l, l') the projection holds;
    ``lmax``: the ranks projected on; ``grids``: the Euler-angle ranks (L, R) of the coarse
    and the fine grid."""

    blocks: dict
    error: float
    ranks: tuple
    lmax: tuple
    grids: tuple


def projection_rule(spectrum: Spectrum, joint, fine: bool) -> tuple[np.ndarray, np.ndarray]:
    """n = 3: nodes y [P, 3] and weights (the reduced measure included) of the chamber rule of
    the numerical projection (RULES3, coarse or ``fine``), sized for the basis degree
    (``quantum.basis_size``): d'Alembert ChamberQuadrature.polar out to the joint density's
    box, the affine models haar3_grid with the spectrum's scales."""
    extra = max(0, int(spectrum.settings.get("basis_size", 4)) - 4)
    if joint.model == "lebesgue3":
        n_rho, n_angle = RULES3["lebesgue3"][int(fine)]
        q = ChamberQuadrature.polar(float(joint.box[0, 1]), n_rho + 2 * extra, n_angle + extra)
        return q.nodes, q.weights
    n_r, n_angle, n_sigma = RULES3["haar3"][int(fine)]
    settings = spectrum.settings
    grid = haar3_grid(settings["scale"], settings.get("scale_sigma", 1.0),
                      settings.get("centre", 0.0), n_r + 2 * extra, n_angle + extra,
                      n_sigma + 2 * extra)
    return grid.nodes, grid.weights


def project_levels(spectrum: Spectrum, operator: Operator, states: LevelStates,
                   pairs: list[tuple[int, int]]) -> Projection3:
    """n = 3: the element matrices M of an operator given by any expression between the levels
    of ``pairs`` [(final, initial), ...] (docs/quantum-transitions.md, "Operators that are not
    polynomials"). Between multiplets with j, j_f only the ranks l <= j + j_f contribute, so O
    is projected on the ranks up to lmax = the largest j_f + j_i (and j'_f + j'_i) at every
    node of a chamber rule (tensor_operators3.project) and fed to the contraction of the exact
    path (tensor_operators3.contract, the nodes as terms, the moments w F_f (x) F_i). The
    Euler-angle ranks are the bandwidth B of O on each side (tensor_operators3.bandwidth, at
    the farthest nodes where the states live) plus lmax; all of it is done on a coarse and on
    a fine grid (RULES3, ranks + RANK_STEP) and the elements must agree to
    PROJECTION_TOLERANCE. ValueError, one line, when they do not, when the bandwidth is not
    resolved, or when the work exceeds MAX_PROJECTION evaluations / MAX_COEFFICIENTS."""
    comps = states.components
    levels = sorted({k for pair in pairs for k in pair})
    top = {k: (max(s.spin for c in comps[k] for s in c.sectors),
               max(s.vorticity for c in comps[k] for s in c.sectors)) for k in levels}
    lmax = tuple(max(top[f][side] + top[i][side] for f, i in pairs) for side in (0, 1))
    joint = comps[levels[0]][0].joint
    rules = [projection_rule(spectrum, joint, fine) for fine in (False, True)]
    expr, used = operator.expression, operator.expression.used
    name = f"{operator.field} {operator.text!r}"
    # the bandwidth per shell of |Q| (it grows outwards, and the work like its sixth power)
    y, w = rules[1]
    Q = invariants_at(joint.model, y)
    mass = sum(w * np.sum(amplitudes(c, y) ** 2, -1) for k in levels for c in comps[k])
    radius = np.linalg.norm(Q, axis=1)
    heavy = mass > 1e-11 * np.max(mass)
    turn = tops.side_rule(1, None)[0][:2]  # two rotations: O at every node in one orientation
    values = np.zeros(len(Q))
    try:
        values[heavy] = tops.operator_grid(expr, used, Q[heavy], turn[:1], turn[1:])[:, 0, 0]
    except ValueError as err:
        raise ValueError(f"{name} {err}") from None
    scale = float(np.sum(mass * np.abs(values)) / np.sum(mass))

    def plan(shells):
        edges = np.quantile(radius[heavy], np.linspace(0, 1, shells + 1)[1:-1])
        shell = np.searchsorted(edges, radius)
        bands = []
        for g in range(shells):
            members = np.flatnonzero(shell == g)
            probe, floor = probe_nodes(Q[members], mass[members], values[members],
                                       np.max(mass), scale)
            try:
                band = tops.bandwidth(expr, used, Q[members[probe]], floor=floor)
            except ValueError as err:
                raise ValueError(f"{name} {err}") from None
            if None in band:
                raise ValueError(f"{name}: its angular spectrum does not decay by rank "
                                 f"{tops.PROBE_SAMPLES // 2 - 2} where the states live: a kink "
                                 f"in the rotations of phi = L diag(Q) R^T (e.g. abs), or "
                                 f"features too sharp where |Q| is largest (e.g. exp(-0.1*G11) "
                                 f"for a body whose Q spreads to 100); it cannot be projected")
            bands.append(band)
        wide = tuple(max(b[side] for b in bands) for side in (0, 1))
        lm = tuple(0 if wide[side] == 0 else lmax[side] for side in (0, 1))
        coarse = [tuple(b[side] + lm[side] for side in (0, 1)) for b in bands]
        fine = [tuple(r + RANK_STEP if wide[side] > 0 else 0 for side, r in enumerate(c))
                for c in coarse]
        counts = np.bincount(shell, minlength=shells)
        rows = tops.side_rows(used)
        work = sum(int(counts[g]) * tops.side_points(fine[g][0], rows[0])
                   * tops.side_points(fine[g][1], rows[1]) for g in range(shells))
        return edges, lm, coarse, fine, work

    edges, lm, coarse, fine, work = plan(1)
    if work > SHELL_WORK:  # worth a bandwidth per shell
        edges, lm, coarse, fine, work = plan(SHELLS)
    counts = np.bincount(np.searchsorted(edges, radius), minlength=len(edges) + 1)
    kept = len(rules[1][0]) * sum((2 * l + 1) ** 2 for l in range(lm[0] + 1)) * sum(
        (2 * l + 1) ** 2 for l in range(lm[1] + 1))  # angular components computed
    rows = tops.side_rows(used)

    per_node = sum((2 * l + 1) ** 2 for l in range(lm[0] + 1)) * sum(
        (2 * l + 1) ** 2 for l in range(lm[1] + 1))
    chunk = max(1, int(4e6 // per_node))  # nodes whose angular components are held at once

    def evaluate(rule, ranks):
        """The blocks on one grid: the contraction is a sum over the nodes, done chunk by
        chunk and rank by rank; the ranks below HARMONIC_FLOOR of the largest are dropped at
        the end (the selection rule)."""
        y, w = rule
        Q = invariants_at(joint.model, y)
        where = np.searchsorted(edges, np.linalg.norm(Q, axis=1))
        amps = {k: [amplitudes(c, y) for c in comps[k]] for k in levels}
        sums, size = {}, {}
        for g in range(len(edges) + 1):
            members = np.flatnonzero(where == g)
            for start in range(0, len(members), chunk):
                idx = members[start:start + chunk]
                try:
                    part = tops.project(expr, used, Q[idx], lm, ranks[g])
                except ValueError as err:
                    raise ValueError(f"{name} {err}") from None
                for key, T in part.items():
                    size[key] = max(size.get(key, 0.0), float(np.max(np.abs(T))))
                for kf, ki in pairs:
                    for nf, cf in enumerate(comps[kf]):
                        for ni, ci in enumerate(comps[ki]):
                            moments = pointwise_moments(cf, amps[kf][nf][idx], ci,
                                                        amps[ki][ni][idx], w[idx])
                            for (sf, si), m in moments.items():
                                block = (kf, ki, nf, ni, sf, si)
                                for key, T in part.items():
                                    M = tops.contract({key: T}, m, (sf.spin, sf.vorticity),
                                                      (si.spin, si.vorticity))
                                    if M is not None:
                                        sums[(block, key)] = sums.get((block, key), 0.0) + M
                                sums.setdefault((block, None), None)
        largest = max(size.values())
        kept = tuple(sorted(key for key, v in size.items() if v > HARMONIC_FLOOR * largest))
        blocks = {}
        for block, _ in [k for k in sums if k[1] is None]:
            found = [sums[(block, key)] for key in kept if (block, key) in sums]
            blocks[block] = sum(found) if found else None
        return blocks, kept

    for attempt in range(1 + RETRIES):  # the ranks raised while the two grids disagree
        if attempt:
            coarse = fine
            fine = [tuple(r + RANK_STEP if r else 0 for r in c) for c in coarse]
            work = sum(int(n) * tops.side_points(f[0], rows[0]) * tops.side_points(f[1], rows[1])
                       for n, f in zip(counts, fine, strict=True))
        if work > MAX_PROJECTION or kept > MAX_COEFFICIENTS:
            raise ValueError(f"{name}: projecting it on the ranks up to {lm} of these levels "
                             f"needs Euler-angle ranks up to {max(fine)} on {len(rules[1][0])} "
                             f"nodes ({work:.1e} evaluations, {kept:.1e} coefficients), more "
                             f"than the {MAX_PROJECTION:.0e} / {MAX_COEFFICIENTS:.0e} this "
                             f"command is built for: ask for fewer levels, or a smoother "
                             f"operator")
        low, high = evaluate(rules[0], coarse), evaluate(rules[1], fine)
        diff, size = 0.0, 0.0
        for key, M in high[0].items():
            scale = math.sqrt(key[4].dimension * key[5].dimension)
            A = np.zeros(1) if M is None else np.asarray(M)
            B = np.zeros(1) if low[0][key] is None else np.asarray(low[0][key])
            size = max(size, scale * float(np.max(np.abs(A))))
            diff = max(diff, scale * float(np.max(np.abs(A - B))))
        if diff <= PROJECTION_TOLERANCE * size:
            return Projection3(high[0], diff / size if size > 0 else 0.0, high[1], lm,
                               (max(coarse), max(fine)))
    raise ValueError(f"{name}: its projection on the angles does not converge (Euler-angle "
                     f"ranks up to {max(coarse)} and {max(fine)}, chamber rules of "
                     f"{len(rules[0][0])} and {len(rules[1][0])} nodes: the elements differ "
                     f"by {diff / size:.1e} of the largest, more than "
                     f"{PROJECTION_TOLERANCE:g})")


def _multiplets(c: Component) -> set[tuple[int, int]]:
    """n = 3: the (j, j') of a component's sectors (an invariant connects equal (j, j'), parities
    included: one odd under phi -> -phi, like det, connects opposite parities)."""
    return {(s.spin, s.vorticity) for s in c.sectors}


def trk_sum(table: TransitionTable) -> float:
    """The energy-weighted sum sum_F (E_F - E_I) B(I -> F) of a table (the Thomas-Reiche-Kuhn
    sum over the levels computed; docs/quantum-transitions.md)."""
    return math.fsum((t.E_final - t.E_initial) * t.strength for t in table.transitions)


__all__ = ["ANGLES", "MAX_ANGLES", "PROBE2", "bandwidth2", "probe_nodes", "PROJECTION_TOLERANCE",
           "RULES3", "RANK_STEP", "RETRIES", "SHELLS", "SHELL_WORK",
           "MAX_PROJECTION", "MAX_COEFFICIENTS", "MAX_STATES", "converged_elements",
           "Projection3", "projection_rule", "project_levels", "pointwise_moments",
           "component_names", "operator_names",
           "Operator", "Component", "level_components", "invariants_at", "reduced_quadrature",
           "amplitudes", "harmonics", "selection_rule", "angular_frame",
           "LevelStates", "level_states", "sector_amplitudes", "weighted_radial",
           "multiplet_moments", "multiplet_matrix", "level_matrix", "Transition", "TransitionTable",
           "matrix_elements", "transitions", "trk_sum"]
