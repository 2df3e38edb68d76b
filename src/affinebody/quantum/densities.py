"""Probability densities of deformation invariants from |Psi|^2 with the right measure
(paper, last section: "Performing some partial integrations one can obtain from Psi-bar Psi
probability distributions for ... deformation invariants, orientations of the main axes").

For a level of :class:`~affinebody.quantum.spectra.Spectrum` the reduced eigenfunction f is
orthonormal under the reduced measure, so the joint density of the invariants is
f^2 x (measure): d'Alembert n = 2: f(r1, r2)^2 r1 r2 dr1 dr2 (r1 = |z| = (Q1 + Q2)/2,
r2 = |w| = (Q1 - Q2)/2, i.e. prod|Q_a^2 - Q_b^2| dQ up to the constant); affine n = 2:
f(x, sigma)^2 sinh x dx dsigma (x = q1 - q2, sigma = q1 + q2 = ln det phi); n = 3 scalar:
f(Q)^2 prod(Q_a^2 - Q_b^2) dQ on the chamber; n = 3 spin = vorticity = 1 (and the affine n = 3
sectors): sum_a f_a^2 J on the solver's quadrature grid (the density of a 9-state multiplet,
summed over its states; its orientation density is uniform). Marginals of Q_a (or q_a),
det phi and Tr G are integrated from the joint density; each integrates to 1 (checked and reported).

Orientations: a sector state e^{i(s alpha + k beta)} (alpha, beta the angles of L and R) has
|Psi|^2 independent of the orientation of the principal axes; the densities returned are those
of the real standing wave cos(s alpha + k beta) spanned by the (s, k) and (-s, -k) copies,
p(alpha) = int cos^2(s alpha + k beta) dbeta / (2 pi^2) and likewise for beta.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from affinebody.quantum.bases import sqrt_x_over_sinh
from affinebody.quantum.channels3 import ChamberQuadrature
from affinebody.quantum.levels import Level, Spectrum


def _hist(values: np.ndarray, weights: np.ndarray, bins: int = 120):
    support = values[weights > 1e-14 * weights.max()]
    lo, hi = float(np.min(support)), float(np.max(support))
    edges = np.linspace(lo, hi + 1e-12 * max(1.0, abs(hi)), bins + 1)
    mass, _ = np.histogram(values, edges, weights=weights)
    centres = 0.5 * (edges[1:] + edges[:-1])
    return centres, mass / np.diff(edges)


def _legendre(lo: float, hi: float, points: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(points)
    return lo + (hi - lo) * (x + 1) / 2, (hi - lo) * w / 2


def _orientation(sector, n: int = 2) -> dict[str, np.ndarray]:
    s, k = sector.spin, sector.vorticity
    if n == 3:  # an SO(3) multiplet averaged over its states: uniform orientation density
        s = k = 0
    ang = np.linspace(0, 2 * np.pi, 361)
    beta = np.linspace(0, 2 * np.pi, 721)[:-1]
    dens_a = np.mean(np.cos(s * ang[:, None] + k * beta[None, :]) ** 2, axis=1)
    dens_b = np.mean(np.cos(s * beta[None, :] + k * ang[:, None]) ** 2, axis=1)
    norm = np.trapezoid(dens_a, ang)
    return {"angle": ang, "L_angle": dens_a / norm, "R_angle": dens_b / np.trapezoid(dens_b, ang)}


def densities(spectrum: Spectrum, state: int, points: int = 300) -> dict:
    """Marginal densities (dict of arrays) for the ``state``-th entry of ``energies()``."""
    level: Level = spectrum.level_of_state(state)
    block = spectrum.blocks[level.block]
    coeff = block.vectors[:, level.index]
    basis = block.basis
    out: dict = {"energy": level.energy, "sector": level.sectors[0].as_dict()}
    if basis.kind == "lebesgue2":
        span = [f.scale * np.sqrt(4 * f.size + 2 * f.m + 30) for f in basis.factors]
        (r1, g1), (r2, g2) = _legendre(0, span[0], points), _legendre(0, span[1], points)
        f1 = basis.factors[0].evaluate(r1)
        f2 = basis.factors[1].evaluate(r2)
        C = coeff.reshape(f1.shape[1], f2.shape[1])
        psi = f1 @ C @ f2.T
        joint = psi**2 * r1[:, None] * r2[None, :]
        w = np.outer(g1, g2) * joint
        R1, R2 = np.meshgrid(r1, r2, indexing="ij")
        coords = {"Q1": R1 + R2, "Q2": R1 - R2, "det": R1**2 - R2**2,
                  "trG": 2 * (R1**2 + R2**2)}
    elif basis.kind == "haar2":
        fx, fs = basis.factors
        x, gx = _legendre(0, fx.scale * np.sqrt(4 * fx.size + 2 * fx.m + 30), points)
        half = fs.scale * np.sqrt(2 * fs.size + 30)
        sig, gs = _legendre(fs.centre - half, fs.centre + half, points)
        u = fx.evaluate(x) * sqrt_x_over_sinh(x)[:, None]
        h = fs.evaluate(sig)
        psi = u @ coeff.reshape(u.shape[1], h.shape[1]) @ h.T
        joint = psi**2 * np.sinh(x)[:, None]
        w = np.outer(gx, gs) * joint
        X, S = np.meshgrid(x, sig, indexing="ij")
        q1, q2 = (S + X) / 2, (S - X) / 2
        coords = {"q1": q1, "q2": q2, "det": np.exp(S),
                  "trG": np.exp(2 * q1) + np.exp(2 * q2)}
    elif basis.kind == "grid3":
        kind, grid, values, _parity, _spin1 = basis.factors
        if callable(values):  # n3.SectorBasis.values: evaluated on demand
            values = values()
        psi = values @ coeff  # [P, d]: the radial functions f_a on the quadrature grid
        w = grid.weights * np.sum(psi**2, axis=-1)
        x = grid.nodes
        if kind == "lebesgue3":
            coords = {"Q1": x[:, 0], "Q2": x[:, 1], "Q3": x[:, 2], "det": np.prod(x, -1),
                      "trG": np.sum(x * x, -1)}
        else:
            coords = {"q1": x[:, 0], "q2": x[:, 1], "q3": x[:, 2],
                      "det": np.exp(np.sum(x, -1)), "trG": np.sum(np.exp(2 * x), -1)}
    else:
        sb = basis.factors[0]
        quad = ChamberQuadrature.build(sb.scale * 10.0, 120, 60)
        psi = sb.evaluate(quad.nodes) @ coeff
        w = quad.weights * psi**2
        Q = quad.nodes
        coords = {"Q1": Q[:, 0], "Q2": Q[:, 1], "Q3": Q[:, 2], "det": np.prod(Q, -1),
                  "trG": np.sum(Q * Q, -1)}
    total = float(np.sum(w))
    out["normalisation"] = total
    marginals = {}
    for name, values in coords.items():
        centres, dens = _hist(np.ravel(values), np.ravel(w) / total)
        marginals[name] = (centres, dens)
    out["marginals"] = marginals
    out["orientation"] = _orientation(level.sectors[0], spectrum.n)
    return out


def write_densities(spectrum: Spectrum, state: int, directory: str | Path) -> dict:
    """Write densities.npz, densities.json (normalisations) and one PNG per density."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    data = densities(spectrum, state)
    arrays, summary = {}, {"state": state, "energy": data["energy"], "sector": data["sector"],
                           "normalisation": data["normalisation"], "integrals": {}}
    for name, (x, p) in data["marginals"].items():
        arrays[f"{name}_x"], arrays[f"{name}_density"] = x, p
        summary["integrals"][name] = float(np.sum(p) * (x[1] - x[0]))
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot(x, p)
        ax.set_xlabel(name)
        ax.set_ylabel("probability density")
        ax.set_title(f"state {state}, E = {data['energy']:.6g}")
        fig.tight_layout()
        fig.savefig(directory / f"density_{name}.png", dpi=100)
        plt.close(fig)
    orient = data["orientation"]
    arrays["angle"] = orient["angle"]
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for key in ("L_angle", "R_angle"):
        arrays[key + "_density"] = orient[key]
        summary["integrals"][key] = float(np.trapezoid(orient[key], orient["angle"]))
        ax.plot(orient["angle"], orient[key], label=key.replace("_", " "))
    ax.set_xlabel("angle of the principal axes (rad)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(directory / "density_orientation.png", dpi=100)
    plt.close(fig)
    np.savez(directory / "densities.npz", **arrays)
    (directory / "densities.json").write_text(json.dumps(summary, indent=2))
    return summary
