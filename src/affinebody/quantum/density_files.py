"""Files of ``affinebody density``: the densities of :mod:`affinebody.quantum.densities` written
as densities.npz (every array), densities.json (arrays, errors, integrals) and one PNG per
density (the application layer: the library computes, this module writes and plots)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from affinebody.quantum.densities import DEFAULT_TOLERANCE, VARIABLES, densities
from affinebody.quantum.spectra import Spectrum


def write_densities(spectrum: Spectrum, state: int, directory: str | Path,
                    points: int | None = None, tolerance: float = DEFAULT_TOLERANCE) -> dict:
    """Write densities.npz, densities.json (every array, error and integral) and one PNG per
    density; returns the JSON payload."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    data = densities(spectrum, state, points, tolerance)
    payload = {"state": state, "energy": data["energy"], "sector": data["sector"],
               "variables": data["variables"], "variables_note": VARIABLES[data["variables"]],
               "level_error": data["level_error"],
               "normalisation": data["normalisation"], "tolerance": tolerance,
               "densities": {}, "integrals": {}, "warnings": data["warnings"]}
    arrays = {}
    for name, m in data["details"].items():
        arrays[f"{name}_x"], arrays[f"{name}_density"] = m.x, m.density
        payload["densities"][name] = m.as_dict()
        payload["integrals"][name] = m.integral
        fig, ax = plt.subplots(figsize=(5, 3.5))
        ax.plot(m.x, m.density)
        ax.set_xlabel(name)
        ax.set_ylabel("probability density")
        ax.set_title(f"state {state}, E = {data['energy']:.6g} (error {m.error:.1e})")
        fig.tight_layout()
        fig.savefig(directory / f"density_{name}.png", dpi=100)
        plt.close(fig)
    orient = data["orientation"]
    arrays["angle"] = orient["angle"]
    label = ("angle of L, R (rad): uniform" if spectrum.n == 2
             else "rotation angle of L, R (rad): Haar")
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for key in ("L_angle", "R_angle"):
        arrays[key + "_density"] = orient[key]
        payload["densities"][key] = {
            "x": orient["angle"].tolist(), "density": orient[key].tolist(), "error": 0.0,
            "integral": 1.0, "converged": True,
            "exact": ("uniform 1/(2 pi): |Psi|^2 of a sector state does not depend on the angle"
                      if spectrum.n == 2 else "(1 - cos omega)/pi: Haar measure of SO(3)")}
        payload["integrals"][key] = 1.0
        ax.plot(orient["angle"], orient[key], label=key.replace("_", " "))
    ax.set_xlabel(label)
    ax.legend()
    fig.tight_layout()
    fig.savefig(directory / "density_orientation.png", dpi=100)
    plt.close(fig)
    np.savez(directory / "densities.npz", **arrays)
    (directory / "densities.json").write_text(json.dumps(payload))
    return payload
