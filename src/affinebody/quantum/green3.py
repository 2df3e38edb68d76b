"""Densities of the diagonal components G_aa of the Green tensor G = phi^T phi = R diag(Q^2) R^T
of an n = 3 state, superposition or thermal mixture (paper, last section; docs/theory/
densities.md, "Components of G (n = 3)").

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.channels3 import ChamberQuadrature
from affinebody.quantum.densities import Marginal
from affinebody.quantum.tensor_operators3 import wigner

#: (chamber nodes per coordinate, points in phi, Gauss nodes in v) of the two rules compared
RULES = ((10, 48, 24), (12, 64, 30))
#: the components reported
COMPONENTS = ("G11", "G22", "G33")
#: default tolerance (x the peak) of the difference between the two rules (the integrand has
#: square-root end points on the walls of the chamber: the rules converge algebraically)
TOLERANCE = 1e-4
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


def _twist_weights(pair: Pair, axis: int) -> np.ndarray:
    """W[m] for the common magnetic numbers m of the two sides: sum c alpha_k,m conj(alpha_l,m),
    alpha = v^T D(S_a^T) U (the twist average keeps equal m)."""
    mk, Uk = _magnetic(pair.jp_k)
    ml, Ul = _magnetic(pair.jp_l)

    Sk = wigner(pair.jp_k, _TO_THIRD[axis].T)  # D(S_a^T)
    Sl = wigner(pair.jp_l, _TO_THIRD[axis].T)
    out = {}
    for c, vk, vl in pair.vectors:
        ak, al = vk @ Sk @ Uk, vl @ Sl @ Ul
        for i, m in enumerate(np.round(mk).astype(int)):
            jl = np.flatnonzero(np.round(ml).astype(int) == m)
            if len(jl):
                out[m] = out.get(m, 0.0) + c * ak[i] * np.conj(al[jl[0]])
    return out


def _rows(j: int, theta: np.ndarray, phi: np.ndarray) -> dict[int, np.ndarray]:
    """m -> the row <m| U^H D(R_2(theta))^T D(R_3(phi))^T [N, phi, V, 2j + 1] (the factor after
    the twist of R = S_a^T (R_3(phi) R_2(theta) R_3(psi))^T in a = v^T D(R)); theta
    [N, phi, V], phi [phi]."""
    m, U = _magnetic(j)
    # R_2(theta) = exp(theta [e_2]_x) = exp(-theta K_02); R_3(phi) = exp(phi K_01)
    left = U.conj().T @ _exp(j, 1, theta)  # U^H D(R_2(-theta)) [N, phi, V, m, c]
    rows = left @ _exp(j, 0, -phi)[None, :, None]  # ... D(R_3(-phi))
    return {int(round(mm)): rows[..., i, :] for i, mm in enumerate(m)}


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


def support(model: str, pair_list) -> tuple[float, float, float, float]:
    """(s_lo, s_hi, r_max, trg): the scale range (and, affine, the traceless radius) outside
    which the mixture has less than 1e-14 of its largest density, and the Tr G below which
    all but 1e-10 of its mass lies, from a coarse scan of |Psi|^2 (the scale grid's mass
    summed over the directions)."""
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
    trg = (np.exp(s / dirs.kappa)[:, None] * np.sum(dirs.P0, -1)[None, :]).ravel()
    order = np.argsort(trg)
    below = np.cumsum(mass.ravel()[order]) / mass.sum()
    top = float(trg[order][min(np.searchsorted(below, 1 - 1e-10), len(order) - 1)])
    return float(lo), float(hi), r_max, top


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
        x = dirs.at_nodes(t)
        flat = x.reshape(-1, 3)
        F, cache = [], {}
        for pair in pair_list:
            for amplitude in (pair.amplitude_k, pair.amplitude_l):
                if id(amplitude) not in cache:
                    values = np.asarray(amplitude(flat))
                    cache[id(amplitude)] = values.reshape(*x.shape[:-1], *values.shape[1:])
            F.append((cache[id(pair.amplitude_k)], cache[id(pair.amplitude_l)]))
        rho = _rho(pair_list, W, F, theta, phi) + _rho(pair_list, W, F, np.pi - theta, phi)
        integrand = rho * jac * np.exp(dirs.power * t) * wvv * ok[..., None]
        out[n] = np.einsum("i,ipv->", dirs.weights, integrand) / (2 * n_phi)
    return out * kappa / np.abs(y)


def g_densities3(spectrum, mixture, points: int = 51, tolerance: float = TOLERANCE,
                 components=COMPONENTS) -> dict[str, Marginal]:
    """Densities of the diagonal ``components`` of G for a mixture [(probability,
    amplitudes, [MultipletState])] (quantum.orientations3) of an n = 3 spectrum on
    ``points`` values in (0, max Tr G], each with the difference between the two rules of
    :data:`RULES` as its error; ``integral``: by the trapezoid rule over the points (from
    y = 0, where the density vanishes)."""
    model = "lebesgue3" if spectrum.model == "dalembert" else "haar3"
    pair_list = pairs(mixture)
    bounds = support(model, pair_list)
    y = np.linspace(0.0, bounds[3], points + 1)[1:]
    out = {}
    for name in components:
        if name not in COMPONENTS:
            raise ValueError(f"n = 3: densities of {name} are not computed (only the diagonal "
                             f"components {', '.join(COMPONENTS)})")
        axis = int(name[1]) - 1
        first, second = (diagonal_density(pair_list, model, axis, y, rule, bounds)
                         for rule in RULES)
        err = float(np.max(np.abs(second - first)))
        integral = float(np.sum((second[1:] + second[:-1]) * np.diff(y)) / 2
                         + y[0] * second[0] / 2)
        out[name] = Marginal(y, second, err, integral, RULES[-1][2],
                             bool(err <= tolerance * np.max(np.abs(second))))
    return out


__all__ = ["RULES", "COMPONENTS", "TOLERANCE", "Pair", "pairs", "Directions", "directions",
           "support", "diagonal_density", "g_densities3"]
