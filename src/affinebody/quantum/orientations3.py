"""Orientation densities of one n = 3 state: the rotation factors L and R of phi = L D R^T
(paper, last section: "probability distributions for ... orientations of the main axes";
docs/theory/densities.md, "Orientations").

A state of the multiplet (j, j') is psi_c = sqrt(d) c^H (D^j(L) (x) D^j'(R)) F(Q), d =
(2j + 1)(2j' + 1), F = Psi(diag Q) in V_j (x) V_j' (quantum.transitions.sector_amplitudes, the
harmonic bases of quantum.covariants3) and c a unit vector. The states of a level are numbered
by the magnetic numbers along the third axis, c = |j m> (x) |j' m'> with m = j, ..., -j (the
outer index) and m' = j', ..., -j' (i K |j m> = m |j m>, K = rotation_generators(j)[0] of
covariants3, the generator of rotations in the plane of the first two axes). Integrating
|psi_c|^2 over R (Schur orthogonality of D^j') and over the reduced variables with their
measure leaves, per unit of the Haar measure of SO(3),

    p_L(L) = (2j + 1) <j m| D^j(L) Phi_L D^j(L)^T |j m>,   Phi_L = int F F^T mu dQ,
    p_R(R) = (2j' + 1) <j' m'| D^j'(R) Phi_R D^j'(R)^T |j' m'>,   Phi_R = int F^T F mu dQ

(trace Phi = 1: the state's normalisation). Phi_L is the distribution of the body-frame
components of the state among the magnetic numbers; where it is diagonal with weights w_k,
p_L = (2j + 1) sum_k w_k |D^j_{mk}(L)|^2: the |D^j|^2 pattern of the sector. Summed over the
2j + 1 values of m, p_L = (2j + 1) trace Phi_L: every multiplet summed over its states is
Haar-distributed.

Reported marginals (each a trigonometric polynomial, integrated exactly by the rules below):

* the rotation angle omega in [0, pi] of L (and of R): (1 - cos omega)/pi x the mean of p over
  the rotation axes (Gauss-Legendre in cos theta x trapezoid in the azimuth, exact for the
  degree 4j of p in the axis);
* the direction of each principal axis, the column k of L (axes of the Cauchy tensor C, in
  space) and of R (axes of the Green tensor G, in the body), as the density of its cosine t
  with the third axis on [-1, 1] (the azimuth is uniform: p_L is invariant under
  L -> R_3(gamma) L): (2j + 1)/2 sum_mu |d^j_{m mu}(theta)|^2 Y_mu (:func:`axis_density`),
  even in t (the sign matrices M fix diag Q: p is invariant under (L, R) -> (L M, R M),
  which reverses two axes).
"""

from __future__ import annotations

import numpy as np

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.densities import state_components
from affinebody.quantum.levels import Spectrum
from affinebody.quantum.tensor_operators3 import wigner
from affinebody.quantum.transitions import (
    level_components,
    reduced_quadrature,
    sector_amplitudes,
)

#: output points of the densities of the rotation angle and of the axis cosines
POINTS = 181
#: the state's amplitude must be normalised under the reduced quadrature to this
NORMALISATION = 1e-8


def magnetic_states(j: int) -> np.ndarray:
    """Columns |j m>, m = j, ..., -j [2j + 1, 2j + 1] (complex, in the real harmonic basis):
    the eigenvectors of i K_01 (rotations about the third axis) with eigenvalue m (each
    up to a phase, which no density depends on)."""
    w, v = np.linalg.eigh(1j * cov.rotation_generators(j)[0])
    order = np.argsort(-w)
    if np.max(np.abs(w[order] - np.arange(j, -j - 1, -1))) > 1e-9:
        raise RuntimeError(f"the eigenvalues of i K_01 on V_{j} are not j..-j")
    return v[:, order]


