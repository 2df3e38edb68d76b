"""Densities of the components G_ab of the Green tensor G = phi^T phi = R diag(Q^2) R^T of an
n = 3 state, superposition or thermal mixture (paper, last section; docs/theory/densities.md,
"Components of G (n = 3)").

Integrating |Psi|^2 over L (Schur orthogonality, as for the orientation of R in
quantum.orientations3) leaves, per unit of the Haar measure of R and of the reduced measure,

    rho(R, x) = Re sum_kl c_kl (v_k^T D^{j'_k}(R)) F_k(x)^T F_l(x) (D^{j'_l}(R)^T conj(v_l)),
    c_kl = conj(c_k) c_l sqrt(d_k d_l)/(2 j_k + 1) (u_l^H u_k)   (j_k = j_l),

and p(y) = int dR int mu(x) dx rho delta(G_aa - y). G_aa = sum_k u_k^2 P_k depends on R only
through its row a, the unit vector u, and on the chamber point through P = diag(Q^2).
Coordinates:

* the chamber point by a direction and a scale s, P = e^{s/kappa} P0: d'Alembert Q = e^s omega
  (omega on the chamber's part of the unit sphere, the rule of
  channels3.ChamberQuadrature.sphere with prod(Q_a^2 - Q_b^2) included, mu dQ = e^{9s} ds x
  its weight, kappa = 1/2); affine models q = qbar + (sigma/3)(1, 1, 1), s = sigma (qbar in
  the traceless plane, polar coordinates as channels3.haar3_grid, dq = r dr dt dsigma /
  sqrt 3, kappa = 3/2);
* R = S_a^T (R_3(phi) R_2(theta) R_3(psi))^T (S_a e_a = e_3), so u = (sin theta cos phi,
  sin theta sin phi, cos theta) in the body axes and g = u^T P0 u = P0_3 + (A - P0_3)
  sin^2 theta, A = P0_1 cos^2 phi + P0_2 sin^2 phi; the twist psi about u leaves G_aa alone
  and its mean of rho is exact (the magnetic components along the third axis decouple).

The delta fixes the scale, s* = kappa ln(y/g), with 1/|dG/ds| = kappa/|y|, and theta is
traded for t = s* itself (g = y e^{-t/kappa}; sin theta dtheta = g dt / (2 kappa
sqrt((A - P0_3)(A - g))), both theta and pi - theta), so the radial profile of the states is
integrated in its own variable; t = t_A + v^2 removes the square-root end point at g = A.
Gauss-Legendre in v and in the chamber coordinates, the trapezoid rule in phi; two rules of
increasing size are compared (``error``).

Off-diagonal G_ab = u^T P v (u, v rows a, b of R, :func:`offdiagonal_density`): the same scale
trick (G_ab = e^{s/kappa} g0, s* = kappa ln(y/g0) for g0 of y's sign, factor kappa/|y|), with
R^T = F(u) R_3(psi) S_a (u anywhere on the sphere, F(u) any rotation taking e_3 to u): g0 =
b cos(psi' - gamma) and the twist psi no longer drops out, but its two roots are summed
exactly, 2 e^{i dm (gamma - c_b)} T_|dm|(g0/b) for each difference dm = m - m' of magnetic
numbers (T the Chebyshev polynomials), so psi is traded for the scale (|dpsi| = |dg0| /
sqrt(b^2 - g0^2)). b(u) vanishes only on the axes u = +-e_k (b ~ distance, an integrable 1/b
at y = 0): the sphere rule (:func:`octant_sphere`) is Duffy-mapped to them and graded towards
them, which keeps the density finite and the rule convergent down to y = 0. The scale
integral depends on u only through b; it is tabulated per chamber direction on a grid in ln b
and interpolated to the sphere's nodes.

The integral of a density (:func:`g_densities3`; docs/theory/densities.md, "Components of G
(n = 3)", its paragraph "Integral") is the trapezoid rule in a variable xi in which p dy/dxi
is smooth: over the output points y = c sinh(xi) (off-diagonal), or over
:data:`INTEGRAL_NODES` nodes of its own y = c sinh^2(xi) from xi = 0 (diagonal: a d'Alembert
density is sqrt(y) x a smooth function of y), with an error estimate (:func:`_xi_integral`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.channels3 import ChamberQuadrature
from affinebody.quantum.densities import Marginal, projected_triangle
from affinebody.quantum.tensor_operators3 import wigner

#: (chamber nodes per coordinate, points in phi, Gauss nodes in v) of the two rules compared
RULES = ((10, 48, 24), (12, 64, 30))
#: the diagonal components
COMPONENTS = ("G11", "G22", "G33")
#: the off-diagonal components (:func:`offdiagonal_density`)
OFF_DIAGONAL = ("G12", "G13", "G23")
#: (chamber nodes per coordinate, sphere nodes per triangle side, table nodes in ln b, v nodes)
#: of the two rules compared for the off-diagonal components
OFF_RULES = ((8, 6, 64, 12), (10, 8, 96, 16))
#: the chamber nodes of the two rules for the affine models (whose chamber directions need more:
#: 8, 10, 12, 14 nodes change the af-is ground state's G12 density by 1e-2, 9e-4, 1.5e-4 x peak)
OFF_AFFINE_DIRECTIONS = (12, 14)
#: the off-diagonal scale integral is tabulated down to e^{-SPAN} x the largest b (below, b K
#: is held at its last value: the contribution of those nodes is O(e^{-SPAN}))
SPAN = 12.0
#: default tolerance (x the peak) of the off-diagonal densities: near y = 0 the integrand
#: gathers at the axes of the chamber's directions that are close to its walls, where the rules
#: converge slowly (about 1e-3 of the peak at y = 0 for an anisotropic state)
OFF_TOLERANCE = 2e-3
#: panels of the sphere rule towards each axis (distance 1, 1/10, ..., 10^-GRADES, 0)
GRADES = 2
#: default tolerance (x the peak) of the difference between the two rules (the integrand has
#: square-root end points on the walls of the chamber: the rules converge algebraically)
TOLERANCE = 1e-4
#: the mass beyond the largest output value of a diagonal component (the Tr G above which it
#: lies, :func:`support`: G_aa <= Tr G) and of an off-diagonal one ((P_max - P_min)/2 >= |G_ab|)
TAIL_TRG = 1e-10
TAIL_SPREAD = 1e-6
#: the nodes y = c sinh^2(xi) (xi uniform from 0) of the integral of a diagonal component
INTEGRAL_NODES = 12
_EU = np.array([1.0, -1.0, 0.0]) / math.sqrt(2)
_EV = np.array([1.0, 1.0, -2.0]) / math.sqrt(6)
#: rotations taking the body axis k to the third axis (S_k e_k = e_3), det 1
_TO_THIRD = (np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]),
             np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.eye(3))


@cache
def _eigen(j: int, g: int) -> tuple[np.ndarray, np.ndarray]:
    """(w, V) with exp(t K^j_g) = V diag(e^{-i w t}) V^H (covariants3 generators)."""
    return np.linalg.eigh(1j * cov.rotation_generators(j)[g])


def _exp(j: int, g: int, t: np.ndarray) -> np.ndarray:
    """exp(t K^j_g) [..., 2j + 1, 2j + 1] (real) at the angles t [...]."""
    w, V = _eigen(j, g)
    phase = np.exp(-1j * np.multiply.outer(t, w))  # [..., m]
    return ((V * phase[..., None, :]) @ V.conj().T).real


@cache
def _magnetic(j: int) -> tuple[np.ndarray, np.ndarray]:
    """(m, U): the eigenvalues m of i K_01 on V_j and their eigenvectors (columns)."""
    return _eigen(j, 0)


@dataclass(frozen=True)
class Pair:
    """The pairs (k, l) of a mixture sharing one pair of multiplet amplitudes, as the weights
    of the twist-averaged rotation factor: rho = Re sum_mm' ... (:func:`_rho`)."""

    amplitude_k: object
    amplitude_l: object
    jp_k: int
    jp_l: int
    vectors: tuple  # ((weight c_kl, v_k, v_l), ...)


