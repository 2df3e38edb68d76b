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

import math
from dataclasses import dataclass

import numpy as np

from affinebody.quantum import covariants3 as cov
from affinebody.quantum.densities import (
    boltzmann_factors,
    require_temperature,
    state_components,
    truncation_warning,
)
from affinebody.quantum.levels import Sector, Spectrum
from affinebody.quantum.tensor_operators3 import wigner
from affinebody.quantum.transitions import (
    level_components,
    level_states,
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
    index of the multiplet, F as a callable of reduced coordinates [N, 3]) of the multiplet
    holding the ``state``-th entry of :meth:`Spectrum.energies` (n = 3); its states are
    first, ..., first + dimension - 1."""
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
    return (level, sector, F, w, state - before % sector.dimension,
            _amplitude_function(component, k))


def _amplitude_function(component, k: int):
    """x [N, 3] -> F [N, 2j + 1, 2j' + 1] of the k-th sector of a component."""
    return lambda x: sector_amplitudes(component, np.asarray(x, float))[k][1]


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
    level, sector, F, w, first, _ = multiplet_of_state(spectrum, state)
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


# ------------------------------------------------------- superpositions and mixtures
@dataclass(frozen=True)
class MultipletState:
    """One state |j m> (x) |j' m'> of an n = 3 multiplet: psi = sqrt(d) u^H D^j(L) F(Q)
    D^j'(R)^T conj(v) (module docstring) with F [P, 2j + 1, 2j' + 1] at the reduced nodes,
    u = |j m>, v = |j' m'> (complex, in the harmonic bases)."""

    index: int
    sector: Sector
    energy: float
    F: np.ndarray
    u: np.ndarray
    v: np.ndarray
    #: F as a function of reduced coordinates x [N, 3] (Q, or q for the affine models)
    amplitude: object = None


def multiplet_state(spectrum: Spectrum, state: int) -> tuple[MultipletState, np.ndarray]:
    """The ``state``-th state of :meth:`Spectrum.energies` (converged, n = 3) and the weights
    of its reduced quadrature."""
    if state < 0:
        raise ValueError(f"state indices must be >= 0 (got {state})")
    level, sector, F, w, first, amplitude = multiplet_of_state(spectrum, state)
    if not level.converged:
        raise ValueError(f"state {state} is not converged (raise quantum.basis_size)")
    position = state - first
    jp = sector.vorticity
    return MultipletState(state, sector, level.energy, F,
                          magnetic_states(sector.spin)[:, position // (2 * jp + 1)],
                          magnetic_states(jp)[:, position % (2 * jp + 1)], amplitude), w


def level_multiplet_states(spectrum: Spectrum, count: int | None = None
                           ) -> tuple[list[MultipletState], np.ndarray]:
    """Every converged state among the first ``count`` of :meth:`Spectrum.energies` (all when
    None) as :class:`MultipletState` (one amplitude per multiplet, shared by its states), and
    the weights of the common reduced quadrature."""
    states = level_states(spectrum)
    out, index = [], 0
    by_level = {id(lv): k for k, lv in enumerate(spectrum.levels)}
    for level in spectrum.states():
        if count is not None and index >= count:
            break
        if id(level) not in by_level:  # an unconverged candidate keeps its place
            index += level.multiplicity
            continue
        k = by_level[id(level)]
        seen: dict = {}
        for sector in level.sectors:
            pairs = [(c, f) for c, f in zip(states.components[k], states.amplitudes[k],
                                            strict=True) if sector in c.sectors]
            c, f = pairs[seen.get(sector, 0)]
            seen[sector] = seen.get(sector, 0) + 1
            F = dict(sector_amplitudes(c, states.y, f))[sector]
            amplitude = _amplitude_function(c, c.sectors.index(sector))
            norm = float(states.weights @ np.sum(F * F, axis=(1, 2)))
            if abs(norm - 1) > NORMALISATION:
                raise ValueError(f"densities: state {index} is normalised only to "
                                 f"{abs(norm - 1):.1e} under the reduced quadrature (raise "
                                 f"quantum.basis_size)")
            U, V = magnetic_states(sector.spin), magnetic_states(sector.vorticity)
            for position in range(sector.dimension):
                jp = sector.vorticity
                out.append(MultipletState(index, sector, level.energy, F,
                                          U[:, position // (2 * jp + 1)],
                                          V[:, position % (2 * jp + 1)], amplitude))
                index += 1
    return (out if count is None else [s for s in out if s.index < count]), states.weights


def side_terms(amplitudes: np.ndarray, states: list[MultipletState], weights: np.ndarray,
               side: str, cache: dict | None = None) -> dict[tuple[int, int], np.ndarray]:
    """The orientation density of L (``side`` "L") or of R of sum_k c_k psi_k (module
    docstring; Schur orthogonality over the other rotation): only pairs with equal labels on
    the other side survive,

        p_L(L) = sum_kl conj(c_k) c_l sqrt(d_k d_l)/(2 j'_k + 1) (v_l^H v_k)
                 u_k^T D^{j_k}(L) Phi_kl D^{j_l}(L)^T conj(u_l),   Phi_kl = int mu F_k F_l^T,

    p_R the same with (j, u) and (j', v) exchanged and Phi_kl = int mu F_k^T F_l. Returned
    as {(j_k, j_l): W [a, d, b, c]} with p = Re sum W[a, d, b, c] D^{j_k}_ab D^{j_l}_dc
    (:func:`terms_density`), the pairs of each (j_k, j_l) summed. ``cache``: a dict keeping
    the Phi_kl of the multiplets across calls (the states of a multiplet share them)."""
    out: dict[tuple[int, int], np.ndarray] = {}
    cache = {} if cache is None else cache
    pairs = list(zip(amplitudes, states, strict=True))
    for k, (ck, sk) in enumerate(pairs):
        for cl, sl in pairs[k:]:
            if side == "L":
                if sk.sector.vorticity != sl.sector.vorticity:
                    continue
                other, overlap, x_k, x_l = sk.sector.vorticity, np.vdot(sl.v, sk.v), sk.u, sl.u
                j_k, j_l = sk.sector.spin, sl.sector.spin
            else:
                if sk.sector.spin != sl.sector.spin:
                    continue
                other, overlap, x_k, x_l = sk.sector.spin, np.vdot(sl.u, sk.u), sk.v, sl.v
                j_k, j_l = sk.sector.vorticity, sl.sector.vorticity
            if abs(overlap) < 1e-14:
                continue
            coef = (np.conj(ck) * cl * math.sqrt(sk.sector.dimension * sl.sector.dimension)
                    / (2 * other + 1) * overlap)
            if sk is not sl:  # the pair (l, k) is the complex conjugate: twice the real part
                coef = 2 * coef
            key = (id(sk.F), id(sl.F), side)
            if key not in cache:
                axes = ([0, 2], [0, 2]) if side == "L" else ([0, 1], [0, 1])
                cache[key] = (np.tensordot(weights[:, None, None] * sk.F, sl.F, axes=axes),
                              sk.F, sl.F)  # the arrays are kept alive with their ids
            phi = cache[key][0]
            W = coef * np.einsum("a,d,bc->adbc", x_k, x_l.conj(), phi)
            out[(j_k, j_l)] = out.get((j_k, j_l), 0.0) + W
    return out


def terms_density(terms: dict[tuple[int, int], np.ndarray], rotations: np.ndarray
                  ) -> np.ndarray:
    """p at rotations [..., 3, 3] from :func:`side_terms` (a real trigonometric polynomial of
    rank <= max(j_k + j_l))."""
    D = {}
    out = np.zeros(rotations.shape[:-2])
    for (j_k, j_l), W in terms.items():
        for j in (j_k, j_l):
            if j not in D:
                D[j] = wigner(j, rotations)
        out += np.einsum("...ab,...dc,adbc->...", D[j_k], D[j_l], W, optimize=True).real
    return out


def _rank(terms: dict) -> int:
    return max([j_k + j_l for j_k, j_l in terms] + [0])


def _merge(parts: list[tuple[float, dict]]) -> dict:
    out: dict = {}
    for p, terms in parts:
        for key, W in terms.items():
            out[key] = out.get(key, 0.0) + p * W
    return out


def angle_density_of(density, rank: int, omega: np.ndarray) -> np.ndarray:
    """Density of the rotation angle omega of a density p on SO(3) (a callable on rotations)
    of rank <= ``rank``: (1 - cos omega)/pi times the mean of p over the rotation axes (exact:
    Gauss-Legendre in the axis's cos theta, trapezoid in its azimuth)."""
    t, wt = np.polynomial.legendre.leggauss(rank + 1)
    az = 2 * np.pi * np.arange(2 * rank + 1) / (2 * rank + 1)
    T, A = np.meshgrid(t, az, indexing="ij")
    st = np.sqrt(1 - T * T)
    n = np.stack([st * np.cos(A), st * np.sin(A), T], -1).reshape(-1, 3)
    weight = np.repeat(wt, len(az)) / (2 * len(az))
    w = np.asarray(omega, float)[:, None, None, None]
    K = np.zeros((len(n), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -n[:, 2], n[:, 1], -n[:, 0]
    K = K - K.transpose(0, 2, 1)
    rot = np.eye(3) + np.sin(w) * K + (1 - np.cos(w)) * (K @ K)  # Rodrigues [omega, n, 3, 3]
    return (1 - np.cos(np.asarray(omega, float))) / np.pi * (density(rot) @ weight)


def axis_density_of(density, rank: int, axis: int, t: np.ndarray) -> np.ndarray:
    """Density of the cosine t of the column ``axis`` of a rotation distributed with p (rank
    <= ``rank``) with the third axis: L = R_3(a) R_2(theta) R_3(chi) S_k, (1/2) x the mean of
    p over a and chi (trapezoid rules, exact)."""
    n = rank + 1
    ang = 2 * np.pi * np.arange(n) / n
    theta = np.arccos(np.clip(np.asarray(t, float), -1.0, 1.0))
    rot = (_z_rotation(ang)[None, :, None] @ _y_rotation(theta)[:, None, None]
           @ _z_rotation(ang)[None, None, :] @ _TO_THIRD[axis])
    return density(rot).mean(axis=(1, 2)) / 2


def _z_rotation(angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(np.shape(angle) + (3, 3))
    out[..., 0, 0], out[..., 0, 1], out[..., 1, 0], out[..., 1, 1] = c, -s, s, c
    out[..., 2, 2] = 1.0
    return out


def state_mixture(spectrum: Spectrum, state: int | None = None,
                  superposition: dict[int, complex] | None = None,
                  temperature: float | None = None, tolerance: float = 1e-6
                  ) -> tuple[list, np.ndarray, str, list[str]]:
    """(mixture [(probability, amplitudes, [MultipletState])], weights of the reduced
    quadrature, kind, warnings) of one state, a superposition {state index: amplitude} or the
    thermal mixture exp(-E/T)/Z over the converged states computed (k_B = 1; a warning when the
    last still has more than ``tolerance`` of the first's weight); n = 3."""
    if spectrum.n != 3:
        raise ValueError("n = 3 orientation densities: the spectrum is n = 2")
    if sum(v is not None for v in (state, superposition, temperature)) != 1:
        raise ValueError("give exactly one of a state, a superposition or a temperature")
    warnings = []
    if state is not None:
        superposition, kind = {state: 1.0}, "state"
    else:
        kind = "superposition" if superposition is not None else "thermal"
    if superposition is not None:
        if not superposition:
            raise ValueError("a superposition needs at least one state")
        c = np.asarray([complex(v) for v in superposition.values()])
        if not np.sum(np.abs(c) ** 2) > 0:
            raise ValueError("a superposition needs a nonzero amplitude")
        picked = [multiplet_state(spectrum, k) for k in superposition]
        weights = picked[0][1]
        if any(len(w) != len(weights) or np.any(w != weights) for _, w in picked):
            raise ValueError("densities: the states do not share one reduced quadrature")
        return ([(1.0, c / np.sqrt(np.sum(np.abs(c) ** 2)), [p for p, _ in picked])], weights,
                kind, warnings)
    require_temperature(temperature)
    states, weights = level_multiplet_states(spectrum)
    boltzmann = boltzmann_factors([st.energy for st in states], temperature)
    if boltzmann[-1] / boltzmann[0] > tolerance:
        warnings.append(truncation_warning(len(states), boltzmann[-1] / boltzmann[0]))
    mixture = [(p, np.ones(1), [st]) for p, st in zip(boltzmann / boltzmann.sum(), states,
                                                      strict=True)]
    return mixture, weights, kind, warnings


def mixture_orientations(spectrum: Spectrum, superposition: dict[int, complex] | None = None,
                         temperature: float | None = None, points: int = POINTS,
                         tolerance: float = 1e-6) -> dict:
    """Orientation densities (the keys of :func:`multiplet_orientations`' ``orientation`` and
    ``integrals``) of a superposition {state index: amplitude} or of the thermal mixture
    exp(-E/T)/Z over the converged states computed (k_B = 1), n = 3: sums of
    :func:`terms_density` over the pure states, marginals by exact rules. A thermal mixture
    (a function of H, which commutes with SO(3) x SO(3)) is Haar-distributed at every T; the
    sum over the states computed shows it. ``warnings``: a thermal mixture truncated where
    the last state computed still has more than ``tolerance`` of the first's weight."""
    mixture, weights, kind, warnings = state_mixture(spectrum, None, superposition, temperature,
                                                     tolerance)
    omega = np.linspace(0.0, np.pi, points)
    t = np.linspace(-1.0, 1.0, points)
    orient, integrals = {"angle": omega, "t": t}, {}
    for side in ("L", "R"):
        cache: dict = {}
        terms = _merge([(p, side_terms(c, sts, weights, side, cache)) for p, c, sts in mixture])
        rank = _rank(terms)

        def density(rot, terms=terms):
            return terms_density(terms, rot)

        orient[f"{side}_angle"] = angle_density_of(density, rank, omega)
        integrals[f"{side}_angle"] = _integral(
            lambda x, d=density, r=rank: angle_density_of(d, r, x), 0.0, np.pi)
        for k in range(3):
            orient[f"{side}_axis{k + 1}"] = axis_density_of(density, rank, k, t)
            integrals[f"{side}_axis{k + 1}"] = _integral(
                lambda x, d=density, k=k, r=rank: axis_density_of(d, r, k, x), -1.0, 1.0)
    return {"kind": kind, "orientation": orient, "integrals": integrals, "G": {},
            "warnings": warnings, "states": [st.index for _, _, sts in mixture for st in sts]}


__all__ = ["POINTS", "MultipletState", "multiplet_state", "level_multiplet_states",
           "side_terms", "terms_density", "state_mixture", "angle_density_of", "axis_density_of",
           "mixture_orientations", "magnetic_states", "rotation_angle_density", "axis_density",
           "multiplet_of_state", "multiplet_orientations", "orientation_densities3"]