def _y_rotation(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(np.shape(angle) + (3, 3))
    out[..., 0, 0], out[..., 0, 2], out[..., 2, 0], out[..., 2, 2] = c, s, -s, c
    out[..., 1, 1] = 1.0
    return out


def _quadratic(j: int, state: np.ndarray, phi: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(2j + 1) <state| D(L) Phi D(L)^T |state> at each rotation [..., 3, 3]."""
    D = wigner(j, rotations)
    v = np.einsum("a,...ab->...b", state.conj(), D)
    return (2 * j + 1) * np.einsum("...a,ab,...b->...", v, phi, v.conj()).real


def rotation_angle_density(j: int, state: np.ndarray, phi: np.ndarray, omega: np.ndarray
                           ) -> np.ndarray:
    """Density of the rotation angle omega in [0, pi] of L (module docstring): (1 - cos omega)
    / pi times the mean of p_L over the axes of rotation (exact product rule)."""
    t, wt = np.polynomial.legendre.leggauss(2 * j + 2)
    az = 2 * np.pi * np.arange(4 * j + 2) / (4 * j + 2)
    T, A = np.meshgrid(t, az, indexing="ij")
    st = np.sqrt(1 - T * T)
    n = np.stack([st * np.cos(A), st * np.sin(A), T], -1).reshape(-1, 3)
    weight = (np.repeat(wt, len(az)) / (2 * len(az)))  # mean over the sphere
    w = np.asarray(omega, float)[:, None, None, None]
    K = np.zeros((len(n), 3, 3))  # [n]_x
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -n[:, 2], n[:, 1], -n[:, 0]
    K = K - K.transpose(0, 2, 1)
    rot = np.eye(3) + np.sin(w) * K + (1 - np.cos(w)) * (K @ K)  # Rodrigues [omega, n, 3, 3]
    mean = np.einsum("on,n->o", _quadratic(j, state, phi, rot), weight)
    return (1 - np.cos(np.asarray(omega, float))) / np.pi * mean


#: rotations taking the body axis k to the third axis (S_k e_k = e_3), det 1
_TO_THIRD = (np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]),
             np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.eye(3))


def axis_density(j: int, m: int, phi: np.ndarray, axis: int, t: np.ndarray) -> np.ndarray:
    """Density of the cosine t in [-1, 1] of the angle between the column ``axis`` (k) of L and
    the third axis, for the state |j m>: L = R_3(a) R_2(theta) R_3(chi) S_k (cos theta = t,
    S_k e_k = e_3) is Haar with the measure dt da dchi / (8 pi^2); R_3(a) multiplies |j m> by
    a phase and the mean over chi keeps the diagonal of Y = D(S_k) Phi D(S_k)^T in the basis
    |j mu>, so

        p_k(t) = (2j + 1)/2 sum_mu |<j m| D^j(R_2(theta)) |j mu>|^2 <j mu| Y |j mu>,

    the |d^j_{m mu}(theta)|^2 pattern weighted by the body-frame shares of axis k."""
    U = magnetic_states(j)
    S = wigner(j, _TO_THIRD[axis])
    shares = np.einsum("am,ab,bm->m", U.conj(), S @ phi @ S.T, U).real
    theta = np.arccos(np.clip(np.asarray(t, float), -1.0, 1.0))
    d = np.einsum("a,...ab,bm->...m", U[:, j - m].conj(), wigner(j, _y_rotation(theta)), U)
    return (2 * j + 1) / 2 * np.abs(d) ** 2 @ shares


def _integral(density, lo: float, hi: float) -> float:
    x, w = np.polynomial.legendre.leggauss(64)
    return float(np.sum(w * density(lo + (hi - lo) * (x + 1) / 2)) * (hi - lo) / 2)


def multiplet_of_state(spectrum: Spectrum, state: int):
    """(level, sector, F [P, 2j + 1, 2j' + 1] at the reduced nodes, weights [P], first state
    index of the multiplet) of the multiplet holding the ``state``-th entry of
    :meth:`Spectrum.energies` (n = 3); its states are first, ..., first + dimension - 1."""
    table = state_components(spectrum, state)
    level, sector = table[state]
    before = sum(1 for lv, sec in table[:state] if lv is level and sec == sector)
    pairs = [(c, k) for c in level_components(spectrum, level, sector=sector)
             for k, s in enumerate(c.sectors)
             if s == sector]
    component, k = pairs[before // sector.dimension]
    y, w = reduced_quadrature([component])
    F = sector_amplitudes(component, y)[k][1]
    norm = float(np.einsum("p,pab,pab->", w, F, F))
    if abs(norm - 1) > NORMALISATION:
        raise ValueError(f"densities: state {state} is normalised only to {abs(norm - 1):.1e} "
                         f"under the reduced quadrature (raise quantum.basis_size)")
    return level, sector, F, w, state - before % sector.dimension


def multiplet_orientations(spectrum: Spectrum, state: int, points: int = POINTS,
                           every: bool = True) -> list[dict]:
    """Orientation densities of every state of the multiplet holding the ``state``-th state
    (n = 3, module docstring), in the order of their indices (``every`` False: of that state
    only); each a dict: ``state``,
    ``sector``, magnetic numbers ``m``, ``m_prime``, ``energy``, ``orientation`` (``angle``:
    omega on [0, pi] with ``L_angle``, ``R_angle``; ``t``: cosines on [-1, 1] with
    ``L_axis1..3``, the principal axes of C (columns of L, Q_1 >= Q_2 >= |Q_3|), and
    ``R_axis1..3``, those of G (columns of R)), ``integrals`` of each (Gauss-Legendre, exact
    for these trigonometric polynomials), ``weights_L``, ``weights_R`` (the diagonals of
    Phi_L, Phi_R in the harmonic basis of covariants3)."""
    if spectrum.n != 3:
        raise ValueError("multiplet_orientations is for n = 3")
    if state < 0:
        raise ValueError(f"state indices must be >= 0 (got {state})")
    level, sector, F, w, first = multiplet_of_state(spectrum, state)
    if not level.converged:
        raise ValueError(f"state {state} is not converged (raise quantum.basis_size)")
    j, jp = sector.spin, sector.vorticity
    phi = {"L": (j, np.einsum("p,pab,pcb->ac", w, F, F)),
           "R": (jp, np.einsum("p,pba,pbc->ac", w, F, F))}
    basis = {"L": magnetic_states(j), "R": magnetic_states(jp)}
    omega = np.linspace(0.0, np.pi, points)
    t = np.linspace(-1.0, 1.0, points)
    out = []
    for position in range(sector.dimension) if every else (state - first,):
        index = {"L": position // (2 * jp + 1), "R": position % (2 * jp + 1)}
        orient, integrals = {"angle": omega, "t": t}, {}
        for side, (spin, moments) in phi.items():
            vec, m = basis[side][:, index[side]], spin - index[side]
            orient[f"{side}_angle"] = rotation_angle_density(spin, vec, moments, omega)
            integrals[f"{side}_angle"] = _integral(
                lambda x, s=spin, v=vec, p=moments: rotation_angle_density(s, v, p, x),
                0.0, np.pi)
            for k in range(3):
                orient[f"{side}_axis{k + 1}"] = axis_density(spin, m, moments, k, t)
                integrals[f"{side}_axis{k + 1}"] = _integral(
                    lambda x, s=spin, m=m, p=moments, k=k: axis_density(s, m, p, k, x),
                    -1.0, 1.0)
        out.append({"state": first + position, "sector": sector.as_dict(),
                    "m": j - index["L"], "m_prime": jp - index["R"], "energy": level.energy,
                    "orientation": orient, "integrals": integrals,
                    "weights_L": np.diag(phi["L"][1]).copy(),
                    "weights_R": np.diag(phi["R"][1]).copy()})
    return out


def orientation_densities3(spectrum: Spectrum, state: int, points: int = POINTS) -> dict:
    """The entry of :func:`multiplet_orientations` for ``state``, with ``kind`` "state", no G
    components and no warnings (the densities are exact given the state's Phi_L, Phi_R)."""
    (entry,) = multiplet_orientations(spectrum, state, points, every=False)
    return {"kind": "state", "G": {}, "warnings": [], **entry}


__all__ = ["POINTS", "wigner", "magnetic_states", "rotation_angle_density", "axis_density",
           "multiplet_of_state", "multiplet_orientations", "orientation_densities3"]