def pairs(mixture, floor: float = 1e-3 * TOLERANCE) -> list[Pair]:
    """The :class:`Pair` s of a mixture [(probability, amplitudes c, [MultipletState])];
    members whose probability is below ``floor`` x the largest are left out."""
    found: dict = {}
    top = max(p for p, _, _ in mixture)
    for p, amplitudes, states in mixture:
        if p < floor * top:
            continue
        listed = list(zip(amplitudes, states, strict=True))
        for k, (ck, sk) in enumerate(listed):
            for cl, sl in listed[k:]:
                if sk.sector.spin != sl.sector.spin:
                    continue
                overlap = np.vdot(sl.u, sk.u)
                if abs(overlap) < 1e-14:
                    continue
                c = (p * np.conj(ck) * cl * math.sqrt(sk.sector.dimension * sl.sector.dimension)
                     / (2 * sk.sector.spin + 1) * overlap) * (1 if sk is sl else 2)
                key = (id(sk.F), id(sl.F))
                if key not in found:
                    found[key] = (sk, sl, [])
                found[key][2].append((c, sk.v, sl.v))
    return [Pair(sk.amplitude, sl.amplitude, sk.sector.vorticity, sl.sector.vorticity,
                 tuple(v)) for sk, sl, v in found.values()]


def weight_matrix(pair: Pair, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(W, m_k, m_l): W[m, m'] = sum c alpha_k,m conj(alpha_l,m') over the pair's vectors,
    alpha = v^T D(S_a^T) U (U: the magnetic eigenvectors along the third axis), so that
    v_k^T D(R) = sum_m alpha_k,m e^{i m psi} (row m after the twist psi of R = S_a^T
    (... R_3(psi))^T), and the magnetic numbers of the two sides."""
    mk, Uk = _magnetic(pair.jp_k)
    ml, Ul = _magnetic(pair.jp_l)
    Sk = wigner(pair.jp_k, _TO_THIRD[axis].T)  # D(S_a^T)
    Sl = wigner(pair.jp_l, _TO_THIRD[axis].T)
    W = np.zeros((len(mk), len(ml)), complex)
    for c, vk, vl in pair.vectors:
        W += c * np.outer(vk @ Sk @ Uk, np.conj(vl @ Sl @ Ul))
    return W, np.round(mk).astype(int), np.round(ml).astype(int)


def _twist_weights(pair: Pair, axis: int) -> dict[int, complex]:
    """W[m] for the common magnetic numbers m of the two sides (the twist average keeps equal
    m): the diagonal of :func:`weight_matrix`."""
    W, mk, ml = weight_matrix(pair, axis)
    return {int(m): W[i, j] for i, m in enumerate(mk) for j in np.flatnonzero(ml == m)}


def _rows(j: int, theta: np.ndarray, phi: np.ndarray) -> dict[int, np.ndarray]:
    """m -> the row <m| U^H D(R_2(theta))^T D(R_3(phi))^T [N, phi, V, 2j + 1] (the factor after
    the twist of R = S_a^T (R_3(phi) R_2(theta) R_3(psi))^T in a = v^T D(R)); theta
    [N, phi, V], phi [phi]."""
    m, U = _magnetic(j)
    # R_2(theta) = exp(theta [e_2]_x) = exp(-theta K_02); R_3(phi) = exp(phi K_01)
    left = U.conj().T @ _exp(j, 1, theta)  # U^H D(R_2(-theta)) [N, phi, V, m, c]
    rows = left @ _exp(j, 0, -phi)[None, :, None]  # ... D(R_3(-phi))
    return {int(round(mm)): rows[..., i, :] for i, mm in enumerate(m)}


def _amplitudes(pair_list, x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(F_k, F_l) per pair] at the reduced coordinates x [..., 3], each amplitude evaluated
    once."""
    flat = x.reshape(-1, 3)
    F, cache = [], {}
    for pair in pair_list:
        for amplitude in (pair.amplitude_k, pair.amplitude_l):
            if id(amplitude) not in cache:
                values = np.asarray(amplitude(flat))
                cache[id(amplitude)] = values.reshape(*x.shape[:-1], *values.shape[1:])
        F.append((cache[id(pair.amplitude_k)], cache[id(pair.amplitude_l)]))
    return F


def _rho(pair_list, weights, F, theta, phi) -> np.ndarray:
    """The twist-averaged rho at the nodes [...]: F [(F_k, F_l) per pair] at the chamber
    points, theta, phi the orientation of u."""
    out = 0.0
    for pair, W, (Fk, Fl) in zip(pair_list, weights, F, strict=True):
        M = np.swapaxes(Fk, -1, -2) @ Fl
        rk = _rows(pair.jp_k, theta, phi)
        rl = rk if pair.jp_l == pair.jp_k else _rows(pair.jp_l, theta, phi)
        for m, w in W.items():
            left = (rk[m][..., None, :] @ M)[..., 0, :]
            out = out + (w * np.sum(left * rl[m].conj(), -1)).real
    return out


@dataclass(frozen=True)
class Directions:
    """Chamber directions: reduced coordinates at scale 0 ``x0`` [N, 3], weights (measure and
    Jacobian included), squared singular values at scale 0 ``P0`` [N, 3], kappa (G scales as
    e^{s/kappa}) and the scale's own weight e^{power s}."""

    model: str
    x0: np.ndarray
    weights: np.ndarray
    P0: np.ndarray
    kappa: float
    power: float

    def at(self, s: np.ndarray) -> np.ndarray:
        """Reduced coordinates [..., N, 3] of every direction at the scales s [...]."""
        if self.model == "lebesgue3":
            return self.x0 * np.exp(s)[..., None, None]
        return self.x0 + (s / 3)[..., None, None]

    def at_nodes(self, s: np.ndarray) -> np.ndarray:
        """Reduced coordinates [N, ..., 3] of direction i at the scales s[i, ...]."""
        x0 = self.x0.reshape(len(self.x0), *([1] * (s.ndim - 1)), 3)
        if self.model == "lebesgue3":
            return x0 * np.exp(s)[..., None]
        return x0 + (s / 3)[..., None]


def directions(model: str, n: int, r_max: float) -> Directions:
    """The direction rule of ``model`` with n nodes per coordinate (module docstring)."""
    if model == "lebesgue3":
        omega, w = ChamberQuadrature.sphere(n)
        return Directions(model, omega, w, omega**2, 0.5, 9.0)
    xr, wr = np.polynomial.legendre.leggauss(n)
    r, w_r = r_max * (xr + 1) / 2, r_max * wr / 2
    t, w_t = np.pi / 6 + (np.pi / 3) * (xr + 1) / 2, (np.pi / 3) * wr / 2
    R, T = np.meshgrid(r, t, indexing="ij")
    q = (R[..., None] * (np.cos(T)[..., None] * _EU + np.sin(T)[..., None] * _EV)).reshape(-1, 3)
    J = np.sinh(q[:, 0] - q[:, 1]) * np.sinh(q[:, 0] - q[:, 2]) * np.sinh(q[:, 1] - q[:, 2])
    w = (w_r[:, None] * r[:, None] * w_t[None, :]).ravel() / math.sqrt(3) * J
    return Directions(model, q, w, np.exp(2 * q), 1.5, 0.0)


def support(model: str, pair_list
            ) -> tuple[float, float, float, float, float, float, float]:
    """(s_lo, s_hi, r_max, trg, spread, median, diagonal): the scale range (and, affine, the
    traceless radius) outside which the mixture has less than 1e-14 of its largest density, the
    Tr G below which all but :data:`TAIL_TRG` of its mass lies (so G_aa <= Tr G beyond it holds
    less still), the (P_max - P_min)/2 (>= |G_ab|, a != b) below which all but
    :data:`TAIL_SPREAD` lies (a bound, so the tail of G_ab beyond it holds less still), its
    median and the median of Tr G / 3 (the scale of the diagonal components), from a coarse scan
    of |Psi|^2 (the scale grid's mass summed over the directions)."""
    if model == "lebesgue3":
        dirs, s = directions(model, 6, 1.0), np.linspace(-8.0, 4.0, 241)
    else:
        dirs, s = directions(model, 8, 12.0), np.linspace(-40.0, 40.0, 321)
    x = dirs.at(s)  # [S, N, 3]
    flat = x.reshape(-1, 3)
    mass = np.zeros(len(flat))
    for pair in pair_list:
        mass += np.sum(np.asarray(pair.amplitude_k(flat)) ** 2, axis=(1, 2))
    mass = mass.reshape(x.shape[:-1]) * np.exp(dirs.power * s)[:, None] * np.abs(dirs.weights)
    keep = mass > 1e-14 * mass.max()
    along = np.flatnonzero(keep.any(1))
    lo, hi = s[max(along[0] - 1, 0)], s[min(along[-1] + 1, len(s) - 1)]
    r_max = 1.0
    if model != "lebesgue3":
        radius = np.linalg.norm(dirs.x0, axis=-1)
        r_max = float(min(radius[keep.any(0)].max() * 1.25 + 0.5, 12.0))
    tops = []
    spread = (dirs.P0.max(-1) - dirs.P0.min(-1)) / 2
    trg = np.sum(dirs.P0, -1)
    for g, level in ((trg, 1 - TAIL_TRG), (spread, 1 - TAIL_SPREAD), (spread, 0.5),
                     (trg / 3, 0.5)):
        value = (np.exp(s / dirs.kappa)[:, None] * g[None, :]).ravel()
        order = np.argsort(value)
        below = np.cumsum(mass.ravel()[order]) / mass.sum()
        tops.append(float(value[order][min(np.searchsorted(below, level), len(order) - 1)]))
    return float(lo), float(hi), r_max, *tops


def diagonal_density(pair_list, model: str, axis: int, y: np.ndarray, rule: tuple,
                     bounds: tuple) -> np.ndarray:
    """The density of G_aa (a = ``axis``) at y > 0 with the rule (chamber nodes, phi points, v
    nodes) (module docstring)."""
    n_dir, n_phi, n_v = rule
    lo, hi, r_max = bounds[:3]
    dirs = directions(model, n_dir, r_max)
    W = [_twist_weights(pair, axis) for pair in pair_list]
    phi = 2 * np.pi * np.arange(n_phi) / n_phi
    xv, wv = np.polynomial.legendre.leggauss(n_v)
    kappa = dirs.kappa
    out = np.zeros(len(y))
    for n, value in enumerate(np.asarray(y, float)):
        P0 = dirs.P0[:, None, :]  # [N, 1, 3]
        A = P0[..., 0] * np.cos(phi) ** 2 + P0[..., 1] * np.sin(phi) ** 2  # [N, phi]
        P3 = np.broadcast_to(P0[..., 2], A.shape)
        t_A = kappa * np.log(value / A)
        with np.errstate(divide="ignore"):
            t_3 = kappa * np.log(value / np.maximum(P3, 1e-300))
        start = np.maximum(t_A, lo)
        end = np.minimum(t_3, hi)
        ok = end > start
        v0 = np.sqrt(np.where(ok, start - t_A, 0.0))
        v1 = np.sqrt(np.where(ok, end - t_A, 0.0))
        v = v0[..., None] + (v1 - v0)[..., None] * (xv + 1) / 2  # [N, phi, V]
        wvv = (v1 - v0)[..., None] * wv / 2
        t = t_A[..., None] + v * v
        g = value * np.exp(-t / kappa)
        gap = np.maximum(A[..., None] - g, 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            jac = np.where(gap > 0, g * 2 * v / (2 * kappa * np.sqrt(
                (A - P3)[..., None] * gap)), 0.0)
        sin2 = np.clip((g - P3[..., None]) / np.where(A > P3, A - P3, 1.0)[..., None], 0, 1)
        theta = np.arcsin(np.sqrt(sin2))
        F = _amplitudes(pair_list, dirs.at_nodes(t))
        rho = _rho(pair_list, W, F, theta, phi) + _rho(pair_list, W, F, np.pi - theta, phi)
        integrand = rho * jac * np.exp(dirs.power * t) * wvv * ok[..., None]
        out[n] = np.einsum("i,ipv->", dirs.weights, integrand) / (2 * n_phi)
    return out * kappa / np.abs(y)


@cache
def octant_sphere(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u [P, 3], weights [P] summing to 1, frames F [P, 3, 3] with F e_3 = u): a rule on the
    unit sphere whose nodes crowd towards the six axes +-e_k. Each octant is the central
    projection of its flat triangle, cut into six triangles (a corner e_k, the midpoint of an
    edge through it, the centroid), each Duffy-mapped with the corner as the collapsed side
    (densities.projected_triangle), so a 1/|u - e_k| integrand is smooth in the rule's
    coordinates; n Gauss-Legendre nodes across and, towards the corner, in rho = 1 - s on the
    panels [1/10, 1] (n nodes), [1/100, 1/10], ..., [0, 10^-GRADES] (n/2 nodes each), which
    resolve the feature of size ~|y| that b K(b) has near the axes at small |y|."""
    x, w = np.polynomial.legendre.leggauss(n)
    x, w = (x + 1) / 2, w / 2
    edges = np.concatenate([10.0 ** -np.arange(GRADES + 1), [0.0]])  # rho = 1 - s panels
    xs, ws = np.polynomial.legendre.leggauss(max(2, n // 2))  # the small panels
    xs, ws = (xs + 1) / 2, ws / 2
    panels = [(x, w) if i == 0 else (xs, ws) for i in range(GRADES + 1)]
    rho = np.concatenate([hi + (lo - hi) * xp for (xp, _), hi, lo in
                          zip(panels, edges[:-1], edges[1:], strict=True)])
    w_rho = np.concatenate([(hi - lo) * wp for (_, wp), hi, lo in
                            zip(panels, edges[:-1], edges[1:], strict=True)])
    S, T = np.meshgrid(1 - rho, x, indexing="ij")
    weights = np.outer(w_rho, w)
    eye, centre = np.eye(3), np.full(3, 1 / 3)
    nodes, rule = [], []
    for k in range(3):
        for j in range(3):
            if j != k:
                vertices = np.array([eye[k], (eye[k] + eye[j]) / 2, centre])
                u, dom = projected_triangle(S, T, vertices, abs(np.linalg.det(vertices)))
                nodes.append(u.reshape(-1, 3))
                rule.append((weights * dom).ravel())
    u, w = np.concatenate(nodes), np.concatenate(rule)
    signs = np.array([[a, b, c] for a in (1, -1) for b in (1, -1) for c in (1, -1)], float)
    u = (signs[:, None, :] * u[None]).reshape(-1, 3)
    w = np.tile(w, len(signs))
    helper = np.eye(3)[np.argmin(np.abs(u), axis=1)]
    e1 = np.cross(helper, u)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return u, w / w.sum(), np.stack([e1, np.cross(u, e1), u], -1)


def _scale_nodes(dirs: Directions, value: float, b: np.ndarray, bounds: tuple, xv, wv):
    """(t, g0/b, weight) [..., V] for |G_ab| = y: the scale t = s* of the chamber point along
    each branch of the twist, g0 = y e^{-t/kappa}, and the weight dt / sqrt(b^2 - g0^2) x the
    Gauss weight (zero where the range is empty), at the amplitudes b [...] of g0 over the
    twist. d'Alembert: z = e^{t/kappa} (the scale of G) = z_b + v^2 from z_b = |y|/b, so
    dt / sqrt(b^2 - g0^2) = 2 kappa dv / (b sqrt(z + z_b)) (the square-root end point removed,
    and z itself the variable when z_b -> 0: the profile is a polynomial in |Q| times a
    Gaussian); affine models: t = t_b + v^2 (t_b = kappa ln(|y|/b)) within the support."""
    lo, hi = bounds[:2]
    kappa = dirs.kappa
    b = np.maximum(b, 1e-300)[..., None]
    sign = 1.0 if value >= 0 else -1.0
    if dirs.model == "lebesgue3":
        z_b = abs(value) / b
        z_hi = math.exp(hi / kappa)
        v1 = np.sqrt(np.maximum(z_hi - z_b, 0.0))
        v = v1 * (xv + 1) / 2
        z = z_b + v * v
        with np.errstate(divide="ignore"):
            t = kappa * np.log(z)
        return t, sign * z_b / z, 2 * kappa * v1 * wv / 2 / (b * np.sqrt(z + z_b))
    if value == 0:
        t = np.broadcast_to(lo + (hi - lo) * (xv + 1) / 2, b.shape[:-1] + xv.shape)
        return t, np.zeros_like(t), (hi - lo) * wv / 2 / b
    t_b = kappa * np.log(abs(value) / b)
    start = np.maximum(t_b, lo)
    ok = hi > start
    v0 = np.sqrt(np.where(ok, start - t_b, 0.0))
    v1 = np.sqrt(np.where(ok, hi - t_b, 0.0))
    v = v0 + (v1 - v0) * (xv + 1) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = np.where(ok, (v1 - v0) * wv / 2 * 2 * v / (
            b * np.sqrt(-np.expm1(-2 * v * v / kappa))), 0.0)
    return t_b + v * v, sign * np.exp(-v * v / kappa), weight


def offdiagonal_density(pair_list, model: str, axes: tuple[int, int], y: np.ndarray,
                        rule: tuple, bounds: tuple) -> np.ndarray:
    """The density of G_ab (a, b = ``axes``, a != b) at the values y with the rule (chamber
    nodes, sphere nodes per triangle side, table nodes in ln b, v nodes) (module docstring).

    R^T = F(u) R_3(psi) S_a with S_a e_a = e_3 and F(u) e_3 = u (:func:`octant_sphere`), so
    u = R^T e_a, v = R^T e_b = cos psi' e1(u) + sin psi' e2(u) (psi' = psi + c_b) and
    g0 = u^T P0 v = b cos(psi' - gamma), b e^{i gamma} = u^T P0 (e1 + i e2). The two roots
    psi' = gamma +- arccos(g0/b) of G_ab = y give sum e^{i dm psi} = 2 e^{i dm (gamma - c_b)}
    T_|dm|(g0/b) for the magnetic numbers dm = m - m' of the rotation factor. The scale
    integral depends on u only through b: per chamber direction it is tabulated as b K_dm(b)
    on a uniform grid in ln b (from the b below which G_ab = y is out of reach, at most
    :data:`SPAN` below the largest b, (P0_max - P0_min)/2) and interpolated (cubic) to the
    sphere's nodes."""
    a, b_axis = axes
    n_dir, n_sphere, n_b, n_v = rule
    dirs = directions(model, n_dir, bounds[2])
    e = _TO_THIRD[a] @ np.eye(3)[b_axis]
    c_b = math.atan2(e[1], e[0])
    u, wu, frames = octant_sphere(n_sphere)
    xv, wv = np.polynomial.legendre.leggauss(n_v)
    H = []  # per pair: (dm values, sum over m - m' = dm of W row_k (x) conj(row_l)) [P, dm, d, e]
    for pair in pair_list:
        W, mk, ml = weight_matrix(pair, a)
        rows = {j: _magnetic(j)[1].conj().T @ wigner(j, np.swapaxes(frames, -1, -2))
                for j in {pair.jp_k, pair.jp_l}}
        dm = np.subtract.outer(mk, ml)
        deltas = np.unique(dm)
        Wd = np.stack([np.where(dm == d, W * np.exp(-1j * d * c_b), 0) for d in deltas])
        H.append((deltas, np.einsum("Dmn,pmd,pne->pDde", Wd, rows[pair.jp_k],
                                    rows[pair.jp_l].conj())))
    P0u = dirs.P0[:, None, :] * u  # [N, P, 3]
    zc = np.sum(P0u * frames[..., 0], -1) + 1j * np.sum(P0u * frames[..., 1], -1)
    b = np.maximum(np.abs(zc), 1e-300)
    gamma, log_b = np.angle(zc), np.log(b)
    measure = wu / b * dirs.weights[:, None]  # [N, P]
    top = np.log((dirs.P0.max(1) - dirs.P0.min(1)) / 2)
    z_hi = math.exp(bounds[1] / dirs.kappa)
    out = np.zeros(len(y))
    for n, value in enumerate(np.asarray(y, float)):
        bottom = top - SPAN if value == 0 else np.maximum(math.log(abs(value) / z_hi), top - SPAN)
        live = bottom < top
        bottom = np.where(live, bottom, top - 1)
        step = (top - bottom) / (n_b - 1)
        grid = bottom[:, None] + step[:, None] * np.arange(n_b)  # [N, B]
        t, ratio, weight = _scale_nodes(dirs, value, np.exp(grid), bounds, xv, wv)
        weight = weight * np.exp((dirs.power - 1 / dirs.kappa) * t + grid[..., None]) \
            * live[:, None, None]
        turn = np.arccos(np.clip(ratio, -1.0, 1.0))
        q = np.clip((log_b - bottom[:, None]) / step[:, None], 0, n_b - 1)  # [N, P]
        i0 = np.clip(np.floor(q).astype(int) - 1, 0, n_b - 4)
        f = q - i0
        lagrange = np.stack([-(f - 1) * (f - 2) * (f - 3) / 6, f * (f - 2) * (f - 3) / 2,
                             -f * (f - 1) * (f - 3) / 2, f * (f - 1) * (f - 2) / 6], -1)
        for (deltas, h), (Fk, Fl) in zip(H, _amplitudes(pair_list, dirs.at_nodes(t)),
                                         strict=True):
            M = np.swapaxes(Fk, -1, -2) @ Fl  # [N, B, V, d, e], real (real amplitudes)
            K = np.einsum("nbv,nbvD,nbvde->nbDde", weight,
                          2 * np.cos(np.abs(deltas) * turn[..., None]), M)
            K = K.reshape(len(K), n_b, -1)
            hr, hi = (part.reshape(len(u), len(deltas), -1) for part in (h.real, h.imag))
            for i in np.flatnonzero(live):  # b K at the sphere's b [P, dm, d e]
                Kp = np.einsum("pj,pjx->px", lagrange[i], K[i][i0[i, :, None] + np.arange(4)])
                Kp = Kp.reshape(hr.shape)
                phase = deltas * gamma[i, :, None]
                G = np.cos(phase) * np.einsum("pDx,pDx->pD", hr, Kp) \
                    - np.sin(phase) * np.einsum("pDx,pDx->pD", hi, Kp)
                out[n] += measure[i] @ np.sum(G, -1)
    return out / (2 * np.pi)


def component_axes(name: str) -> tuple[int, int]:
    """(a, b), 0-based, of a component name G11 .. G23 (:data:`COMPONENTS`,
    :data:`OFF_DIAGONAL`)."""
    if name not in COMPONENTS + OFF_DIAGONAL:
        raise ValueError(f"n = 3: densities of {name} are not computed (the components "
                         f"{', '.join(COMPONENTS + OFF_DIAGONAL)})")
    return int(name[1]) - 1, int(name[2]) - 1


def _xi_integral(f: np.ndarray, change: np.ndarray, h: float, tail: float
                 ) -> tuple[float, float]:
    """(I, error) of int f dxi over uniform nodes of step h (f = p dy/dxi at the nodes, the
    first and last the ends of the range): I the trapezoid rule T_h and error
    = |T_h - T_2h| (T_2h the rule of step 2h on the even-numbered nodes, up to the last of
    them) + sum_k w_k |change_k| (w the trapezoid weights, ``change`` the difference of the two
    density rules times dy/dxi: the density's own quadrature error) + ``tail`` (the mass beyond
    the grid). T_h converges at least as fast as T_2h, so |T_h - T_2h| bounds its error once
    the rules resolve the density (docs/theory/densities.md, "Components of G (n = 3)", its
    paragraph "Integral")."""
    w = np.full(len(f), h)
    w[[0, -1]] = h / 2
    even = f[::2]
    w2 = np.full(len(even), 2 * h)
    w2[[0, -1]] = h
    integral = float(w @ f)
    return integral, abs(integral - float(w2 @ even)) + float(w @ np.abs(change)) + tail


def g_densities3(spectrum, mixture, points: int = 51, tolerance: float = TOLERANCE,
                 components=COMPONENTS, off_tolerance: float = OFF_TOLERANCE
                 ) -> dict[str, Marginal]:
    """Densities of the ``components`` of G for a mixture [(probability, amplitudes,
    [MultipletState])] (quantum.orientations3) of an n = 3 spectrum, each with the difference
    between the two rules of :data:`RULES` (diagonal) or :data:`OFF_RULES` (off-diagonal) as
    its error, flagged unconverged above ``tolerance`` (``off_tolerance`` for the
    off-diagonal ones) x the peak. Diagonal: ``points`` values in (0, max Tr G]; off-diagonal:
    ``points`` values y = c sinh(xi) in [-m, m] (xi uniform, m = max (P_max - P_min)/2, c its
    median: :func:`support`). ``integral``: the trapezoid rule in xi, with ``integral_error``
    (:func:`_xi_integral`: the difference from the rule on every other node, the density's own
    error and the mass beyond the nodes, :data:`TAIL_TRG`, :data:`TAIL_SPREAD`); off-diagonal
    over the output points, diagonal over :data:`INTEGRAL_NODES` nodes of its own,
    y = c sinh^2(xi) with xi uniform from 0 to the largest value (c the median of Tr G / 3:
    y ~ c xi^2 at 0, where a d'Alembert density is sqrt(y) x a smooth function of y, so
    p dy/dxi is smooth, even in xi and 0 at xi = 0; y ~ e^{2 xi} in the tail), as the output
    points start too far from 0 to resolve the density there."""
    if points < 3:
        raise ValueError(f"n = 3 G densities need at least 3 points (got {points}): the "
                         f"integral's error compares the rule on every other point")
    model = "lebesgue3" if spectrum.model == "dalembert" else "haar3"
    pair_list = pairs(mixture)
    bounds = support(model, pair_list)
    out = {}
    for name in components:
        a, b = component_axes(name)
        if a == b:
            y = np.linspace(0.0, bounds[3], points + 1)[1:]
            # the integral's own nodes y = c sinh^2(xi), xi uniform from 0 (module docstring)
            c = bounds[6]
            xi = math.asinh(math.sqrt(bounds[3] / c)) * np.arange(INTEGRAL_NODES + 1) \
                / INTEGRAL_NODES
            jacobian = c * np.sinh(2 * xi)  # dy/dxi, 0 at xi = 0 (where no node is needed)
            first, second = (diagonal_density(pair_list, model, a, np.concatenate(
                [y, c * np.sinh(xi[1:]) ** 2]), rule, bounds) for rule in RULES)
            f, change = (np.concatenate([[0.0], v[points:] * jacobian[1:]])
                         for v in (second, second - first))
            first, second = first[:points], second[:points]
            limit, nodes, tail = tolerance, RULES[-1][2], TAIL_TRG
        else:
            # y = c sinh(xi), xi uniform and symmetric (y = 0 exactly for an odd count), c the
            # median bound: points gather at the peak and still reach the tails
            c = bounds[5]
            xi = math.asinh(bounds[4] / c) * (2 * np.arange(points) - points + 1) / (points - 1)
            y, jacobian = c * np.sinh(xi), c * np.cosh(xi)
            rules = OFF_RULES if model == "lebesgue3" else tuple(
                (n, *rule[1:]) for n, rule in zip(OFF_AFFINE_DIRECTIONS, OFF_RULES, strict=True))
            first, second = (offdiagonal_density(pair_list, model, (a, b), y, rule, bounds)
                             for rule in rules)
            f, change = second * jacobian, (second - first) * jacobian
            limit, nodes, tail = off_tolerance, rules[-1][3], TAIL_SPREAD
        err = float(np.max(np.abs(second - first)))
        integral, integral_error = _xi_integral(f, change, float(xi[1] - xi[0]), tail)
        out[name] = Marginal(y, second, err, integral, nodes,
                             bool(err <= limit * np.max(np.abs(second))), integral_error)
    return out


__all__ = ["RULES", "COMPONENTS", "TOLERANCE", "OFF_DIAGONAL", "OFF_RULES",
           "OFF_AFFINE_DIRECTIONS", "OFF_TOLERANCE", "SPAN", "GRADES", "TAIL_TRG",
           "TAIL_SPREAD", "INTEGRAL_NODES", "Pair", "pairs",
           "weight_matrix", "Directions", "directions", "support", "diagonal_density",
           "octant_sphere", "offdiagonal_density", "component_axes", "g_densities3"]
