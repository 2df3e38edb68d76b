"""Probability densities of deformation invariants from |Psi|^2 with the right measure
(paper, last section: "Performing some partial integrations one can obtain from Psi-bar Psi
probability distributions for ... deformation invariants, orientations of the main axes").

Every density is an exact marginal of the joint density of the reduced variables, evaluated
point by point (docs/theory/densities.md): at each output value y,

    p_f(y) = int delta(f(x) - y) rho(x) dx,

done by a change of variables that puts the level set {f = y} on a fixed parameter domain
(with the Jacobian 1/|grad f| and the end points that depend on y, so the cusps at det = 0 and
Q_n = 0 and the walls Q_a = Q_b are end points of the rule, never inside it) and Gauss-Legendre
quadrature over the remaining variables. No histogram.

Joint densities (the reduced eigenfunction is orthonormal under the reduced measure, so each
integrates to 1; docs/theory/two-polar.md):

* d'Alembert n = 2, variables Q: in r1 = |z| = (Q1 + Q2)/2, r2 = |w| = (Q1 - Q2)/2,
  rho = f(r1, r2)^2 r1 r2 dr1 dr2 (= f^2 (Q1^2 - Q2^2)/8 dQ1 dQ2).
* affine n = 2 (GL+(2)), variables q: in x = q1 - q2 >= 0, sigma = q1 + q2 = ln det phi,
  rho = F(x, sigma)^2 sinh x = (sum c u_j(x) h_l(sigma))^2 x dx dsigma (g^2 sinh x = x).
* d'Alembert n = 3, variables Q on Q1 > Q2 > |Q3|: rho = sum_a f_a(Q)^2 prod_{a<b}(Q_a^2 - Q_b^2).
* affine n = 3, variables q on q1 > q2 > q3: rho = sum_a f_a(q)^2 prod_{a<b} sinh(q_a - q_b).

For a multiplet (n = 3, dimension > 1) the f_a are the M-fixed coordinates and rho is the
density of the multiplet summed over its states (its orientation density is uniform). The n = 3
bases are known on the solver's grid (channels3: values, n3: a recipe over candidates); every
one of their functions is front(x) x polynomial of degree <= basis_size, so the amplitude is
re-expressed exactly in that form (fitted at the nodes, checked off them) for fast evaluation
at the quadrature points of the marginals.

Marginals reported: Q_a (d'Alembert) or q_a (affine), det phi, Tr G. Each carries ``error``,
the largest change over the output points between the Gauss rule of N nodes per integrated
variable and the nested coarser rule of 2N/3 nodes (N raised until the error is at most
``tolerance`` times the peak of the density, else the density is flagged ``converged: false``);
this is the quadrature error of the marginal of the computed eigenfunction (the eigenfunction's
own discretisation error is the level's ``error``). ``integral`` is int p dy by Gauss-Legendre
panels graded towards y = 0.

Orientations: a sector state e^{i(s alpha + k beta)} f (n = 2) has |Psi|^2 independent of the
angles alpha, beta of L and R, so both orientation densities are exactly uniform, 1/(2 pi) on
[0, 2 pi) (a real standing wave cos(s alpha + k beta) would not be; the sector labels fix the
complex state). n = 3: the multiplet sum is invariant under L -> U L, R -> V R, so L and R are
Haar-distributed on SO(3); the density of the rotation angle omega in [0, pi] of L (and of R) is
exactly (1 - cos omega)/pi. A single state of a multiplet has the |D^j|^2 pattern of its
magnetic numbers (quantum/orientations3.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cache

import numpy as np
from scipy import linalg

from affinebody.quantum.bases import sqrt_x_over_sinh
from affinebody.quantum.levels import Level, Spectrum

#: node counts tried per integrated variable (n = 2: one variable; n = 3: two, so fewer),
#: each 3/2 of the one before: the nested check rule of 2N/3 nodes is the previous count
NODES = {2: (48, 72, 108, 162, 243), 3: (24, 36, 54, 81)}
#: default number of output points of each density
POINTS = {2: 301, 3: 101}
DEFAULT_TOLERANCE = 1e-8
#: what the invariants named Q_a / q_a are (the JSON's ``variables_note``)
VARIABLES = {
    "Q": "d'Alembert: signed singular values Q1 >= ... >= |Qn| of phi, Qn with the sign of det "
         "phi; densities per unit of the variable on the x axis",
    "q": "affine models (GL+(n)): q_a = ln Q_a, q1 >= ... >= qn; det phi = exp(sum q) > 0; "
         "densities per unit of the variable on the x axis",
}
#: the reduced coordinates of a basis are kept while |Psi|^2 (times the measure) is above this
#: fraction of its largest value at the nodes of the normalisation quadrature
SUPPORT = 1e-14


@cache
def _unit_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [0, 1]."""
    x, w = np.polynomial.legendre.leggauss(n)
    return (x + 1) / 2, w / 2


