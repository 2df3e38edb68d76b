"""Time evolution of a wave packet of the n = 3 body in the SO(3) x SO(3) sector (0, 0) by its
expansion in the sector's eigenstates (paper, last section; docs/quantum-transitions.md).

A state of the sector (0, 0) is a function of phi invariant under phi -> U phi V^T (U, V in
SO(3)): it carries no spin and no vorticity, and it is a function of the singular values, Q
(d'Alembert, Q1 >= Q2 >= |Q3|) or q = ln Q (affine models, q1 >= q2 >= q3), invariant under
their Weyl group W (permutations, and for d'Alembert an even number of sign changes). The
packet is the W-symmetrised Gaussian

    psi_0(X) = N sum_{g in W} exp(-|gX - X0|^2 / (4 w^2) + i p0 . (gX - X0) / hbar),

a smooth function of phi (no singularity at the walls of the chamber, where the reduced measure
m(X) vanishes). Far from the walls (many widths) one term dominates on the chamber, and
|psi_0|^2 m dX is close to m(X) times the Gaussian of centre X0; nearer, it is what the sector
makes of a Gaussian. Its classical counterpart is the motion with zero angular momentum from
phi = diag(Q0) with momentum diag(p0) (d'Alembert), which stays diagonal.

With the sector's Galerkin eigenpairs (E_n, a_n) (channels3: the Weyl-invariant Arnoldi
basis of degree ``basis_size`` for d'Alembert, the invariant polynomials times the Haar
Gaussian for the affine models, solved densely on one chamber quadrature that also integrates
the packet), c_n = <a_n|psi_0> and

    psi(t) = sum_n c_n e^{-i E_n t / hbar} a_n,
    <A>(t) = sum_{mn} conj(c_m(t)) c_n(t) <a_m|A|a_n>,
    S(t) = |sum_n |c_n|^2 e^{-i E_n t / hbar}|^2,

exactly, for any t; the matrices <a_m|A|a_n> of the observables (the three variables, det phi,
Tr G and their squares) are integrated once, so the work per time is O(K^2) for K states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import permutations

import numpy as np

from affinebody._checks import require_x64
from affinebody.quantum.bases import solve_block
from affinebody.quantum.channels3 import (
    ChamberQuadrature,
    channel3_block,
    haar3_grid,
    scalar3_block,
    setup3,
)
from affinebody.quantum.evolution import MAX_WORK, Evolution, require_captured
from affinebody.quantum.levels import AffineInertia, Potential, Settings

#: the largest polynomial degree (quantum.basis_size) evolve solves for n = 3
MAX_DEGREE3 = 24
#: the observables reported (the model's three variables, det phi, Tr G)
VARIABLES3 = {"dalembert": ("Q1", "Q2", "Q3", "det", "trG"),
              "affine": ("q1", "q2", "q3", "det", "trG")}


@dataclass(frozen=True)
class Sector3:
    """The eigenpairs of the n = 3 sector (0, 0) and the quadrature they live on: nodes x
    [P, 3] (Q or q), weights [P] (the reduced measure included), basis values [P, K]
    (orthonormal under the weights), energies [K], eigenvectors [K, K] (columns) and their
    error estimates [K] (nested and widened check bases; inf beyond them)."""

    model: str
    nodes: np.ndarray
    weights: np.ndarray
    values: np.ndarray
    energies: np.ndarray
    vectors: np.ndarray
    errors: np.ndarray
    settings: dict


def sector_states(model: str, degree: int) -> int:
    """The number of basis functions of the sector (0, 0) at ``degree``: the invariant
    monomials p2^a e3^b p4^c (weights 2, 3, 4; d'Alembert) or t^a p2^b p3^c (weights 1, 2, 3;
    affine models) of total weight <= degree."""
    wa, wb, wc = (2, 3, 4) if model == "dalembert" else (1, 2, 3)
    return sum(1 for a in range(degree // wa + 1) for b in range(degree // wb + 1)
               for c in range(degree // wc + 1) if wa * a + wb * b + wc * c <= degree)


def check_degree(model: str, degree: int, times: int) -> None:
    """Refuse at once a degree above :data:`MAX_DEGREE3`, or an evolution whose work, (times)
    x (states)^2 for each of the 10 moment matrices, exceeds
    :data:`affinebody.quantum.evolution.MAX_WORK`."""
    if degree > MAX_DEGREE3:
        raise ValueError(f"quantum.basis_size = {degree} is more than evolve solves for n = 3 "
                         f"(polynomial degree {MAX_DEGREE3})")
    states = sector_states(model, degree)
    work = times * states**2 * 10
    if work > MAX_WORK:
        raise ValueError(f"evolve: {times} times x {states} states is more work than allowed "
                         f"({work:.1e} > {MAX_WORK:.0e}): ask for fewer --steps or a smaller "
                         f"quantum.basis_size")


def scalar_sector3(model: str, potential: Potential, hbar: float, *, inertia: float = 1.0,
                   I: float = 1.0, A: float = 0.0, B: float = 0.0,  # noqa: E741
                   settings: Settings | None = None, reach: float = 0.0) -> Sector3:
    """Every eigenpair of the n = 3 sector (0, 0) (channels3's bases, the scales of
    :func:`affinebody.quantum.channels3.setup3`). d'Alembert: the chamber quadrature reaches
    at least |Q| = ``reach`` (the packet's extent)."""
    require_x64()  # a potential expression is evaluated by JAX
    settings = settings or Settings(basis_size=10)
    degree = settings.basis_size
    check_degree(model, degree, 1)
    affine = None if model == "dalembert" else AffineInertia(model, I, A, B)
    setup = setup3(model, potential, hbar, inertia, affine, settings)
    if model == "dalembert":
        rho = max(setup.scale * (8.0 + 0.75 * math.sqrt(degree + 1)), reach)
        quad = ChamberQuadrature.build(rho, n_rho=40 + 2 * degree, n_angle=16 + degree)

        def build(d, s):
            return scalar3_block(potential, hbar, inertia, d, s, quad)
    else:
        def grid(d, s):
            return haar3_grid(s, setup.sigma_scale(s), setup.centre, 24 + 2 * d, 12 + d, 8 + d)

        def build(d, s):
            return channel3_block("haar3", potential, hbar, affine, grid(d, s), d, s,
                                  setup.sigma_scale(s), setup.centre)
    E, vec, err, basis = solve_block(build, degree, setup.scale, 10**6, setup.check)
    if model == "dalembert":
        nodes, weights = quad.nodes, quad.weights
        values = basis.factors[0].evaluate(nodes)
    else:
        used = grid(degree, setup.scale)
        nodes, weights = used.nodes, used.weights
        values = basis.factors[2][:, 0, :]
    return Sector3(model, nodes, weights, values, E, vec, err, setup.info(settings))


def weyl_group(model: str) -> list[np.ndarray]:
    """The Weyl group of the chamber as 3 x 3 signed permutation matrices: every permutation,
    times (d'Alembert) the sign changes of an even number of entries."""
    out = []
    flips = ([np.ones(3)] if model != "dalembert" else
             [np.array(s, float) for s in ((1, 1, 1), (-1, -1, 1), (-1, 1, -1), (1, -1, -1))])
    for p in permutations(range(3)):
        for f in flips:
            out.append(np.eye(3)[list(p)] * f[:, None])
    return out


def packet3(model: str, x: np.ndarray, centre, momentum, width: float, hbar: float
            ) -> np.ndarray:
    """The W-symmetrised Gaussian packet (module docstring) at x [P, 3], unnormalised."""
    X0, p0 = np.asarray(centre, float), np.asarray(momentum, float)
    psi = np.zeros(len(x), complex)
    for g in weyl_group(model):
        d = x @ g.T - X0
        psi += np.exp(-np.sum(d * d, -1) / (4 * width**2) + 1j * (d @ p0) / hbar)
    return psi


def check_packet3(model: str, centre, width: float) -> None:
    """One-line refusals: a width that is not positive; a centre outside the chamber."""
    X = np.asarray(centre, float)
    if not (math.isfinite(width) and width > 0):
        raise ValueError(f"--width must be > 0 (got {width})")
    inside = X[0] >= X[1] >= abs(X[2]) if model == "dalembert" else X[0] >= X[1] >= X[2]
    if not inside:
        order = "Q1 >= Q2 >= |Q3|" if model == "dalembert" else "q1 >= q2 >= q3"
        raise ValueError(f"--at: the packet's centre must lie in the chamber {order} (got "
                         f"{', '.join(f'{v:g}' for v in X)})")


def evolve3(sector: Sector3, centre, momentum, width: float, times: np.ndarray, hbar: float
            ) -> Evolution:
    """The evolution of the packet (module docstring) over ``times`` in the eigenstates of
    ``sector`` (a :func:`scalar_sector3`)."""
    model = sector.model
    check_packet3(model, centre, width)
    times = np.asarray(times, float)
    check_degree(model, sector.settings["basis_size"], len(times))
    x, w, F = sector.nodes, sector.weights, sector.values
    psi = packet3(model, x, centre, momentum, width, hbar)
    psi /= math.sqrt(float(np.sum(w * np.abs(psi) ** 2)))
    c = sector.vectors.T @ (F.T @ (w * psi.real) + 1j * (F.T @ (w * psi.imag)))
    captured = float(np.sum(np.abs(c) ** 2))
    require_captured(captured)
    E, errors = sector.energies, sector.errors
    p = np.abs(c) ** 2
    energy_error = float(np.sum(p * np.where(np.isfinite(errors), errors, np.abs(E))) / captured)
    names = VARIABLES3["dalembert" if model == "dalembert" else "affine"]
    Q = x if model == "dalembert" else np.exp(x)
    observables = dict(zip(names, (*x.T, np.prod(Q, -1), np.sum(Q * Q, -1)), strict=True))
    phases = np.exp(-1j * np.outer(times, E) / hbar)  # [T, K]
    ct = c[None, :] * phases
    mean, spread = {}, {}
    for name, v in observables.items():
        # <a_m|A|a_n> in the eigenbasis, for A and A^2
        M1 = sector.vectors.T @ (F.T @ ((w * v)[:, None] * F)) @ sector.vectors
        M2 = sector.vectors.T @ (F.T @ ((w * v * v)[:, None] * F)) @ sector.vectors
        m1 = np.einsum("tm,mn,tn->t", ct.conj(), M1, ct).real / captured
        m2 = np.einsum("tm,mn,tn->t", ct.conj(), M2, ct).real / captured
        mean[name] = m1
        spread[name] = np.sqrt(np.maximum(m2 - m1 * m1, 0.0))
    norm = np.sum(np.abs(ct) ** 2, -1)
    energy = (np.abs(ct) ** 2 @ E) / norm
    survival = np.abs(phases @ p) ** 2 / captured**2
    return Evolution(times, E, c, captured, energy_error, mean, spread, survival, norm, energy)


__all__ = ["MAX_DEGREE3", "VARIABLES3", "Sector3", "sector_states", "check_degree",
           "scalar_sector3", "weyl_group", "packet3", "check_packet3", "evolve3"]
