"""Certified lower bounds of the lowest level of every n = 2 sector and every n = 3 sector
(j, j'): the stopping rule of the sector search (docs/theory/two-polar.md, "Lower bounds of a
sector"; n = 3: :func:`lebesgue3_shell_bounds`, :func:`haar3_shell_bounds`).

In a sector the reduced operator is H = T + U with a kinetic part T that is a non-negative
quadratic form under the sector's measure (integrate by parts: <psi, T psi> = (hbar^2/M)
int |d_x psi|^2 sinh x dx dsigma + hbar^2/(M + 2B) int |d_sigma psi|^2 ..., resp.
(hbar^2/4I) int |d_r1 psi|^2 + |d_r2 psi|^2 r1 r2 dr1 dr2) and a multiplication operator U, so
E_min(sector) >= inf U:

* affine models, sector (s, k), p = s + k, d = s - k, x = q1 - q2 >= 0, sigma = q1 + q2:
  U = V + c p^2 / sinh^2(x/2) - c d^2 / cosh^2(x/2) + e r^2, c = hbar^2/(16 M), e = hbar^2/(2 I~),
  r = k (af-is) or s (is-af);
* d'Alembert, block (|m1|, |m2|), r1 = rho cos(theta), r2 = rho sin(theta):
  U = V + hbar^2 (m1^2 / r1^2 + m2^2 / r2^2) / (4 I).

V is bounded below on a partition of the reduced domain into cells (unbounded ones included)
by interval arithmetic on its expression (:mod:`affinebody.quantum.intervals`); the centrifugal
terms are bounded on each cell in closed form (for af-is: inf over u = sinh^2(x/2) in
[u_lo, u_hi] of a/u - b/(1 + u), attained at the ends or at u* = sqrt(a)/(sqrt(b) - sqrt(a))).
The minimum over cells of the two bounds is a lower bound of E_min(sector).

Infinitely many sectors: the centrifugal part is a quadratic form in (p, d) (resp. (m1, m2)),
so on each cell U >= v_cell + lambda_min L^2 for every sector of shell L. Affine models (not
af-af): 2 (s^2 + k^2) = p^2 + d^2 >= 2 L^2 and lambda_min >= det / tr = c (e - 4c) /
(4c + (e/2) sinh^2 x) (both from the 2 x 2 matrix of the form, decreasing in x); d'Alembert:
m1^2 + m2^2 >= L^2 / 2 and lambda_min = hbar^2 / (4 I rho^2). The tail bound is the minimum over
cells at the first shell not enumerated.

What is certified and what is assumed: the enclosures of V (round-off, libm within 1 ulp, see
:mod:`affinebody.quantum.intervals`) and the closed forms above, evaluated in float64 and
lowered by a relative 1e-12; the comparison with the K-th level uses the computed (Galerkin,
i.e. variational upper-bound) candidate energies. A potential given as a Python callable
cannot be bounded: the search then runs to max_spin and the result says it is conditional.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.intervals import (
    Haar3Cells,
    HaarCells,
    Interval,
    Lebesgue3Cells,
    LebesgueCells,
    Unsupported,
    Value,
    lower_bounds,
)
from affinebody.quantum.levels import AffineInertia

#: safety margin (relative) subtracted from every bound for the float64 evaluation
MARGIN = 1e-12


@dataclass(frozen=True)
class ShellBounds:
    """Lower bounds of the lowest level: ``shell_min[L]`` over the sectors of shell L
    (L = 0 .. len - 1), ``tail`` over every sector of a higher shell."""

    shell_min: np.ndarray
    tail: float
    method: str
    #: the bound of each sector (block key) of the shells enumerated
    sector: dict = field(default_factory=dict)

    def of(self, key: tuple) -> float:
        """Lower bound of every level of the block ``key`` (-inf if unknown)."""
        return float(self.sector.get(key, -np.inf))

    def beyond(self, shell: int) -> float:
        """Lower bound of every level of the sectors of the shells > ``shell``."""
        rest = self.shell_min[shell + 1:]
        return float(min(np.min(rest) if len(rest) else np.inf, self.tail))


def _lowered(value: np.ndarray) -> np.ndarray:
    return value - MARGIN * (1.0 + np.abs(value))


def _expression(potential) -> str:
    text = getattr(potential, "text", None)
    if not isinstance(text, str):
        raise Unsupported("the potential is a Python callable, not an expression")
    return text


# --------------------------------------------------------------------- affine models (n = 2)
def haar_strip_edges() -> np.ndarray:
    """Edges of the strips in x = q1 - q2: fine near 0, geometric far out, the last unbounded."""
    return np.concatenate([np.linspace(0.0, 8.0, 321), np.geomspace(8.0, 80.0, 41)[1:],
                           [np.inf]])


def haar_strip_minima(text: str, centre: float, x_edges: np.ndarray, sigma_stiffness: float = 0.0,
                      kappas: tuple[float, ...] = (0.0,)) -> np.ndarray:
    """w_i <= inf over x in [x_i, x_(i+1)] of the fibre operator T_sigma + V(x, .) (module
    docstring): for each kappa >= 0, T_sigma + kappa (sigma - centre)^2 >= sqrt(alpha kappa)
    (alpha = ``sigma_stiffness`` = hbar^2 / (M + 2B): the oscillator ground state), so
    w_i = max over kappa of [sqrt(alpha kappa) + inf (V - kappa (sigma - centre)^2)], the
    infimum bounded by interval arithmetic on cells in sigma (width 0.025 within 12 of
    ``centre``, wider out to 48, then two unbounded ones). kappa = 0 is the plain inf V."""
    inner = np.linspace(-12.0, 12.0, 961)
    outer = np.geomspace(12.0, 48.0, 25)[1:]
    s_edges = np.concatenate([[-np.inf], centre - outer[::-1], centre + inner, centre + outer,
                              [np.inf]])
    XL, SL = np.meshgrid(x_edges[:-1], s_edges[:-1], indexing="ij")
    XH, SH = np.meshgrid(x_edges[1:], s_edges[1:], indexing="ij")
    cells = HaarCells(XL, XH, SL, SH)
    best = np.full(len(x_edges) - 1, -np.inf)
    for kappa in kappas:
        # V - kappa (sigma - centre)^2, the square joining the degree-0 group as a form
        square = Value(Interval.point(-kappa * centre * centre), a=2 * kappa * centre,
                       qq=-kappa)
        shifted = lower_bounds(text, cells, square if kappa > 0 else None)
        zero_point = math.sqrt(sigma_stiffness * kappa) * (1 - 1e-12)
        best = np.maximum(best, np.min(shifted, axis=1) + zero_point)
    return best


def centrifugal_haar_min(a: np.ndarray, b: np.ndarray, x_lo: np.ndarray, x_hi: np.ndarray
                         ) -> np.ndarray:
    """inf over x in [x_lo, x_hi] of a / sinh^2(x/2) - b / cosh^2(x/2) (a, b >= 0), closed form
    in u = sinh^2(x/2): f(u) = a/u - b/(1 + u) decreases if b <= a, else has its minimum
    -(sqrt(b) - sqrt(a))^2 at u* = sqrt(a) / (sqrt(b) - sqrt(a))."""
    a, b = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float))
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        u_lo = np.sinh(x_lo / 2) ** 2
        u_hi = np.where(np.isfinite(x_hi), np.sinh(np.minimum(x_hi, 1400.0) / 2) ** 2, np.inf)
        ra, rb = np.sqrt(a), np.sqrt(b)
        u_star = np.where(rb > ra, ra / np.where(rb > ra, rb - ra, 1.0), np.inf)
        u = np.clip(u_star, u_lo, u_hi)

        def f(u):
            first = np.where(a == 0, 0.0, a / u)
            second = np.where(b == 0, 0.0, b / (1 + u))
            return first - second
        value = f(u)
    return np.where(np.isnan(value), -np.inf, value)


def haar2_shell_bounds(potential, hbar: float, inertia: AffineInertia, max_shell: int,
                       centre: float, scale_sigma: float) -> ShellBounds:
    """Lower bounds per shell max(|s|, |k|) <= ``max_shell`` and beyond, for af-is / is-af
    (module docstring). Raises :class:`Unsupported` where none can be certified."""
    if inertia.model == "af-af":
        raise Unsupported("af-af is unbounded below")
    text = _expression(potential)
    edges = haar_strip_edges()
    x_lo, x_hi = edges[:-1], edges[1:]
    alpha = hbar**2 / inertia.dilatation
    base = alpha / scale_sigma**4  # the stiffness of which scale_sigma is the oscillator length
    v = haar_strip_minima(text, centre, edges, alpha,
                          tuple(f * base for f in (0.0, 0.25, 0.5, 0.75, 0.9)))
    c = hbar**2 / (16 * inertia.M)
    e = hbar**2 * inertia.inv_I_tilde / 2
    shell_min = np.full(max_shell + 1, np.inf)
    sector: dict = {}
    for L in range(max_shell + 1):
        keys = [(s, k) for s in range(-L, L + 1) for k in range(-L, L + 1)
                if max(abs(s), abs(k)) == L and (s + k) % 2 == 0]
        s, k = np.array(keys, float).T
        r = k if inertia.model == "af-is" else s
        cent = centrifugal_haar_min(((s + k) ** 2)[:, None], ((s - k) ** 2)[:, None],
                                    x_lo[None, :], x_hi[None, :])
        each = _lowered(np.min(v[None, :] + c * cent, axis=1) + e * r * r)
        sector.update(zip(keys, each.tolist(), strict=True))
        shell_min[L] = np.min(each)
    with np.errstate(over="ignore"):
        sinh2 = np.sinh(np.minimum(x_hi, 700.0)) ** 2
        lam = np.maximum(c * (e - 4 * c), 0.0) / (4 * c + 0.5 * e * sinh2)
    lam = np.where(np.isfinite(x_hi), lam, 0.0)
    L = max_shell + 1
    tail = float(_lowered(np.min(v + 2 * lam * L * L)))
    return ShellBounds(shell_min, tail,
                       "certified: kinetic form >= 0, V bounded below by interval arithmetic "
                       "on its expression over cells of (x, sigma), centrifugal terms in closed "
                       "form (docs/theory/two-polar.md, 'Lower bounds of a sector')", sector)


# --------------------------------------------------------------------- d'Alembert (n = 2)
def lebesgue2_shell_bounds(potential, hbar: float, inertia: float, max_shell: int,
                           length: float) -> ShellBounds:
    """Lower bounds per shell |m1| + |m2| <= ``max_shell`` and beyond for the n = 2 d'Alembert
    body, J = inertia * Id (module docstring); ``length``: the oscillator length of the basis,
    which sets the radial cells. Raises :class:`Unsupported` where none can be certified."""
    text = _expression(potential)
    r_edges = length * np.concatenate([np.linspace(0.0, 8.0, 161), np.geomspace(8.0, 64.0, 21)[1:],
                                       [np.inf]])
    t_edges = np.linspace(0.0, math.pi / 2, 65)
    RL, TL = np.meshgrid(r_edges[:-1], t_edges[:-1], indexing="ij")
    RH, TH = np.meshgrid(r_edges[1:], t_edges[1:], indexing="ij")
    v = lower_bounds(text, LebesgueCells(RL, RH, TL, TH)).ravel()
    w = hbar**2 / (4 * inertia)
    with np.errstate(divide="ignore"):
        inv1 = np.where(np.isfinite(RH), 1 / (RH * np.cos(TL)) ** 2, 0.0).ravel()
        inv2 = np.where(np.isfinite(RH), 1 / (RH * np.sin(TH)) ** 2, 0.0).ravel()
        inv_rho = np.where(np.isfinite(RH), 1 / RH**2, 0.0).ravel()
    shell_min = np.full(max_shell + 1, np.inf)
    sector: dict = {}
    for L in range(max_shell + 1):
        a = np.arange(L + 1, dtype=float)[:, None]
        bound = v[None, :] + w * (a * a * inv1[None, :] + (L - a) ** 2 * inv2[None, :])
        each = _lowered(np.min(bound, axis=1))
        sector.update({(int(m), L - int(m)): float(b) for m, b in zip(a[:, 0], each,
                                                                        strict=True)})
        shell_min[L] = float(np.min(each))
    L = max_shell + 1
    tail = float(_lowered(np.min(v + w * L * L / 2 * inv_rho)))
    return ShellBounds(shell_min, tail,
                       "certified: kinetic form >= 0, V bounded below by interval arithmetic "
                       "on its expression over cells of (rho, theta), centrifugal terms at the "
                       "cell corners (docs/theory/two-polar.md, 'Lower bounds of a sector')",
                       sector)


# ------------------------------------------------------------------------------- n = 3
def _sectors3(max_shell: int) -> list[list[tuple[int, int]]]:
    """The sectors (j, j') with a non-empty module, by shell max(j, j') <= ``max_shell``."""
    return [[(j, jp) for j in range(L + 1) for jp in range(L + 1) if max(j, jp) == L
             and cov.fixed_dimension(j, jp) > 0] for L in range(max_shell + 1)]


def _by_shell(each, max_shell: int, tail: float, method: str) -> ShellBounds:
    shell_min = np.full(max_shell + 1, np.inf)
    sector: dict = {}
    for L, keys in enumerate(_sectors3(max_shell)):
        for key in keys:
            sector[key] = float(each(*key))
            shell_min[L] = min(shell_min[L], sector[key])
    return ShellBounds(shell_min, float(tail), method, sector)


def lebesgue3_shell_bounds(potential, hbar: float, inertia: float, max_shell: int,
                           length: float) -> ShellBounds:
    """Lower bounds of the lowest level of every n = 3 d'Alembert sector (j, j'), J = inertia
    * Id, shells max(j, j') <= ``max_shell`` and beyond (docs/theory/two-polar.md, "Lower
    bounds of an n = 3 sector").

    On R^9, -Lap = -d_rho^2 - (8/rho) d_rho + (-Lap_S8)/rho^2 with the radial part a
    non-negative form under rho^8 drho; a state of the sector lies, on every sphere, in the
    harmonics of degree >= d = covariants3.lowest_degree(j, j') (>= max(j, j')), where -Lap_S8
    >= d (d + 7). So E_min >= inf over Q of hbar^2 d (d + 7) / (2 I |Q|^2) + V(Q), bounded on
    cells (rho, theta, psi) of the chamber (:class:`~affinebody.quantum.intervals.Lebesgue3Cells`)
    with the centrifugal term at rho_hi; the bound increases with d, so d = max_shell + 1
    bounds every sector of the shells not enumerated."""
    text = _expression(potential)
    r_edges = length * np.concatenate([np.linspace(0.0, 12.0, 601),
                                       np.geomspace(12.0, 96.0, 25)[1:], [np.inf]])
    t_edges = np.linspace(0.0, math.atan(math.sqrt(2.0)), 17)
    p_edges = np.linspace(-math.pi / 4, math.pi / 4, 17)
    lo = np.meshgrid(r_edges[:-1], t_edges[:-1], p_edges[:-1], indexing="ij")
    hi = np.meshgrid(r_edges[1:], t_edges[1:], p_edges[1:], indexing="ij")
    v = np.min(lower_bounds(text, Lebesgue3Cells(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])),
               axis=(1, 2))
    with np.errstate(divide="ignore"):
        inv = np.where(np.isfinite(r_edges[1:]), 1 / r_edges[1:] ** 2, 0.0)
    w = hbar**2 / (2 * inertia)

    def bound(d: int) -> float:
        return float(_lowered(np.min(v + w * d * (d + 7) * inv)))
    return _by_shell(lambda j, jp: bound(cov.lowest_degree(j, jp)), max_shell,
                     bound(max_shell + 1),
                     "certified: radial kinetic form >= 0, the sector's harmonics of degree "
                     ">= d carry -Lap_S8 >= d(d+7), V bounded below by interval arithmetic on "
                     "its expression over cells of (rho, theta, psi) "
                     "(docs/theory/two-polar.md, 'Lower bounds of an n = 3 sector')")


#: (gamma, beta b^2, R / b) of the trial functions h = exp(-gamma rho . q - beta psi_R(|y|))
TRIALS = ((0.5, 0.0, 1.0), (1.0, 0.0, 1.0)) + tuple(
    (g, bb, rr) for g in (0.0, 0.25, 0.5, 1.0) for bb in (0.25, 0.5, 0.75, 1.0, 1.5, 2.0)
    for rr in (2.0, 4.0, 8.0))


def haar3_kinetic_min(gamma: float, beta: float, R: float, x_lo: np.ndarray, x_hi: np.ndarray,
                      r_lo: np.ndarray, r_hi: np.ndarray, x12_hi: np.ndarray | None = None,
                      x23_hi: np.ndarray | None = None) -> np.ndarray:
    """Lower bound of L h / h on cells where x13 = q_1 - q_3 lies in [x_lo, x_hi] and the shear
    radius |y| in [r_lo, r_hi], for h = exp(-phi), phi = gamma rho . q + beta psi(|y|),
    rho = (1, 0, -1) (half the sum of the roots q_a - q_b), y the traceless part of q,
    psi(r) = r^2/2 for r <= R and R r - R^2/2 beyond (C^1, convex). Then
    int |grad_perp F|^2 J dq >= int (L h / h) F^2 J dq (ground-state representation,
    docs/theory/two-polar.md, "Lower bounds of an n = 3 sector"), with
    L h / h = -|grad phi|^2 + Lap phi + grad ln J . grad phi, i.e. for r <= R

        gamma (coth x12 + coth x23 + 2 coth x13) - 2 gamma^2
        + beta (2 + sum_ab x_ab coth x_ab) - 2 gamma beta x13 - beta^2 r^2,

    and for r >= R (psi' = R, Lap psi = R / r, x13 / r in [sqrt(3/2), sqrt 2], sum_ab x_ab
    coth x_ab >= sum_ab x_ab = 2 x13) at least gamma (...) - 2 gamma^2 + beta sqrt 6 R
    - 2 sqrt 2 gamma beta R - beta^2 R^2. coth is convex and decreasing, x coth x convex and
    increasing, x12 + x23 = x13, so coth x12 + coth x23 >= 2 coth(x13/2) and x12 coth x12 +
    x23 coth x23 >= x13 coth(x13/2); given ``x12_hi``, ``x23_hi`` also coth x12 + coth x23 >=
    coth x12_hi + coth x23_hi. A cell meeting both regions takes the smaller bound."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        def coth(x):
            return np.where(np.isfinite(x), 1.0 / np.tanh(np.minimum(x, 700.0)), 1.0)
        cot = np.maximum(2 * coth(x_hi / 2), 0.0 if x12_hi is None else coth(x12_hi)
                         + coth(x23_hi)) + 2 * coth(x_hi)
        xl = np.minimum(x_lo, 700.0)
        xcot = np.where(x_lo > 0, xl / np.tanh(xl / 2) + xl / np.tanh(xl), 3.0)
        base = gamma * cot - 2 * gamma**2
        if not beta:
            return base
        rr = np.minimum(r_hi, R)
        inner = base + beta * (2 + xcot) - 2 * gamma * beta * math.sqrt(2.0) * rr - beta**2 * rr**2
        outer = base + beta * math.sqrt(6.0) * R - 2 * math.sqrt(2.0) * gamma * beta * R \
            - beta**2 * R**2
        out = np.minimum(np.where(r_lo < R, inner, np.inf), np.where(r_hi > R, outer, np.inf))
    return np.where(np.isnan(out), -np.inf, out)