def _on(lo, hi, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes [..., n] and weights [..., n] of the n-point Gauss rule on [lo, hi] (arrays)."""
    s, w = _unit_rule(n)
    lo, hi = np.asarray(lo, float)[..., None], np.asarray(hi, float)[..., None]
    return lo + (hi - lo) * s, (hi - lo) * w


#: the Gauss-Kronrod (7, 15) pair on [-1, 1] (QUADPACK's qk15): the 8 nonnegative Kronrod
#: nodes, the odd-numbered of which are the Gauss nodes, and their Kronrod weights
_KRONROD_NODES = (0.991455371120812639206854697526329, 0.949107912342758524526189684047851,
                  0.864864423359769072789712788640926, 0.741531185599394439863864773280788,
                  0.586087235467691130294144838258730, 0.405845151377397166906606412076961,
                  0.207784955007898467600689403773245, 0.0)
_KRONROD_WEIGHTS = (0.022935322010529224963732008058970, 0.063092092629978553290700663189204,
                    0.104790010322250183839876322541518, 0.140653259715525918745189590510238,
                    0.169004726639267902826583426598550, 0.190350578064785409913256402421014,
                    0.204432940075298892414161999234649, 0.209482141084727828012999174891714)


def kronrod_panels(edges) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nodes [P, 15], Kronrod weights and Gauss weights (0 at the nodes the 7-point Gauss rule
    does not have) of the 15-point Gauss-Kronrod rule on each of the P intervals between
    ``edges``: the Kronrod sum is exact for polynomials of degree 22, the Gauss sum for degree
    13, and their difference estimates the error of the Gauss sum (so bounds the Kronrod one's
    where the integrand is resolved)."""
    half = np.asarray(_KRONROD_NODES)
    x = np.concatenate([-half, half[-2::-1]])
    wk = np.concatenate([_KRONROD_WEIGHTS, _KRONROD_WEIGHTS[-2::-1]])
    _, gauss_w = np.polynomial.legendre.leggauss(7)
    wg = np.zeros(15)
    wg[1::2] = gauss_w  # x[1::2] are the Gauss nodes gauss_x, in the same order
    edges = np.asarray(edges, float)
    lo, width = edges[:-1, None], np.diff(edges)[:, None]
    return lo + width * (x + 1) / 2, width * wk / 2, width * wg / 2


def _square(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tensor Gauss rule on [0, 1]^2: s [n*n], t [n*n], weights [n*n]."""
    s, w = _unit_rule(n)
    S, T = np.meshgrid(s, s, indexing="ij")
    return S.ravel(), T.ravel(), np.outer(w, w).ravel()


# ------------------------------------------------------------------- joint densities
@dataclass(frozen=True)
class Joint:
    """The joint density of the reduced variables of one eigenvector (measure included).

    ``model``: "lebesgue2" (coordinates (r1, r2)), "haar2" ((x, sigma)), "lebesgue3" (Q),
    "haar3" (q). ``box``: per coordinate [lo, hi] beyond which |Psi|^2 is negligible (the
    cut-off of the infinite integrals). ``nodes``/``weights``: a quadrature of the reduced
    domain (for the normalisation and the support of each invariant)."""

    model: str
    amplitude: object  # callable: coordinates [..., d] -> values [..., r] of the f_a
    box: np.ndarray  # [d, 2]
    nodes: np.ndarray  # [P, d]
    weights: np.ndarray  # [P]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        flat = x.reshape(-1, x.shape[-1])
        out = np.empty(len(flat))
        for i in range(0, len(flat), 16384):
            part = flat[i:i + 16384]
            amp2 = np.sum(np.asarray(self.amplitude(part)).reshape(len(part), -1) ** 2, -1)
            with np.errstate(over="ignore", invalid="ignore"):  # far out: 0 x (overflow)
                out[i:i + 16384] = np.where(amp2 > 0, amp2 * measure(self.model, part), 0.0)
        return out.reshape(x.shape[:-1])


def measure(model: str, x: np.ndarray) -> np.ndarray:
    """The reduced measure (docs/theory/two-polar.md): r1 r2; x (= g^2 sinh x); prod (Q_a^2 -
    Q_b^2); prod sinh(q_a - q_b) (each >= 0 on its chamber)."""
    if model == "lebesgue2":
        return x[..., 0] * x[..., 1]
    if model == "haar2":
        return x[..., 0]
    pairs = ((0, 1), (0, 2), (1, 2))
    if model == "lebesgue3":
        return np.prod([x[..., a] ** 2 - x[..., b] ** 2 for a, b in pairs], axis=0)
    return np.prod([np.sinh(x[..., a] - x[..., b]) for a, b in pairs], axis=0)


#: numbers per block of :func:`separable_values` (points x states x columns; at least 2048
#: points): the product of a block's basis values and the stacked coefficients stays in
#: cache (per state 2.4x faster than one product over 2^16 points of 24 x 24 coefficients,
#: measured on one core)
SEPARABLE_BLOCK = 2**17


def coefficient_extent(coefficients: np.ndarray) -> tuple[int, int]:
    """(rows, columns) of stacked coefficients C [S, I, J] that hold every one above round-off
    (float64 epsilon x its state's largest): the terms beyond them are below the rounding of
    the sum, and low states of a well-scaled basis occupy its first functions (the ground state
    of the n = 2 oscillator its first 3 of 24)."""
    C = np.abs(np.asarray(coefficients, float))
    above = C > np.finfo(float).eps * C.reshape(len(C), -1).max(-1)[:, None, None]
    if not above.any():
        return 1, 1
    return (int(np.flatnonzero(above.any((0, 2)))[-1]) + 1,
            int(np.flatnonzero(above.any((0, 1)))[-1]) + 1)


def separable_values(first: np.ndarray, second: np.ndarray, coefficients: np.ndarray
                     ) -> np.ndarray:
    """f_s(x_p) = sum_ij u_i(x_p) C_sij v_j(x_p) [P, S] from the values of the two factors,
    ``first`` u [P, >= I] and ``second`` v [P, >= J] (their first I and J functions used), and
    the stacked coefficients C [S, I, J] (cut to :func:`coefficient_extent` by the callers):
    one matrix product u (C_1 ... C_S) per block of points (:data:`SEPARABLE_BLOCK`)."""
    S, rows, cols = np.shape(coefficients)
    stacked = np.ascontiguousarray(
        np.asarray(coefficients, float).transpose(1, 0, 2).reshape(rows, -1))
    out = np.empty((len(first), S))
    block = max(2048, SEPARABLE_BLOCK // (S * cols))
    for lo in range(0, len(first), block):
        u, v = first[lo:lo + block, :rows], second[lo:lo + block, :cols]
        out[lo:lo + block] = np.einsum("psj,pj->ps", (u @ stacked).reshape(len(u), S, cols), v)
    return out


def _factor_values(evaluated: dict, factor, column: int, x: np.ndarray, count: int
                   ) -> np.ndarray:
    """The first ``count`` functions of a basis factor at column ``column`` of the points x
    [P, 2], from ``evaluated`` where it holds as many (the values shared between the
    amplitudes of a mixture at the same points)."""
    held = evaluated.get((factor, column))
    if held is None or held.shape[-1] < count:
        held = evaluated[factor, column] = factor.evaluate(x[:, column], count)
    return held


@dataclass(frozen=True, eq=False)
class _Separable:
    """f(x) = sum_ij C_ij u_i(x_0) v_j(x_1): an n = 2 eigenvector in its product basis (u, v
    the two factors, ``coefficients`` C). Called with a dict ``evaluated``, it shares the
    values of a factor at a column of x with every other amplitude called with the same dict
    and the same points (the states of a mixture at the points of one G density)."""

    first: object
    second: object
    coefficients: np.ndarray

    def __call__(self, x: np.ndarray, evaluated: dict | None = None) -> np.ndarray:
        evaluated = {} if evaluated is None else evaluated
        rows, cols = coefficient_extent(self.coefficients[None])
        return separable_values(_factor_values(evaluated, self.first, 0, x, rows),
                                _factor_values(evaluated, self.second, 1, x, cols),
                                self.coefficients[None, :rows, :cols])[:, 0]


def _separable_blocks(entries) -> list[tuple]:
    """[(first, second, weights w [S], coefficients C [S, I, J])] of ``entries`` [(w_s,
    :class:`_Separable` f_s)]: the states sharing both factors (one block of the solver)
    together, C cut to :func:`coefficient_extent`."""
    grouped: dict[tuple, list] = {}
    for weight, amplitude in entries:
        grouped.setdefault((amplitude.first, amplitude.second), []).append(
            (weight, amplitude.coefficients))
    blocks = []
    for (first, second), members in grouped.items():
        C = np.stack([c for _, c in members])
        rows, cols = coefficient_extent(C)
        blocks.append((first, second, np.array([w for w, _ in members]), C[:, :rows, :cols]))
    return blocks


def _squared_sum(blocks: list[tuple], x: np.ndarray, evaluated: dict) -> np.ndarray:
    """sum_s w_s f_s(x)^2 [P] at the points x [P, 2] over the :func:`_separable_blocks`: each
    block's states in one :func:`separable_values`, each factor evaluated once, as far as any
    state needs it (docs/theory/densities.md, "Evaluating many states at once")."""
    needed: dict[tuple, int] = {}
    for first, second, _, C in blocks:
        for key, count in zip(((first, 0), (second, 1)), C.shape[1:], strict=True):
            needed[key] = max(needed.get(key, 0), count)
    for (factor, column), count in needed.items():
        _factor_values(evaluated, factor, column, x, count)
    total = np.zeros(len(x))
    for first, second, weights, C in blocks:
        values = separable_values(evaluated[first, 0], evaluated[second, 1], C)
        total += (values * values) @ weights
    return total


def joint_density(spectrum: Spectrum, level: Level) -> Joint:
    """The :class:`Joint` of a level's eigenvector (the first of its sectors)."""
    block = spectrum.blocks[level.block]
    coeff = block.vectors[:, level.index]
    basis = block.basis
    if basis.kind == "lebesgue2":
        f1, f2 = basis.factors
        C = coeff.reshape(f1.size, f2.size)
        T = 4 * max(f1.size, f2.size) + 2 * (f1.m + f2.m) + 40  # |r|^2 / b^2 cut-off
        R = f1.scale * math.sqrt(T / 2)
        r, w = _on(0.0, R, 96)
        R1, R2 = np.meshgrid(r, r, indexing="ij")
        nodes = np.stack([R1.ravel(), R2.ravel()], -1)
        return Joint("lebesgue2", _Separable(f1, f2, C), np.array([[0.0, R], [0.0, R]]),
                     nodes, np.outer(w, w).ravel())
    if basis.kind == "haar2":
        fx, fs = basis.factors
        C = coeff.reshape(fx.size, fs.size)
        X = fx.scale * math.sqrt(4 * fx.size + 2 * fx.m + 80)
        S = fs.scale * math.sqrt(2 * fs.size + 80)
        x, wx = _on(0.0, X, 96)
        s, ws = _on(fs.centre - S, fs.centre + S, 96)
        XX, SS = np.meshgrid(x, s, indexing="ij")
        return Joint("haar2", _Separable(fx, fs, C),
                     np.array([[0.0, X], [fs.centre - S, fs.centre + S]]),
                     np.stack([XX.ravel(), SS.ravel()], -1), np.outer(wx, ws).ravel())
    if basis.kind == "scalar3":
        sb = basis.factors[0]
        return _joint3("lebesgue3", lambda Q: sb.evaluate(Q) @ coeff, sb.degree, sb.scale, 1.0,
                       0.0)
    if basis.kind == "grid3":
        return _grid3_joint(spectrum, basis, coeff)
    raise ValueError(f"densities: unknown basis kind {basis.kind!r}")


def _grid3_joint(spectrum: Spectrum, basis, coeff: np.ndarray) -> Joint:
    """n = 3 bases stored by their values on the solver's grid: n3.SectorBasis (a recipe over
    the candidates, re-evaluated at any points) or channels3.channel3_block (values only; the
    combination of its candidates is recovered by least squares on the grid and checked)."""
    kind, grid, values, _parity, spin1 = basis.factors
    x = grid.nodes
    if callable(values):  # n3.SectorBasis.values: a recipe
        sb = values.__self__

        def amplitude(p):
            if hasattr(sb, "combination"):  # n3.HarmonicBasis: radial sums per harmonic first
                return sb.combination(coeff, p)
            return np.einsum("prk,k->pr", replace(sb, nodes=p).values(), coeff)
        degree, scale, scale_sigma, centre = sb.candidate_args
    else:
        from affinebody.quantum.channels3 import channel_candidates

        settings = spectrum.settings
        degree, scale = settings["basis_size"], settings["scale"]
        scale_sigma, centre = settings.get("scale_sigma", 1.0), settings.get("centre", 0.0)
        cand = channel_candidates(kind, x, degree, scale, scale_sigma, centre, spin1)[0]
        P, d, K = cand.shape
        sw = np.sqrt(grid.weights)[:, None, None]
        target = (values @ coeff)[:, :, None]
        mix = linalg.lstsq((sw * cand).reshape(P * d, K), (sw * target).reshape(P * d, 1))[0]
        error = np.max(np.abs(np.einsum("pdk,k->pd", cand, mix[:, 0]) - target[..., 0]))
        if error > 1e-9 * np.max(np.abs(target)):
            raise ValueError(f"densities: the n = 3 channel basis could not be re-evaluated "
                             f"off its grid (residual {error:.1e})")

        def amplitude(p):
            c = channel_candidates(kind, p, degree, scale, scale_sigma, centre, spin1)[0]
            return np.einsum("pdk,k->pd", c, mix[:, 0])
    return _joint3(kind, amplitude, degree, scale, scale_sigma, centre)


def _joint3(model: str, amplitude, degree: int, scale: float, scale_sigma: float,
            centre: float) -> Joint:
    """n = 3: the box and a quadrature of the chamber of our own, wider than the solver's
    (Gauss-Hermite in sigma reaching +-8 scale_sigma; Q up to scale sqrt(3 degree + 40))."""
    from affinebody.quantum.channels3 import ChamberQuadrature, haar3_grid

    if model == "lebesgue3":
        quad = ChamberQuadrature.build(scale * math.sqrt(3 * degree + 40), 96, 40)
        x, w = quad.nodes, quad.weights / measure(model, quad.nodes)
    else:
        grid = haar3_grid(scale, scale_sigma, centre, 48, 20, 48)
        x, w = grid.nodes, grid.weights / measure(model, grid.nodes)
    amplitude = _polynomial_form(model, amplitude, x, w, degree, scale, scale_sigma, centre)
    mass = w * Joint(model, amplitude, np.zeros((3, 2)), x, w)(x)
    inside = x[mass > 1e-20 * np.max(mass)]  # the nodes where rho is not negligible
    if model == "lebesgue3":
        Qmax = float(np.max(np.linalg.norm(inside, axis=-1)))
        box = np.array([[0.0, Qmax], [0.0, Qmax], [-Qmax, Qmax]])
    else:  # the q-cube holding them
        box = np.tile([np.min(inside), np.max(inside)], (3, 1))
    return Joint(model, amplitude, box, x, w)


def _front3(model: str, x: np.ndarray, scale: float, scale_sigma: float, centre: float
            ) -> np.ndarray:
    """The non-polynomial factor shared by every n = 3 basis function (channels3, n3):
    e^{-|Q|^2/2b^2} (d'Alembert); prod sqrt((q_a - q_b)/sinh(q_a - q_b)) e^{-(|y|^2 + t^2)/2}
    with y = (q - mean q)/b, t = (sum q - centre)/b_sigma (affine)."""
    if model == "lebesgue3":
        return np.exp(-0.5 * np.sum(x * x, -1) / scale**2)
    y = (x - x.mean(-1, keepdims=True)) / scale
    t = (x.sum(-1) - centre) / scale_sigma
    g = np.prod([sqrt_x_over_sinh(x[:, a] - x[:, b]) for a, b in ((0, 1), (0, 2), (1, 2))], 0)
    return g * np.exp(-0.5 * (np.sum(y * y, -1) + t * t))


def _polynomial_form(model: str, amplitude, x: np.ndarray, w: np.ndarray, degree: int,
                     scale: float, scale_sigma: float, centre: float):
    """The n = 3 amplitude as front(x) x (polynomials of total degree <= ``degree`` in
    z = (x - centre/3)/b): every basis function of channels3 and n3 has that form, so it is
    exact, and it is far cheaper to evaluate than the candidates (which carry gradients). The
    coefficients in products of Hermite polynomials H_i(z_1) H_j(z_2) H_k(z_3) are fitted by
    least squares at the quadrature nodes and checked against ``amplitude`` at points off the
    nodes; if the check fails (relative 1e-10), ``amplitude`` itself is returned."""
    from numpy.polynomial.hermite import hermvander

    shift = 0.0 if model == "lebesgue3" else centre / 3
    exps = np.array([(i, j, k) for i in range(degree + 1) for j in range(degree + 1 - i)
                     for k in range(degree + 1 - i - j)])

    def design(p):
        z = (p - shift) / scale
        H = [hermvander(z[:, a], degree) for a in range(3)]
        front = _front3(model, p, scale, scale_sigma, centre)
        return front[:, None] * H[0][:, exps[:, 0]] * H[1][:, exps[:, 1]] * H[2][:, exps[:, 2]]

    rng = np.random.default_rng(0)
    fit = x[:: max(1, len(x) // 20000)]
    sw = np.sqrt(w[:: max(1, len(x) // 20000)])[:, None]
    values = np.asarray(amplitude(fit)).reshape(len(fit), -1)
    coeff = linalg.lstsq(sw * design(fit), sw * values)[0]
    test = x[rng.choice(len(x), 1000, replace=False)] + 0.05 * scale * rng.normal(size=(1000, 3))
    direct = np.asarray(amplitude(test)).reshape(len(test), -1)
    if np.max(np.abs(design(test) @ coeff - direct)) > 1e-10 * np.max(np.abs(values)):
        return amplitude
    return lambda p: design(p) @ coeff


# ------------------------------------------------------------------------- marginals
def _marginals2(joint: Joint) -> dict:
    """name -> (function of the output variable, p(y, N) with N nodes): n = 2."""
    J = joint
    if J.model == "lebesgue2":
        R = J.box[0, 1]

        def q1(y, n):  # Q2 = u in [-y, y]; r = ((y + u)/2, (y - u)/2); dQ1 dQ2 = 2 dr1 dr2
            u, w = _on(-y, y, n)
            return 0.5 * np.sum(w * J(np.stack([(y[:, None] + u) / 2, (y[:, None] - u) / 2],
                                                -1)), -1)

        def q2(y, n):  # Q1 = u in [|y|, 2R]
            u, w = _on(np.abs(y), 2 * R, n)
            return 0.5 * np.sum(w * J(np.stack([(u + y[:, None]) / 2, (u - y[:, None]) / 2],
                                                -1)), -1)

        def det(y, n):  # v = r1^2 + r2^2 in [|y|, 2R^2]: p = (1/8) int f^2 dv (8 r1 r2 cancels)
            v, w = _on(np.abs(y), 2 * R * R, n)
            r = np.sqrt(np.maximum(np.stack([(v + y[:, None]) / 2, (v - y[:, None]) / 2], -1),
                                   0.0))
            return np.sum(w * np.asarray(J.amplitude(r.reshape(-1, 2))).reshape(v.shape) ** 2,
                          -1) / 8

        def trg(y, n):  # r = rho (cos t, sin t), rho^2 = y/2: p = (1/4) int rho dt
            t, w = _on(np.zeros_like(y), np.full_like(y, np.pi / 2), n)
            rho = np.sqrt(np.maximum(y, 0) / 2)[:, None]
            return 0.25 * np.sum(w * J(np.stack([rho * np.cos(t), rho * np.sin(t)], -1)), -1)

        return {"Q1": (lambda r: r[:, 0] + r[:, 1], q1), "Q2": (lambda r: r[:, 0] - r[:, 1], q2),
                "det": (lambda r: r[:, 0] ** 2 - r[:, 1] ** 2, det),
                "trG": (lambda r: 2 * (r[:, 0] ** 2 + r[:, 1] ** 2), trg)}
    X = J.box[0, 1]

    def along(y, n, sigma_of, factor):  # int_0^X P(x, sigma(y, x)) dx * factor(y)
        x, w = _on(np.zeros_like(y), np.full_like(y, X), n)
        return factor(y) * np.sum(w * J(np.stack([x, sigma_of(y[:, None], x)], -1)), -1)

    return {
        # q1 = (sigma + x)/2: sigma = 2 q1 - x, d sigma = 2 d q1
        "q1": (lambda p: (p[:, 1] + p[:, 0]) / 2,
               lambda y, n: along(y, n, lambda y, x: 2 * y - x, lambda y: 2.0)),
        "q2": (lambda p: (p[:, 1] - p[:, 0]) / 2,
               lambda y, n: along(y, n, lambda y, x: 2 * y + x, lambda y: 2.0)),
        # det = e^sigma: p_det(y) = p_sigma(ln y) / y
        "det": (lambda p: np.exp(p[:, 1]),
                lambda y, n: along(y, n, lambda y, x: np.log(y) + 0 * x, lambda y: 1 / y)),
        # Tr G = 2 e^sigma cosh x: sigma = ln(y / (2 cosh x)), d sigma = dy / y
        "trG": (lambda p: 2 * np.exp(p[:, 1]) * np.cosh(p[:, 0]),
                lambda y, n: along(y, n, lambda y, x: np.log(y / (2 * np.cosh(x))),
                                   lambda y: 1 / y)),
    }


def _marginals3(joint: Joint) -> dict:
    """name -> (function of the output variable, p(y, N)): n = 3, double integrals over
    [0, 1]^2 with an N x N Gauss rule."""
    J = joint

    def integrate(y, n, mapping):
        s, t, w = _square(n)
        pts, jac = mapping(y[:, None], s[None, :], t[None, :])
        return np.sum(w * jac * J(pts), -1)

    if J.model == "lebesgue3":
        Qmax = J.box[0, 1]

        def q1(Y, s, t):  # Q2 = y s, Q3 = y s (2t - 1): triangle y > Q2 > |Q3|
            Q2 = Y * s
            return _stack(Y + 0 * s, Q2, Q2 * (2 * t - 1)), 2 * Y * Y * s

        def q2(Y, s, t):  # Q1 in [y, Qmax], Q3 in [-y, y]
            return _stack(Y + (Qmax - Y) * s, Y + 0 * s, Y * (2 * t - 1)), 2 * Y * (Qmax - Y)

        def q3(Y, s, t):  # Q2 in [|y|, Qmax], Q1 in [Q2, Qmax]
            a = np.abs(Y)
            Q2 = a + (Qmax - a) * s
            return _stack(Q2 + (Qmax - Q2) * t, Q2, Y + 0 * s), (Qmax - a) * (Qmax - Q2)

        def det(Y, s, t):
            # y != 0: Q1 = e^v, Q2 = e^u, Q3 = y e^{-u-v}, dQ1 dQ2 / |Q1 Q2| = du dv on
            # ln|y|/3 < v < ln Qmax, (ln|y| - v)/2 < u < v (Q2 > |Q3|, Q1 > Q2);
            # y = 0: Q3 = 0, Q2 = Q1 t, Q1 = Qmax s, Jacobian 1/(Q1 Q2) * Q1 Qmax
            a = np.abs(Y)
            zero = a == 0
            la = np.log(np.where(zero, 1.0, a))
            v = la / 3 + (math.log(Qmax) - la / 3) * s
            u = (la - v) / 2 + (v - (la - v) / 2) * t
            jac = (math.log(Qmax) - la / 3) * (1.5 * v - la / 2)
            Q1, Q2 = np.exp(v), np.exp(u)
            Q3 = Y * np.exp(-u - v)
            Q1z = Qmax * s
            Q2z = Q1z * t
            with np.errstate(divide="ignore", invalid="ignore"):
                jz = np.where(t > 0, Qmax / np.where(t > 0, Q2z, 1.0), 0.0)
            return (_stack(np.where(zero, Q1z, Q1), np.where(zero, Q2z, Q2),
                           np.where(zero, 0.0, Q3)), np.where(zero, jz, jac))

        def trg(Y, s, t):
            # sphere |Q|^2 = y through the chamber: Q = rho Z/|Z|, Z on the flat triangle
            # e1, (1,1,1), (1,1,-1) (area coordinates a = s, b = (1 - s) t), d omega =
            # 2 da db / |Z|^3; p = (rho / 2) int p(rho omega) d omega
            Z, dom = projected_triangle(s, t, np.array([[1.0, 0, 0], [1, 1, 1], [1, 1, -1]]),
                                        2.0)
            rho = np.sqrt(np.maximum(Y, 0.0))
            return rho[..., None] * Z, rho / 2 * dom

        rules = {"Q1": (lambda Q: Q[:, 0], q1), "Q2": (lambda Q: Q[:, 1], q2),
                 "Q3": (lambda Q: Q[:, 2], q3), "det": (lambda Q: np.prod(Q, -1), det),
                 "trG": (lambda Q: np.sum(Q * Q, -1), trg)}
    else:
        lo, hi = J.box[0]

        def q1(Y, s, t):  # q2 in [lo, y], q3 in [lo, q2]
            q2 = lo + (Y - lo) * s
            return _stack(Y + 0 * s, q2, lo + (q2 - lo) * t), (Y - lo) * (q2 - lo)

        def q2(Y, s, t):  # q1 in [y, hi], q3 in [lo, y]
            return _stack(Y + (hi - Y) * s, Y + 0 * s, lo + (Y - lo) * t), (hi - Y) * (Y - lo)

        def q3(Y, s, t):  # q2 in [y, hi], q1 in [q2, hi]
            q2 = Y + (hi - Y) * s
            return _stack(q2 + (hi - q2) * t, q2, Y + 0 * s), (hi - Y) * (hi - q2)

        R = (hi - lo) * math.sqrt(2 / 3)  # the traceless radius that leaves the box
        eu = np.array([1.0, -1.0, 0.0]) / math.sqrt(2)
        ev = np.array([1.0, 1.0, -2.0]) / math.sqrt(6)

        def det(Y, s, t):
            # det = e^sigma; q = (sigma/3)(1,1,1) + r (cos th e_u + sin th e_v), th in
            # (pi/6, pi/2), dq = r dr dth dsigma / sqrt3: p_det(y) = p_sigma(ln y) / y
            r, th = R * s, np.pi / 6 + (np.pi / 3) * t
            sig = np.log(Y)
            q = (sig[..., None] / 3 + r[..., None] * (np.cos(th)[..., None] * eu
                                                      + np.sin(th)[..., None] * ev))
            return q, (R * np.pi / 3) * r / (math.sqrt(3) * Y) + 0 * s

        def trg(Y, s, t):
            # Q = e^q on Q1 > Q2 > Q3 > 0: Q = rho Z/|Z| on the flat triangle e1, (1,1,0),
            # (1,1,1) (d omega = da db / |Z|^3), dq = dQ / (Q1 Q2 Q3), |Q|^2 = y
            Z, dom = projected_triangle(s, t, np.array([[1.0, 0, 0], [1, 1, 0], [1, 1, 1]]), 1.0)
            rho = np.sqrt(Y)
            Q = rho[..., None] * Z
            with np.errstate(divide="ignore"):
                q = np.log(np.maximum(Q, 1e-300))
            return q, rho / 2 * dom / np.prod(Q, -1)

        rules = {"q1": (lambda q: q[:, 0], q1), "q2": (lambda q: q[:, 1], q2),
                 "q3": (lambda q: q[:, 2], q3), "det": (lambda q: np.exp(np.sum(q, -1)), det),
                 "trG": (lambda q: np.sum(np.exp(2 * q), -1), trg)}
    return {name: (f, (lambda y, n, m=m: integrate(y, n, m))) for name, (f, m) in rules.items()}


def _stack(a, b, c):
    a, b, c = np.broadcast_arrays(a, b, c)
    return np.stack([a, b, c], -1)


def projected_triangle(s, t, vertices: np.ndarray, volume: float):
    """Unit vectors over the central projection of the flat triangle ``vertices`` (Duffy map:
    area coordinates a = s, b = (1 - s) t) and the solid-angle Jacobian volume (1 - s) / |Z|^3
    (``volume`` = |det vertices|)."""
    a, b = s, (1 - s) * t
    Z = (a[..., None] * vertices[0] + b[..., None] * vertices[1]
         + (1 - a - b)[..., None] * vertices[2])
    norm = np.linalg.norm(Z, axis=-1)
    return Z / norm[..., None], volume * (1 - s) / norm**3


# ---------------------------------------------------------------------------- driver
@dataclass(frozen=True)
class Marginal:
    """One density: output points ``x``, values ``density``, the quadrature error estimate
    (max over x of |p_N - p_{2N/3}|), its integral over x, the node count N used and whether
    the error is within the tolerance (relative to the peak)."""

    x: np.ndarray
    density: np.ndarray
    error: float
    integral: float
    nodes: int
    converged: bool
    #: the integral's own error estimate, where it has one (the components of G)
    integral_error: float | None = None

    def as_dict(self) -> dict:
        out = {"x": self.x.tolist(), "density": self.density.tolist(), "error": self.error,
               "integral": self.integral, "nodes": self.nodes, "converged": self.converged}
        if self.integral_error is not None:
            out["integral_error"] = self.integral_error
        return out


def _converged(fn, y: np.ndarray, sizes: tuple[int, ...], tolerance: float):
    """p with N in ``sizes`` (each 3/2 of the one before, so the nested rule of 2N/3 nodes is the
    previous N and is not evaluated again) until |p_N - p_{2N/3}| <= tolerance x peak."""
    coarse = fn(y, (2 * sizes[0]) // 3)
    for n in sizes:
        p = fn(y, n)
        err, peak = float(np.max(np.abs(p - coarse))), float(np.max(np.abs(p)))
        if err <= tolerance * peak:
            break
        coarse = p
    return p, err, n, err <= tolerance * peak


def _support(values: np.ndarray, mass: np.ndarray) -> tuple[float, float]:
    keep = mass > SUPPORT * np.max(mass)
    return float(np.min(values[keep])), float(np.max(values[keep]))


def _grid(lo: float, hi: float, points: int, geometric: bool = False) -> np.ndarray:
    """Output points: an odd symmetric grid through 0 when [lo, hi] contains 0 inside (0 is
    where det and Q_n have their cusp), else uniform on [lo, hi] (``geometric``: uniform in
    ln y, for det and Tr G of the affine models, which spread over decades)."""
    if geometric and lo > 0:
        return np.geomspace(lo, hi, points)
    if lo < 0 < hi:
        x = max(-lo, hi) * np.linspace(-1.0, 1.0, points + (1 - points % 2))
        return (x - x[::-1]) / 2  # exactly antisymmetric, exactly 0 in the middle
    return np.linspace(lo, hi, points)


def _integral(fn, lo: float, hi: float, n: int) -> float:
    """int_lo^hi p by 16-node Gauss-Legendre panels: graded geometrically towards 0 on each side
    of 0 when 0 is an end point or inside (where det and Q_n have their cusp and Tr G, Q_a a
    power-law end point), geometric in y when 0 < lo (det, Tr G of the affine models)."""
    total = 0.0
    for a, b in ([(lo, 0.0), (0.0, hi)] if lo < 0 < hi else [(lo, hi)]):
        if a == 0.0 or b == 0.0:
            end = b if a == 0.0 else a
            edges = np.sort(end * np.concatenate([[0.0], 2.0 ** -np.arange(9, -1, -1)]))
        elif a > 0:
            edges = np.geomspace(a, b, 9)
        else:
            edges = np.linspace(a, b, 9)
        y, w = _on(edges[:-1], edges[1:], 16)
        total += float(np.sum(w.ravel() * fn(y.ravel(), n)))
    return total


def _trimmed(fn, lo: float, hi: float, n: int, geometric: bool) -> tuple[float, float]:
    """[lo, hi] shrunk to where a coarse evaluation of p (y p for a geometric grid) exceeds
    1e-12 of its peak (the output points cover the density, not the far tails of the
    support)."""
    y = _grid(lo, hi, 61, geometric)
    p = fn(y, n) * (y if geometric else 1.0)
    keep = np.flatnonzero(p > 1e-12 * np.max(p))
    a, b = y[max(keep[0] - 1, 0)], y[min(keep[-1] + 1, len(y) - 1)]
    if lo < 0 < hi and a < 0 < b:
        a, b = -max(-a, b), max(-a, b)
    return float(a), float(b)


def _rules(joint: Joint) -> dict:
    """name -> (the invariant as a function of the reduced coordinates, p(y, N), floor): p is
    0 below the range of a nonnegative invariant; ``floor`` = 0 where the output grid starts
    at that end point (d'Alembert Q1, Tr G, and Q2 for n = 3), None elsewhere (the affine det
    and Tr G > 0 start at their support)."""
    rules = _marginals2(joint) if joint.model.endswith("2") else _marginals3(joint)
    if joint.model.startswith("lebesgue"):
        positive = ("Q1", "trG") + (("Q2",) if joint.model == "lebesgue3" else ())
        strict = False
    else:
        positive, strict = ("det", "trG"), True

    def restricted(fn):
        def p(y, n):
            inside = y > 0 if strict else y >= 0
            out = np.zeros(len(y))
            if np.any(inside):
                out[inside] = fn(y[inside], n)
            return out
        return p
    return {name: (f, restricted(fn), None if strict else 0.0) if name in positive
            else (f, fn, None) for name, (f, fn) in rules.items()}


def density_at(joint: Joint, name: str, y, nodes: int) -> np.ndarray:
    """The marginal density of ``name`` (as in :func:`densities`) at the points ``y`` (inside
    the support box of ``joint``) with an ``nodes``-point Gauss rule per integrated variable."""
    return _rules(joint)[name][1](np.atleast_1d(np.asarray(y, float)), nodes)


def densities(spectrum: Spectrum, state: int, points: int | None = None,
              tolerance: float = DEFAULT_TOLERANCE) -> dict:
    """Exact marginal densities for the ``state``-th entry of ``energies()`` (module docstring).

    Returns a dict: ``energy``, ``sector``, ``variables`` ("Q" for d'Alembert, "q" for the
    affine models), ``normalisation`` (int rho over the reduced domain), ``marginals``
    (name -> (x, density)), ``details`` (name -> :class:`Marginal`), ``orientation``,
    ``warnings`` (densities whose error exceeds ``tolerance`` x their peak)."""
    level, sector = spectrum.state_eigenvector(state)
    return {**marginal_densities(spectrum, level, points, tolerance), "sector": sector.as_dict()}


def marginal_densities(spectrum: Spectrum, level: Level, points: int | None = None,
                       tolerance: float = DEFAULT_TOLERANCE) -> dict:
    """:func:`densities` for one :class:`Level` (any block and index of ``spectrum``)."""
    n = spectrum.n
    points = points or POINTS[n]
    joint = joint_density(spectrum, level)
    mass = joint.weights * joint(joint.nodes)
    details, warnings = {}, []
    for name, (f, fn, floor) in _rules(joint).items():
        lo, hi = _support(f(joint.nodes), mass)
        lo = lo if floor is None else floor  # resolved down to its end point
        geometric = name in ("det", "trG") and joint.model.startswith("haar")
        y = _grid(*_trimmed(fn, lo, hi, NODES[n][0], geometric), points, geometric)
        p, err, nodes, ok = _converged(fn, y, NODES[n], tolerance)
        ok = bool(ok and np.all(np.isfinite(p)))
        details[name] = Marginal(y, p, err, _integral(fn, lo, hi, nodes), nodes, ok)
        if not ok:
            warnings.append(_density_warning(name, details[name], tolerance))
    return {"energy": level.energy, "sector": level.sectors[0].as_dict(),
            "variables": "Q" if joint.model.startswith("lebesgue") else "q",
            "normalisation": float(np.sum(mass)), "level_error": level.error,
            "marginals": {k: (m.x, m.density) for k, m in details.items()},
            "details": details, "orientation": orientation(n), "warnings": warnings}


def orientation(n: int) -> dict[str, np.ndarray]:
    """Exact orientation densities (module docstring): n = 2 uniform 1/(2 pi) in the angles of L
    and R on [0, 2 pi]; n = 3 the Haar density (1 - cos omega)/pi of the rotation angle."""
    if n == 2:
        ang = np.linspace(0, 2 * np.pi, 361)
        dens = np.full_like(ang, 1 / (2 * np.pi))
    else:
        ang = np.linspace(0, np.pi, 361)
        dens = (1 - np.cos(ang)) / np.pi
    return {"angle": ang, "L_angle": dens, "R_angle": dens.copy()}


# ------------------------------------------------------- orientations and components of G
#: (nodes in the angle beta of R, nodes in the shape coordinate) of the G densities: graded
#: Gauss rules (:func:`_graded`), each checked against the one before; a finer rule is
#: computed only where the change to the one before is above the tolerance. The change
#: estimates the error of the coarser of the two (the rules converge faster than
#: geometrically: the af-is ground state's G12 at the smallest |y| changes by 4.8e-4, 1.6e-6,
#: 1.9e-10 of its peak from rule to rule), so the fifth rule lets a density whose fourth is
#: accurate be shown to be (docs/theory/densities.md, "Components of G (n = 2)")
ORIENTATION_NODES = ((96, 72), (144, 108), (216, 162), (324, 243), (486, 364))
#: default tolerance of the G densities (x their peak): their integrand concentrates at the
#: edges of the rule as y -> 0, so they converge more slowly than the invariants' densities
G_TOLERANCE = 1e-6
#: the components of G = phi^T phi = R D^2 R^T reported (n = 2)
G_COMPONENTS = ("G11", "G22", "G12")


@dataclass(frozen=True)
class PureState:
    """A normalised superposition sum_i c_i psi_i of sector states (n = 2).

    Each psi_i = e^{i(s alpha - k beta)} f(reduced) / (2 pi) with L = rot(alpha), R = rot(beta)
    the factors of phi = L D R^T (D = diag(Q1, Q2), Q1 >= |Q2|): the character of its sector
    (spin s, vorticity k: phi -> phi R(t)^T has eigenvalue -hbar k, n2.n2_sectors) times the
    real reduced eigenfunction f of its block. ``amplitudes`` [m] complex; ``joints`` the
    :class:`Joint` of each f; ``spins``, ``vorticities`` [m]."""

    amplitudes: np.ndarray
    joints: tuple
    spins: np.ndarray
    vorticities: np.ndarray


def state_components(spectrum: Spectrum, state: int) -> list[tuple[Level, object]]:
    """The (level, sector) of every state of :meth:`Spectrum.energies` up to ``state``, in that
    order (a degenerate level contributes one entry per state of each of its sectors)."""
    out = []
    for level in spectrum.states():
        for sector in level.sectors:
            for _ in range(sector.dimension):
                out.append((level, sector))
                if len(out) > state:
                    return out
    raise ValueError(f"densities: state {state} is beyond the {len(out)} states computed")


def pure_state(spectrum: Spectrum, amplitudes: dict[int, complex]) -> PureState:
    """The normalised superposition sum_k c_k |state k> (keys: indices into
    :meth:`Spectrum.energies`, each a sector state, n = 2). ValueError for n = 3 or an
    unconverged state."""
    if spectrum.n != 2:
        raise ValueError("orientation densities of single states and superpositions are "
                         "implemented for n = 2 (n = 3: multiplets and thermal mixtures are "
                         "Haar-distributed)")
    if not amplitudes:
        raise ValueError("a superposition needs at least one state")
    if min(amplitudes) < 0:
        raise ValueError(f"state indices must be >= 0 (got {min(amplitudes)})")
    c = np.asarray([complex(v) for v in amplitudes.values()])
    if not np.sum(np.abs(c) ** 2) > 0:
        raise ValueError("a superposition needs a nonzero amplitude")
    chosen = [spectrum.state_eigenvector(k) for k in amplitudes]
    return PureState(c / np.sqrt(np.sum(np.abs(c) ** 2)),
                     tuple(joint_density(spectrum, lv) for lv, _ in chosen),
                     np.asarray([sec.spin for _, sec in chosen]),
                     np.asarray([sec.vorticity for _, sec in chosen]))


#: the most states ``affinebody density --temperature`` asks for: it asks for at least twice
#: quantum.levels and more states than it has (levels come whole), up to this, until the last
#: state of the thermal mixture has a Boltzmann factor below the densities' tolerance
#: (:func:`boltzmann_factors`; quantum.cli.solve_thermal)
MAX_THERMAL_STATES = 256


def require_temperature(temperature: float) -> None:
    """ValueError unless 0 < T < inf (k_B = 1)."""
    if not 0 < temperature < math.inf:
        raise ValueError(f"the temperature must be finite and > 0 (got {temperature})")


def boltzmann_factors(energies, temperature: float) -> np.ndarray:
    """exp(-(E - E_min) / T) of states of energies E (k_B = 1, not normalised): the last one's
    is the order of the weight of each state above it that a mixture of these leaves out."""
    require_temperature(temperature)
    energies = np.asarray(energies, float)
    return np.exp(-(energies - energies.min()) / temperature)


def truncation_warning(count: int, tail: float) -> str:
    """The warning of a thermal mixture of ``count`` states that leaves out a state of
    Boltzmann factor ``tail`` relative to the first, above the tolerance."""
    return (f"thermal mixture truncated at the {count} states computed: a state left out "
            f"(above them, or unconverged among them) has up to {tail:.1e} of the Boltzmann "
            f"weight of the first (raise quantum.levels, or quantum.basis_size; --temperature "
            f"asks for up to {MAX_THERMAL_STATES} states, in whole levels)")


def thermal_states(spectrum: Spectrum, temperature: float) -> tuple[list, np.ndarray, float]:
    """The thermal mixture exp(-E / T) / Z over the converged states computed (k_B = 1):
    (pure states, probabilities, the largest Boltzmann factor, relative to the lowest state,
    of a state left out: an unconverged one, or the last computed, whose factor is the order
    of that of each state above it).

    A sector state's angular part is a character, uniform in both angles, so its densities
    depend on its reduced eigenfunction alone: the states of conjugate sectors that share one
    (one block, one index) are one entry, with their probabilities summed."""
    count = len(spectrum.energies())
    table = state_components(spectrum, count - 1)
    factors = boltzmann_factors([level.energy for level, _ in table], temperature)
    kept = [k for k, (level, _) in enumerate(table) if level.converged]
    tail = max([factors[-1]] + [f for (level, _), f in zip(table, factors, strict=True)
                                if not level.converged])
    total = factors[kept].sum()
    merged: dict[tuple, list] = {}
    for k in kept:
        level, _ = spectrum.state_eigenvector(k)
        merged.setdefault((level.block, level.index), [k, 0.0])[1] += factors[k] / total
    states = [pure_state(spectrum, {k: 1.0}) for k, _ in merged.values()]
    return states, np.array([w for _, w in merged.values()]), float(tail)


def _union_box(joints) -> np.ndarray:
    boxes = np.stack([j.box for j in joints])
    return np.stack([boxes[:, :, 0].min(0), boxes[:, :, 1].max(0)], axis=-1)


def _cross_terms(pure: PureState, x: np.ndarray, evaluated: dict | None = None) -> list:
    """(c_i^* c_j, s_j - s_i, k_j - k_i, f_i f_j measure at x [..., 2]) per ordered pair
    (``evaluated``: basis values shared between calls at the same x, :class:`_Separable`)."""
    model = pure.joints[0].model
    flat = x.reshape(-1, x.shape[-1])
    amps = [np.asarray(j.amplitude(flat, evaluated)).reshape(x.shape[:-1])
            for j in pure.joints]
    mu = measure(model, x)
    out = []
    for i, ci in enumerate(pure.amplitudes):
        for j, cj in enumerate(pure.amplitudes):
            out.append((np.conj(ci) * cj, int(pure.spins[j] - pure.spins[i]),
                        int(pure.vorticities[j] - pure.vorticities[i]), amps[i] * amps[j] * mu))
    return out


def angle_densities(pure: PureState, angle, nodes: int = 160) -> dict[str, np.ndarray]:
    """Exact densities of alpha (the angle of L: principal axes of the Cauchy tensor C) and of
    beta (the angle of R: principal axes of G) on [0, 2 pi):

        p_L(alpha) = (1/2pi) sum_{i, j: k_i = k_j} c_i^* c_j e^{i (s_j - s_i) alpha} O_ij,
        p_R(beta)  = (1/2pi) sum_{i, j: s_i = s_j} c_i^* c_j e^{-i (k_j - k_i) beta} O_ij,

    O_ij = int f_i f_j (measure) over the reduced domain (Gauss rule on the union of the
    supports, ``nodes`` per coordinate): a finite Fourier series, uniform 1/(2 pi) for a
    sector state and for any mixture of sector states."""
    box = _union_box(pure.joints)
    a, wa = _on(box[0, 0], box[0, 1], nodes)
    b, wb = _on(box[1, 0], box[1, 1], nodes)
    grid = np.stack(np.meshgrid(a, b, indexing="ij"), -1)
    weights = np.outer(wa, wb)
    angle = np.asarray(angle, float)
    p_l = np.zeros(angle.shape, dtype=complex)
    p_r = np.zeros(angle.shape, dtype=complex)
    for coef, ds, dk, values in _cross_terms(pure, grid):
        overlap = coef * np.sum(values * weights)
        if dk == 0:
            p_l += overlap * np.exp(1j * ds * angle)
        if ds == 0:
            p_r += overlap * np.exp(-1j * dk * angle)
    return {"L_angle": p_l.real / (2 * np.pi), "R_angle": p_r.real / (2 * np.pi)}


def _graded(edges, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre on each interval between ``edges`` (n nodes in all), mapped by the
    quintic t^3 (10 - 15 t + 6 t^2), whose first two derivatives vanish at both ends: the nodes
    crowd towards the edges, where the G densities concentrate as y -> 0."""
    s, w = _unit_rule(max(2, n // (len(edges) - 1)))
    h = s**3 * (10 - 15 * s + 6 * s**2)
    dh = 30 * s**2 * (1 - s) ** 2
    nodes, weights = [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        nodes.append(a + (b - a) * h)
        weights.append((b - a) * dh * w)
    return np.concatenate(nodes), np.concatenate(weights)


#: points (values x rule nodes) evaluated at once by :func:`_g_density`: the basis values of
#: every factor of a mixture at them are held together (2^16 x 8 bytes x the basis size each)
G_CHUNK = 2**16


def _g_density(mixture, name: str, y: np.ndarray, nb: int, nr: int) -> np.ndarray:
    """Density of the component ``name`` of G at the values y for a mixture [(probability,
    PureState)], the states evaluated together at the same points (the basis values of a
    factor shared between them, :class:`_Separable`; the states of one sector each summed
    per block, :func:`_squared_sum`). G is homogeneous of degree 2 in
    Q, so the delta of G - y fixes the scale exactly and leaves a smooth integral over the
    angle beta of R (trapezoid rule, periodic) and one shape coordinate (Gauss):

    * haar2 (x = q1 - q2, sigma = q1 + q2): A = (Q1^2 + Q2^2)/2 = e^sigma cosh x,
      B = (Q1^2 - Q2^2)/2 = e^sigma sinh x; G11 = A + B cos 2beta, G22 = A - B cos 2beta,
      G12 = B sin 2beta, i.e. G = e^sigma g(x, beta): sigma = ln(y / g), dG/dsigma = y;
    * lebesgue2 (r1 = rho cos theta, r2 = rho sin theta; Q1 = r1 + r2, Q2 = r1 - r2):
      A = rho^2, B = rho^2 sin 2theta, G = rho^2 g(theta, beta): rho^2 = y / g, and
      rho d rho d theta with dG/drho = 2 y / rho gives the factor rho^2 / (2 y)."""
    model = mixture[0][1].joints[0].model
    beta, wbeta = _graded(np.pi / 2 * np.arange(5), nb)
    box = _union_box([joint for _, pure in mixture for joint in pure.joints])
    if model == "haar2":
        t, wt = _graded(np.array([0.0, box[0, 1]]), nr)
        even, odd = np.cosh(t)[:, None], np.sinh(t)[:, None]
    else:
        t, wt = _graded(np.pi / 4 * np.arange(3), nr)
        even, odd = np.ones_like(t)[:, None], np.sin(2 * t)[:, None]
    c2, s2 = np.cos(2 * beta)[None, :], np.sin(2 * beta)[None, :]
    g = {"G11": even + odd * c2, "G22": even - odd * c2, "G12": 0.0 * even + odd * s2}[name]
    y = np.asarray(y, float)
    out = np.zeros(len(y))
    phase = {}
    squares, others = [], []
    for probability, pure in mixture:
        amplitude = pure.joints[0].amplitude
        if len(pure.joints) == 1 and isinstance(amplitude, _Separable):
            squares.append((probability * abs(pure.amplitudes[0]) ** 2, amplitude))
        else:
            others.append((probability, pure))
    squares = _separable_blocks(squares)
    step = max(1, G_CHUNK // g.size)
    for lo in range(0, len(y), step):  # a few values at a time: [values, nr, nb] arrays
        value = y[lo:lo + step][:, None, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = value / g[None]  # e^sigma or rho^2; no solution where <= 0 or infinite
        ok = np.isfinite(scale) & (scale > 0) & (value != 0)
        scale = np.where(ok, scale, 1.0)
        if model == "haar2":
            coords = np.stack([np.broadcast_to(t[None, :, None], scale.shape), np.log(scale)],
                              -1)
            factor = 1.0 / np.where(value != 0, np.abs(value), 1.0)
        else:
            rho = np.sqrt(scale)
            coords = np.stack([rho * np.cos(t)[None, :, None], rho * np.sin(t)[None, :, None]],
                              -1)
            factor = scale / (2 * np.where(value != 0, np.abs(value), 1.0))
        total, evaluated = np.zeros(scale.shape), {}
        if squares:  # the states of one sector each: |c|^2 f^2 (measure), no phase
            flat = coords.reshape(-1, 2)
            total += (_squared_sum(squares, flat, evaluated) * measure(model, flat)
                      ).reshape(scale.shape)
        for probability, pure in others:
            for coef, _, dk, values in _cross_terms(pure, coords, evaluated):
                if dk not in phase:
                    phase[dk] = np.exp(-1j * dk * beta)[None, None, :]
                total += probability * (coef * phase[dk]).real * values
        total = np.where(ok, total * factor, 0.0)
        out[lo:lo + step] = np.einsum("vrb,r,b->v", total, wt, wbeta) / (2 * np.pi)
    return out


def g_component_densities(mixture, points: int = 51, tolerance: float = G_TOLERANCE,
                          components=G_COMPONENTS) -> dict[str, Marginal]:
    """Densities of the ``components`` (of G11, G22, G12; G = phi^T phi) of a mixture
    [(probability, PureState)] (n = 2): :func:`_g_density` on
    ``points`` values over the support (Tr G bounds |G_ab|; for the Lebesgue measure graded
    towards y = 0, :data:`GRADING`), each rule of :data:`ORIENTATION_NODES` checked against
    the one before point by point (:func:`_converged_g_density`; ``error``: the largest last
    change).
    States whose probability is below 1e-3 ``tolerance`` x the largest are left out.
    ``integral``: int p dy over the whole range, y = 0 included, by its own quadrature
    (:func:`_g_integral`, not the output points), with its error estimate
    ``integral_error``."""
    top_weight = max(w for w, _ in mixture)
    mixture = [(w, pure) for w, pure in mixture if w >= 1e-3 * tolerance * top_weight]
    # the range: Tr G (which bounds |G_ab|) below which all but 1e-10 of each state's mass
    # lies, and for the affine models (log-normal-like tails) the smallest squared singular
    # value above which all but 1e-10 lies, with a geometric grid between them
    hi, low = 0.0, np.inf
    for _, pure in mixture:
        for joint in pure.joints:
            mass = np.abs(joint.weights * joint(joint.nodes))
            xs = joint.nodes
            if joint.model == "haar2":
                trg = 2 * np.exp(xs[:, 1]) * np.cosh(xs[:, 0])
                small = np.exp(xs[:, 1] - xs[:, 0])
            else:
                trg = 2 * (xs[:, 0] ** 2 + xs[:, 1] ** 2)
                small = np.zeros_like(trg)
            for values, upper in ((trg, True), (small, False)):
                order = np.argsort(values)
                below = np.cumsum(mass[order]) / np.sum(mass)
                at = np.searchsorted(below, 1 - 1e-10 if upper else 1e-10)
                value = float(values[order][min(at, len(order) - 1)])
                hi, low = (max(hi, value), low) if upper else (hi, min(low, value))
    geometric = mixture[0][1].joints[0].model == "haar2"
    out = {}
    # a mixture of sector states has R uniform and independent of the shape, so G22 (beta
    # turned by a quarter) has the law of G11 (computed once) and G12 that of -G12
    uniform_r = all(len(pure.joints) == 1 for _, pure in mixture)
    for name in components:
        if name == "G22" and uniform_r and "G11" in out:
            out[name] = out["G11"]
            continue
        # y = 0 (where the densities of G11, G22 are limits and that of G12 has a logarithmic
        # peak) is left out of the grid; the Lebesgue grid is graded towards it (y ~ k^1.5),
        # where a d'Alembert ground state has its peak (e^-y, e^-2|y| for the oscillator: on
        # an even grid the first point, 1/51 of the range, showed 0.6 of the peak)
        if geometric:
            lo = low
            top = hi if name != "G12" else hi / 2
            half = np.geomspace(lo, top, points if name != "G12" else points // 2 + 1)
            y = half if name != "G12" else np.concatenate([-half[::-1], half])
        elif name == "G12":
            half = hi / 2 * (np.arange(1, points // 2 + 1) / (points // 2)) ** GRADING
            y = np.concatenate([-half[::-1], half])
        else:
            y = hi * (np.arange(1, points + 1) / points) ** GRADING
        inner = low if geometric else hi * 4.0**-ZERO_PANELS
        if name == "G12" and uniform_r:  # beta -> -beta: an even density, computed for y > 0
            p, change, nr = _converged_g_density(mixture, name, half, tolerance)
            p, change = np.concatenate([p[::-1], p]), np.concatenate([change[::-1], change])
            integral, integral_error = (2 * v for v in _g_integral(
                mixture, name, 0.0, hi / 2, inner, INTEGRAL_SLACK * tolerance))
        else:
            p, change, nr = _converged_g_density(mixture, name, y, tolerance)
            a, b = (-hi / 2, hi / 2) if name == "G12" else (low if geometric else 0.0, hi)
            integral, integral_error = _g_integral(mixture, name, a, b, inner,
                                                   INTEGRAL_SLACK * tolerance)
        err = float(np.max(change))
        out[name] = Marginal(y, p, err, integral, nr,
                             bool(np.all(np.isfinite(p)) and err <= tolerance * np.max(np.abs(p))),
                             integral_error)
    return out


#: Exponent of the grading of the Lebesgue G grids towards y = 0 (points at range x (k/K)^1.5).
GRADING = 1.5


def _converged_g_density(mixture, name: str, y: np.ndarray, tolerance: float,
                         weights: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, int]:
    """(p at y, the last change of each point, node count nr of the finest rule used) of
    :func:`_g_density` summed over the mixture: each rule of :data:`ORIENTATION_NODES` against
    the one before, point by point; a point whose value changed by at most ``tolerance`` x the
    peak keeps it, the others go on to the next rule (the points near y = 0 need finer rules
    than the rest). With quadrature ``weights`` w in y, a point is done when w x change is at
    most ``tolerance`` x I / (2 x number of points) (I = sum |w p| on the first rule) or its
    change at most ``tolerance`` x |p| / 2: either way the sum of w x value (an integral)
    changes by at most about ``tolerance`` x I, and a point of small weight (near y = 0,
    where the rules converge slowly) stops early."""
    (nb, nr), *finer = ORIENTATION_NODES
    p = _g_density(mixture, name, y, nb, nr)
    total = np.sum(np.abs(weights) * np.abs(p)) if weights is not None else None
    change = np.full(len(y), np.inf)
    active = np.ones(len(y), dtype=bool)
    for nb, nr in finer:
        finer_p = _g_density(mixture, name, y[active], nb, nr)
        change[active] = np.abs(finer_p - p[active])
        p[active] = finer_p
        if weights is None:
            active = ~(change <= tolerance * np.max(np.abs(p)))  # nan stays active
        else:  # half the budget spread over the points, half in proportion to w x value
            active = ~((np.abs(weights) * change <= tolerance * total / (2 * len(y)))
                       | (change <= tolerance * np.abs(p) / 2))
        if not active.any():
            break
    return p, change, nr


#: the integral of a G density is refined to this multiple of the densities' tolerance (x the
#: integral): a check that the density holds the whole mass (its error estimate is
#: pessimistic: 1e-6 stated where the oscillator's integrals are within 1e-8 of 1)
INTEGRAL_SLACK = 10
#: panels of the integrals of the G densities: ratio-4 panels from each end of the range
#: towards y = 0, for the Lebesgue measure ZERO_PANELS of them, then one panel to 0 (G11 and
#: G22 tend to a limit at 0, G12 to a logarithmic peak)
ZERO_PANELS = 3


def _panel_edges(a: float, b: float, inner: float) -> np.ndarray:
    """Edges of ratio-4 panels on [a, b] (one side of 0): geometric from the end away from 0
    down to ``inner`` and one panel from there to 0 where 0 is an end, else geometric."""
    if a == 0.0 or b == 0.0:
        end = abs(a or b)
        count = max(1, int(np.ceil(np.log(end / inner) / np.log(4.0))))
        return np.sign(a or b) * np.concatenate([[0.0], np.geomspace(inner, end, count + 1)])
    return np.geomspace(a, b, max(1, int(np.ceil(np.log(b / a) / np.log(4.0)))) + 1)


def _g_integral(mixture, name: str, lo: float, hi: float, inner: float, tolerance: float
                ) -> tuple[float, float]:
    """(int_lo^hi p dy, its error estimate) for the density p of the component ``name`` of G:
    15-point Gauss-Kronrod panels (:func:`kronrod_panels`) of ratio 4 on each side of 0, down
    to |y| = ``inner`` and then one panel to 0 where 0 is an end of [lo, hi] or inside it,
    else geometric from lo > 0 to hi (the affine models' G11 and G22). The values are refined
    by :func:`_converged_g_density` with the panel weights until the sum changes by at most
    ``tolerance`` x the integral. Error: |Kronrod - Gauss| plus the sum of weight x last change
    of each value (the rules' own error)."""
    sides = [(lo, 0.0), (0.0, hi)] if lo < 0 < hi else [(lo, hi)]
    nodes, wk, wg = (np.concatenate(parts).ravel() for parts in zip(
        *(kronrod_panels(np.sort(_panel_edges(a, b, inner))) for a, b in sides), strict=True))
    p, change, _ = _converged_g_density(mixture, name, nodes, tolerance, wk)
    kronrod, gauss = float(np.sum(wk * p)), float(np.sum(wg * p))
    return kronrod, abs(kronrod - gauss) + float(np.sum(np.abs(wk) * change))


def _density_warning(name: str, m: Marginal, tolerance: float) -> str:
    """The one-line warning of an unconverged density: not finite, or its error too large."""
    bad = int(np.sum(~np.isfinite(m.density)))
    if bad:
        return (f"density of {name}: not finite at {bad} of {len(m.density)} points "
                f"(written as they are, flagged converged: false)")
    peak = float(np.max(np.abs(m.density)))
    return (f"density of {name}: quadrature error {m.error / peak:.1e} of its peak "
            f"{peak:.3g}, above the tolerance {tolerance:g}")


def orientation_densities(spectrum: Spectrum, state: int | None = None,
                          superposition: dict[int, complex] | None = None,
                          temperature: float | None = None, points: int = 51,
                          tolerance: float = G_TOLERANCE) -> dict:
    """Densities of the orientations of the principal axes of C and G (the angles of L and R,
    phi = L D R^T) and of the components of G for one state, a superposition {state index:
    amplitude} or the thermal mixture at ``temperature`` (exactly one of them).

    n = 2: the angle densities of :func:`angle_densities` (uniform for a sector state and for
    the thermal mixture, a sum of sector states) and :func:`g_component_densities`. n = 3:
    quantum.orientations3 (not called from here: that module sits above this one); refused
    here (ValueError)."""
    if sum(v is not None for v in (state, superposition, temperature)) != 1:
        raise ValueError("give exactly one of a state, a superposition or a temperature")
    if spectrum.n == 3:
        raise ValueError("n = 3: the orientation densities of states, superpositions and "
                         "thermal mixtures are quantum.orientations3 (orientation_densities3, "
                         "mixture_orientations)")
    warnings = []
    if temperature is not None:
        states, probabilities, tail = thermal_states(spectrum, temperature)
        mixture = list(zip(probabilities, states, strict=True))
        if tail > tolerance:
            warnings.append(truncation_warning(len(states), tail))
        kind = "thermal"
    else:
        amplitudes = superposition if superposition is not None else {state: 1.0}
        mixture = [(1.0, pure_state(spectrum, amplitudes))]
        kind = "superposition" if superposition is not None else "state"
    angle = np.linspace(0.0, 2 * np.pi, 361)
    sums = {"L_angle": np.zeros_like(angle), "R_angle": np.zeros_like(angle)}
    for w, pure in mixture:
        for key, value in angle_densities(pure, angle).items():
            sums[key] += w * value
    details = g_component_densities(mixture, points, tolerance)
    for name, m in details.items():
        if not m.converged:
            warnings.append(_density_warning(name, m, tolerance))
    return {"kind": kind, "orientation": {"angle": angle, **sums}, "G": details,
            "warnings": warnings}


__all__ = [
    "NODES", "POINTS", "DEFAULT_TOLERANCE", "VARIABLES", "SUPPORT", "Joint", "measure",
    "joint_density", "Marginal", "density_at", "densities", "marginal_densities", "orientation",
    "ORIENTATION_NODES", "G_TOLERANCE", "G_COMPONENTS", "GRADING", "INTEGRAL_SLACK",
    "ZERO_PANELS", "G_CHUNK", "kronrod_panels", "PureState", "SEPARABLE_BLOCK",
    "coefficient_extent", "separable_values",
    "state_components", "pure_state", "MAX_THERMAL_STATES", "require_temperature",
    "boltzmann_factors",
    "truncation_warning", "thermal_states", "angle_densities", "g_component_densities",
    "orientation_densities", "projected_triangle"
]