#: fractions theta of the Casimir coefficient e kept on the Casimir-carrying generator
THETAS = (0.0, 0.25, 0.5, 0.75, 0.9, 1.0)


def _two_smallest(values: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    ordered = np.sort(np.stack(values), axis=0)
    return ordered[0], ordered[1]


def haar3_centrifugal_min(j_free: int, j_paid: int, x_hi: list[np.ndarray], c0: float,
                          e: float, monotone: bool = False) -> np.ndarray:
    """Lower bound of the centrifugal and Casimir terms of an n = 3 affine sector on cells where
    x_g = q_a - q_b <= ``x_hi[g]`` (g = 12, 23, 13): j_paid is the spin of the generators v
    that carry e |v|^2 (af-is: j'; is-af: j), j_free the other one.

    Per pair the form is (a, b; b, a + e) in (u_g, v_g), a = 4 c0 / sinh^2 x, b = a cosh x.
    For theta in [0, 1] and f = (1 - theta) e it is >= diag(mu, theta e) with mu = a - b^2/
    (a + f) = (f - 4 c0) a / (a + f) (a sinh^2 x = 4 c0): decreasing in x from f - 4 c0 to 0
    if f >= 4 c0, else >= f - 4 c0 everywhere; and >= lambda (1, 1), lambda = det / tr
    decreasing. The weights w_g = |u_g|^2 / |f|^2 sum to j(j+1) = j^2 + j and each is <= j^2
    (the largest eigenvalue of -K_g^2 on V_j), so sum_g mu_g w_g >= mu_(1) j^2 + mu_(2) j with
    mu_(1) <= mu_(2) the two smallest of the mu_g >= 0 (likewise for lambda with j^2 + j'^2,
    j + j'); sum_g |v_g|^2 = j_paid (j_paid + 1). The best of these forms per cell; for
    j_paid = 0 (v = 0) the form is exactly sum_g A_g |u_g|^2, for j_free = 0 (u = 0)
    sum_g (A_g + e) |v_g|^2, bounded the same way;
    ``monotone``: only those non-decreasing in both spins (f >= 4 c0 and lambda)."""
    jf, jp = j_free, j_paid
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        a = [np.where(np.isfinite(x), 4 * c0 / np.sinh(np.minimum(x, 700.0)) ** 2, 0.0)
             for x in x_hi]
        if jp == 0 or jf == 0:  # v = 0 (resp. u = 0): the form is A |u|^2 (resp. (A + e) |v|^2)
            low, second = _two_smallest(a)
            j = jf or jp
            return low * j * j + second * j + (e * jp * (jp + 1) if jp else 0.0)
        lam = [np.where(np.isfinite(x), max(c0 * (e - 4 * c0), 0.0)
                        / (2 * c0 + 0.25 * e * np.sinh(np.minimum(x, 700.0)) ** 2), 0.0)
               for x in x_hi]
        low, second = _two_smallest(lam)
        best = low * (jf * jf + jp * jp) + second * (jf + jp)
        for theta in THETAS:
            f = (1 - theta) * e
            if f >= 4 * c0:
                low, second = _two_smallest([np.where(np.isinf(ag), f - 4 * c0,
                                                      (f - 4 * c0) * ag / (ag + f)) for ag in a])
                free = low * jf * jf + second * jf
            elif monotone:
                continue
            else:
                free = np.full_like(a[0], (f - 4 * c0) * jf * (jf + 1))
            best = np.maximum(best, free + theta * e * jp * (jp + 1))
    return best


#: sectors with at most this many radial functions also take the lowest eigenvalue of their
#: centrifugal matrix on each cell (:func:`haar3_centrifugal_matrix_min`)
MATRIX_RANK = 48


def haar3_centrifugal_matrix_min(j: int, jp: int, c_plus: np.ndarray, c_minus: np.ndarray,
                                 casimir: float) -> np.ndarray:
    """Lower bound, per cell, of the centrifugal and Casimir terms of the n = 3 affine sector
    (j, j'): the lowest eigenvalue of sum_g [c_plus[g] N_plus[g] + c_minus[g] N_minus[g]]
    + casimir on the M-fixed subspace (:func:`~affinebody.quantum.covariants3.fixed_forms`,
    N_pm = |u_g +- v_g|^2 >= 0), with c_plus[g] <= c = c_0 / sinh^2(x_g/2) and
    c_minus[g] <= -c' = -c_0 / cosh^2(x_g/2) on the cell (c at the cell's largest x_g, -c' at
    its smallest: c decreases, -c' increases with x_g). Both forms N_pm are non-negative, so
    lowering their coefficients lowers the form; the lowest eigenvalue (numpy's eigvalsh,
    lowered by 1e-12 of the matrix's size) bounds it on every state of the sector. Exact
    where the pairwise closed forms of :func:`haar3_centrifugal_min` lose the coupling of
    the three pairs (the (j, 1) sectors)."""
    plus, minus = cov.fixed_forms(j, jp)
    U = (np.einsum("g...,grs->...rs", c_plus, plus)
         + np.einsum("g...,grs->...rs", c_minus, minus))
    size = np.abs(U).sum(axis=(-2, -1))
    return np.linalg.eigvalsh(U)[..., 0] - 1e-12 * (1.0 + size) + casimir


#: the cells (r, t) near the minimum of a sector's bound are split SPLIT x SPLIT
SPLIT = 2

#: multiples of the dilatation stiffness hbar^2 3 / (2 (M + 3B) b^4) tried per shear cell
KAPPAS = (0.0, 0.25, 0.5, 0.9, 1.0, 2.0)


def haar3_shell_bounds(potential, hbar: float, inertia: AffineInertia, max_shell: int,
                       centre: float, scale_sigma: float = 1.0, scale: float = 1.0,
                       enumerate_to: int | None = None) -> ShellBounds:
    """Lower bounds of the lowest level of every n = 3 af-is / is-af sector (j, j'), shells
    max(j, j') <= ``max_shell`` and beyond (docs/theory/two-polar.md, "Lower bounds of an
    n = 3 sector").

    The gradient form splits into the dilatation and the shear plane (G has the eigenvalue
    1/(M + 3B) on (1, 1, 1), 1/M on the plane): with sigma = q_1 + q_2 + q_3 it is
    alpha |d_sigma f|^2 + (hbar^2/2M) |grad_perp f|^2, alpha = 3 hbar^2 / (2 (M + 3B)), J
    independent of sigma. Hence, pointwise in the shear plane,
    * alpha |d_sigma f|^2 + kappa (sigma - centre)^2 |f|^2 >= sqrt(alpha kappa) |f|^2 along
      each sigma line (the oscillator ground state; kappa >= 0 chosen per shear cell,
      multiples :data:`KAPPAS` of alpha / ``scale_sigma``^4);
    * the shear form (hbar^2/2M) |grad_perp f|^2 >= (hbar^2/2M) (L h / h) |f|^2 in the
      integral, for one trial function h on the whole plane (:func:`haar3_kinetic_min`,
      :data:`TRIALS` with beta in units of 1/``scale``^2, R of ``scale``; the best h per
      sector);
    * the centrifugal and Casimir terms >= free C_free + paid C_paid (pair by pair, every
      x_g <= q_1 - q_3, sum_g |u_g|^2 = j(j+1), sum_g |v_g|^2 = j'(j'+1)), the best of the
      forms of :func:`haar3_centrifugal_min`.
    So E_min >= max over h of inf over the chamber of V - kappa (sigma - centre)^2 +
    sqrt(alpha kappa) + (hbar^2/2M) L h / h + centrifugal, bounded on cells (r, t, sigma)
    (:class:`~affinebody.quantum.intervals.Haar3Cells`; q_1 - q_3 = sqrt2 r sin(t + pi/6),
    the centrifugal bounds at its largest value on the cell). Sectors with min(j, j') <= 1
    also take the lowest eigenvalue of their centrifugal matrix
    (:func:`haar3_centrifugal_matrix_min`), and the cells near a sector's minimum (within
    hbar^2/(2 M scale^2) for its best trial, repeatedly while the minimum moves) are split
    SPLIT x SPLIT, each part trying its coarse cell's best kappa. Sectors are bounded one by
    one up to the shell ``enumerate_to`` (at least ``max_shell``); beyond
    (j(j+1) + j'(j'+1) >= L(L+1)) only the part of the centrifugal bound with both
    coefficients >= 0 is used."""
    if inertia.model == "af-af":
        raise Unsupported("af-af is unbounded below")
    text = _expression(potential)
    r_edges = np.concatenate([np.linspace(0.0, 6.0, 121), np.geomspace(6.0, 60.0, 21)[1:],
                              [np.inf]])
    t_edges = np.linspace(math.pi / 6, math.pi / 2, 17)
    inner = np.linspace(-12.0, 12.0, 49)  # sigma enters V by exact forms where it can
    outer = np.geomspace(12.0, 48.0, 5)[1:]
    s_edges = np.concatenate([[-np.inf], centre - outer[::-1], centre + inner, centre + outer,
                              [np.inf]])
    alpha = 3 * hbar**2 / (2 * (inertia.M + 3 * inertia.B))
    kappas = [f * alpha / scale_sigma**4 for f in KAPPAS]
    c0 = hbar**2 / (16 * inertia.M)
    e = hbar**2 * inertia.inv_I_tilde / 2

    def cells(r_lo, r_hi, t_lo, t_hi, use: np.ndarray | None = None) -> dict:
        """Per cell (1D arrays): v (V with the dilatation, bounded below; ``use``: the one
        kappa to try per cell, else all, the best recorded), the extreme x_g, c at each x_g's
        largest and -c' at its smallest value, the trials' kinetic bounds."""
        v = np.full(len(r_lo), -np.inf)
        best = np.zeros(len(r_lo), int)
        for k, kappa in enumerate(kappas):
            rows = slice(None) if use is None else np.flatnonzero(use == k)
            if use is not None and not len(rows):
                continue
            lo = np.broadcast_arrays(r_lo[rows, None], t_lo[rows, None], s_edges[None, :-1])
            hi = np.broadcast_arrays(r_hi[rows, None], t_hi[rows, None], s_edges[None, 1:])
            box = Haar3Cells(lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
            # V - kappa (sigma - centre)^2, the square joining the degree-0 group as a form
            square = Value(Interval.point(-kappa * centre * centre), a=2 * kappa * centre,
                           qq=-kappa)
            shifted = np.min(lower_bounds(text, box, square if kappa > 0 else None), axis=1)
            shifted = shifted + math.sqrt(alpha * kappa) * (1 - 1e-12)
            best[rows] = np.where(shifted > v[rows], k, best[rows])
            v[rows] = np.maximum(v[rows], shifted)
        root2 = math.sqrt(2.0)
        # x13 = sqrt2 r sin(t + pi/6) (largest at t = pi/3), x12 = sqrt2 r cos t (decreasing
        # in t), x23 = sqrt2 r sin(t - pi/6) (increasing)
        top = np.where(t_hi <= math.pi / 3, np.sin(t_hi + math.pi / 6),
                       np.where(t_lo >= math.pi / 3, np.sin(t_lo + math.pi / 6), 1.0))
        x = {"13hi": root2 * r_hi * top,
             "13lo": root2 * r_lo * np.minimum(np.sin(t_lo + math.pi / 6),
                                               np.sin(t_hi + math.pi / 6)),
             "12hi": root2 * r_hi * np.cos(t_lo), "12lo": root2 * r_lo * np.cos(t_hi),
             "23hi": root2 * r_hi * np.sin(t_hi - math.pi / 6),
             "23lo": root2 * r_lo * np.sin(t_lo - math.pi / 6)}
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            c_plus = np.array([np.where(np.isfinite(x[g]), c0 / np.sinh(
                np.minimum(x[g], 1400.0) / 2) ** 2, 0.0) for g in ("12hi", "13hi", "23hi")])
            c_minus = np.array([-c0 / np.cosh(np.minimum(x[g], 1400.0) / 2) ** 2
                                for g in ("12lo", "13lo", "23lo")])
        kinetic = np.array([hbar**2 / (2 * inertia.M) * haar3_kinetic_min(
            g, bb / scale**2, rr * scale, x["13lo"], x["13hi"], r_lo, r_hi, x["12hi"],
            x["23hi"]) for g, bb, rr in TRIALS])
        return {"v": v, "kappa": best, "pairs": [x["12hi"], x["23hi"], x["13hi"]],
                "c_plus": c_plus, "c_minus": c_minus, "kinetic": kinetic}

    R_lo, T_lo = (a.ravel() for a in np.meshgrid(r_edges[:-1], t_edges[:-1], indexing="ij"))
    R_hi, T_hi = (a.ravel() for a in np.meshgrid(r_edges[1:], t_edges[1:], indexing="ij"))
    coarse = cells(R_lo, R_hi, T_lo, T_hi)
    split: dict[int, dict] = {}  # coarse cell -> its SPLIT x SPLIT cells (as needed)

    def refined(index: np.ndarray) -> dict:
        missing = [int(i) for i in index if int(i) not in split]
        if missing:
            f = (np.arange(SPLIT + 1) / SPLIT)[None, :]
            m = np.array(missing)
            r = R_lo[m, None] + f * np.where(np.isfinite(R_hi[m]), R_hi[m] - R_lo[m], 0.0)[:, None]
            r[:, -1] = R_hi[m]
            t = T_lo[m, None] + f * (T_hi[m] - T_lo[m])[:, None]
            t[:, -1] = T_hi[m]  # the parts cover the cell exactly
            rl, tl = (a.reshape(len(m), -1) for a in np.broadcast_arrays(
                r[:, :-1, None], t[:, None, :-1]))
            rh, th = (a.reshape(len(m), -1) for a in np.broadcast_arrays(
                r[:, 1:, None], t[:, None, 1:]))
            # each split cell tries the kappa that was best on its coarse cell
            data = cells(rl.ravel(), rh.ravel(), tl.ravel(), th.ravel(),
                         np.repeat(coarse["kappa"][m], SPLIT * SPLIT))
            n = SPLIT * SPLIT
            for k, i in enumerate(missing):
                part = slice(k * n, (k + 1) * n)
                split[i] = {"v": data["v"][part], "pairs": [p[part] for p in data["pairs"]],
                            "c_plus": data["c_plus"][:, part],
                            "c_minus": data["c_minus"][:, part],
                            "kinetic": data["kinetic"][:, part]}
        parts = [split[int(i)] for i in index]
        return {"v": np.concatenate([p["v"] for p in parts]),
                "pairs": [np.concatenate([p["pairs"][g] for p in parts]) for g in range(3)],
                "c_plus": np.concatenate([p["c_plus"] for p in parts], axis=1),
                "c_minus": np.concatenate([p["c_minus"] for p in parts], axis=1),
                "kinetic": np.concatenate([p["kinetic"] for p in parts], axis=1)}

    paid = 1 if inertia.model == "af-is" else 0  # af-is: e j'(j'+1); is-af: e j(j+1)
    window = hbar**2 / (2 * inertia.M * scale**2)  # a kinetic energy of the basis scale

    def total(data: dict, j: int, jp: int) -> np.ndarray:
        """v + centrifugal + kinetic per trial and cell [trials, cells]."""
        spins = (j, jp) if paid else (jp, j)
        cent = haar3_centrifugal_min(*spins, data["pairs"], c0, e)
        if min(j, jp) <= 1 and cov.fixed_dimension(j, jp) <= MATRIX_RANK and data is not coarse:
            casimir = e * (jp * (jp + 1) if paid else j * (j + 1))
            cent = np.maximum(cent, haar3_centrifugal_matrix_min(
                j, jp, data["c_plus"], data["c_minus"], casimir))
        return data["v"] + cent + data["kinetic"]

    def bound(j: int, jp: int) -> float:
        tot = total(coarse, j, jp)
        done = np.zeros(tot.shape[1], bool)
        for _ in range(4):  # split the cells near the best trial's minimum, until it moves
            values = np.min(tot, axis=1)
            best = int(np.argmax(values))
            near = np.flatnonzero((tot[best] <= values[best] + window) & ~done)
            if not len(near):
                break
            fine = total(refined(near), j, jp).reshape(len(TRIALS), len(near), -1)
            tot[:, near] = np.maximum(tot[:, near], np.min(fine, axis=2))
            done[near] = True
        return float(_lowered(np.max(np.min(tot, axis=1))))
    pairs, v, kinetic = coarse["pairs"], coarse["v"], coarse["kinetic"]
    max_shell = max(max_shell, enumerate_to or 0)
    L = max_shell + 1
    # every sector beyond has j_free >= L or j_paid >= L: (j_free, 0) and (0, j_paid) exactly
    # (increasing in the spin), else the forms non-decreasing in both spins at (L, 1), (1, L)
    tail_cent = np.minimum.reduce([haar3_centrifugal_min(L, 0, pairs, c0, e),
                                   haar3_centrifugal_min(L, 1, pairs, c0, e, monotone=True),
                                   haar3_centrifugal_min(1, L, pairs, c0, e, monotone=True),
                                   haar3_centrifugal_min(0, L, pairs, c0, e)])
    tail = float(_lowered(np.max(np.min(v + tail_cent + kinetic, axis=1))))
    return _by_shell(bound, max_shell, tail,
                     "certified: dilatation oscillator and shear ground-state representation "
                     "bound the gradient form, centrifugal and Casimir terms pair by pair and "
                     "as the sector's matrix, "
                     "V bounded below by interval arithmetic on its expression over cells of "
                     "(r, t, sigma) (docs/theory/two-polar.md, 'Lower bounds of an n = 3 "
                     "sector')")


__all__ = ["MARGIN", "ShellBounds", "haar_strip_edges", "haar_strip_minima",
           "centrifugal_haar_min", "haar2_shell_bounds", "lebesgue2_shell_bounds",
           "lebesgue3_shell_bounds", "haar3_kinetic_min", "haar3_centrifugal_min",
           "MATRIX_RANK", "haar3_centrifugal_matrix_min",
           "haar3_shell_bounds"]
