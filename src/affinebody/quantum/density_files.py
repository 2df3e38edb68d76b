"""Files of ``affinebody density``: the densities of :mod:`affinebody.quantum.densities` written
as densities.npz (every array), densities.json (arrays, errors, integrals) and one PNG per
density (the application layer: the library computes, this module writes and plots)."""

from __future__ import annotations

import cmath
from pathlib import Path

import numpy as np

from affinebody._json import json_text
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
                      if spectrum.n == 2 else "(1 - cos omega)/pi: Haar measure of SO(3), the "
                      "multiplet summed over its states (one state: --orientation)")}
        payload["integrals"][key] = 1.0
        ax.plot(orient["angle"], orient[key], label=key.replace("_", " "))
    ax.set_xlabel(label)
    ax.legend()
    return _save(fig, directory / "density_orientation.png", directory / "densities", arrays,
                 payload)


def _save(fig, png: Path, stem: Path, arrays: dict, payload: dict) -> dict:
    """Write the figure, STEM.npz (the arrays) and STEM.json (the payload); return payload."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(png, dpi=100)
    plt.close(fig)
    np.savez(stem.with_suffix(".npz"), **arrays)
    stem.with_suffix(".json").write_text(json_text(payload))
    return payload


def parse_superposition(text: str) -> dict[int, complex]:
    """``"0:1,8:0.5j"`` -> {0: 1, 8: 0.5j} (state index: amplitude, Python complex syntax);
    ValueError with the expected form otherwise."""
    try:
        pairs = [(int(index), complex(amplitude.replace(" ", "")))
                 for index, amplitude in (item.split(":") for item in text.split(","))]
    except ValueError:
        raise ValueError(f"--superpose must be index:amplitude pairs like 0:1,8:0.5j (got "
                         f"{text!r})") from None
    out: dict[int, complex] = {}
    for index, amplitude in pairs:
        if index in out:  # a dict would keep the last silently
            raise ValueError(f"--superpose: state {index} is given twice (give each state "
                             f"once, with the sum of its amplitudes)")
        if not cmath.isfinite(amplitude):
            raise ValueError(f"--superpose: the amplitude of state {index} must be finite (got "
                             f"{amplitude})")
        out[index] = amplitude
    return out


def write_orientation(spectrum: Spectrum, directory: str | Path, state: int | None = None,
                      superposition: dict[int, complex] | None = None,
                      temperature: float | None = None, points: int | None = None,
                      tolerance: float | None = None, green: tuple[str, ...] = ()) -> dict:
    """Write orientation.json, orientation.npz and orientation.png: the densities of the
    angles of L and R (principal axes of C and G) and of G11, G22, G12 of a state, a
    superposition or the thermal mixture (:func:`orientation_densities`); returns the JSON
    payload."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from affinebody.quantum.densities import G_TOLERANCE, orientation_densities

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if spectrum.n == 3:
        return _write_orientation3(spectrum, directory, state, superposition, temperature,
                                   green, min(points or 21, 51))
    if green:
        raise ValueError("--g-components is for n = 3 (n = 2 computes G11, G22, G12 always)")
    tolerance = G_TOLERANCE if tolerance is None else tolerance
    data = orientation_densities(spectrum, state, superposition, temperature,
                                 points=min(points or 51, 201), tolerance=tolerance)
    orient = data["orientation"]
    payload = {"kind": data["kind"], "state": state, "temperature": temperature,
               "superposition": None if superposition is None else
               {str(k): [v.real, v.imag] for k, v in superposition.items()},
               "angle_note": ("angle of L = rot(alpha) (principal axes of C) and of "
                              "R = rot(beta) (principal axes of G), phi = L D R^T, rad"
                              if spectrum.n == 2 else "rotation angle of L and R (Haar)"),
               "tolerance": tolerance, "densities": {}, "warnings": data["warnings"]}
    arrays = {"angle": orient["angle"]}
    for key in ("L_angle", "R_angle"):
        arrays[key] = orient[key]
        payload["densities"][key] = {"x": orient["angle"].tolist(),
                                     "density": orient[key].tolist()}
    for name, m in data["G"].items():
        arrays[f"{name}_x"], arrays[f"{name}_density"] = m.x, m.density
        payload["densities"][name] = m.as_dict()
    panels = 1 + bool(data["G"])
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 3.5), squeeze=False)
    for key in ("L_angle", "R_angle"):
        axes[0, 0].plot(orient["angle"], orient[key], label=key.replace("_", " "))
    axes[0, 0].set_xlabel("angle (rad)")
    axes[0, 0].set_ylabel("probability density")
    axes[0, 0].legend()
    for name, m in data["G"].items():
        axes[0, 1].plot(m.x, m.density, label=_g_label(name, m))
    if data["G"]:
        axes[0, 1].set_xlabel("component of G")
        axes[0, 1].legend()
    fig.suptitle(f"{data['kind']}" + (f" {state}" if state is not None else "")
                 + (f", T = {temperature:g}" if temperature is not None else ""))
    return _save(fig, directory / "orientation.png", directory / "orientation", arrays, payload)


def _g_label(name: str, m) -> str:
    """The legend of a G-component density (n = 2 and 3): its error and its integral with the
    integral's error."""
    return (f"{name} (error {m.error:.1e}; integral {m.integral:.6f} "
            f"\u00b1 {m.integral_error:.0e})")


#: n = 3: the most (points x components) of G densities one request may ask for
MAX_GREEN_WORK = 80


def _write_orientation3(spectrum: Spectrum, directory: Path, state: int | None,
                        superposition: dict[int, complex] | None = None,
                        temperature: float | None = None, green: tuple[str, ...] = (),
                        points: int = 21) -> dict:
    """n = 3: the densities of one state (:func:`orientation_densities3`), a superposition or
    the thermal mixture (:func:`mixture_orientations`): rotation angles of L and R, cosines of
    their principal axes with the third axis, and the components of G listed in ``green``
    (quantum.green3), as orientation.json / .npz / .png."""
    import matplotlib.pyplot as plt

    from affinebody.quantum import green3
    from affinebody.quantum.orientations3 import (
        mixture_orientations,
        orientation_densities3,
        state_mixture,
    )

    known = green3.COMPONENTS + green3.OFF_DIAGONAL
    unknown = [name for name in green if name not in known]
    if unknown:
        raise ValueError(f"--g-components: {', '.join(unknown)} not computed for n = 3 (the "
                         f"components {', '.join(known)})")
    if len(green) * points > MAX_GREEN_WORK:
        raise ValueError(f"--g-components: {len(green)} densities x {points} points is more "
                         f"than the {MAX_GREEN_WORK} this command is built for (about a second "
                         f"each): lower quantum.density_points or ask for fewer components")

    if state is not None:
        data = orientation_densities3(spectrum, state)
    else:
        data = mixture_orientations(spectrum, superposition, temperature)
    orient = data["orientation"]
    payload = {"kind": data["kind"], "state": state, "temperature": temperature,
               "superposition": None if superposition is None else
               {str(k): [v.real, v.imag] for k, v in superposition.items()},
               "angle_note": ("L_angle, R_angle: rotation angle omega of L and R (rad, Haar: "
                              "(1 - cos omega)/pi); L_axis1..3: cosine of the angle between "
                              "the principal axis k of C (column k of L, Q1 >= Q2 >= |Q3|) and "
                              "the third axis, R_axis1..3 the same for G (columns of R); a "
                              "state is |j m> (x) |j' m'> along the third axis"),
               "densities": {}, "integrals": data["integrals"], "warnings": data["warnings"]}
    if state is not None:
        payload.update({"energy": data["energy"], "sector": data["sector"], "m": data["m"],
                        "m_prime": data["m_prime"], "weights_L": data["weights_L"].tolist(),
                        "weights_R": data["weights_R"].tolist()})
    arrays = {"angle": orient["angle"], "t": orient["t"]}
    g_marginals = {}
    if green:
        mixture, *_ = state_mixture(spectrum, state, superposition, temperature)
        g_marginals = green3.g_densities3(spectrum, mixture, points, components=green)
        for name, m in g_marginals.items():
            arrays[f"{name}_x"], arrays[f"{name}_density"] = m.x, m.density
            payload["densities"][name] = m.as_dict()
            limit = green3.TOLERANCE if name in green3.COMPONENTS else green3.OFF_TOLERANCE
            if not m.converged:
                peak = float(np.max(np.abs(m.density)))
                payload["warnings"].append(
                    f"density of {name}: the two rules differ by {m.error / peak:.1e} of its "
                    f"peak {peak:.3g}, above the tolerance {limit:g}")
    fig, axes = plt.subplots(1, 2 + bool(green), figsize=(5 * (2 + bool(green)), 3.5))
    for name, m in g_marginals.items():
        axes[2].plot(m.x, m.density, label=_g_label(name, m))
    if green:
        axes[2].set_xlabel("component of G")
    for key, values in orient.items():
        if key in ("angle", "t"):
            continue
        x = orient["angle"] if key.endswith("angle") else orient["t"]
        arrays[key] = values
        payload["densities"][key] = {"x": x.tolist(), "density": values.tolist(),
                                     "integral": data["integrals"][key]}
        axes[0 if key.endswith("angle") else 1].plot(
            x, values, "--" if key.startswith("R") else "-", label=key.replace("_", " "))
    axes[0].set_xlabel("rotation angle (rad)")
    axes[1].set_xlabel("cosine of the axis with the third axis")
    for ax in axes:
        ax.set_ylabel("probability density")
        ax.legend(fontsize=7)
    if state is not None:
        sector = data["sector"]
        fig.suptitle(f"state {state}: (j, j') = ({sector['spin']}, {sector['vorticity']}), "
                     f"m = {data['m']}, m' = {data['m_prime']}")
    else:
        fig.suptitle(data["kind"] + (f", T = {temperature:g}" if temperature is not None else ""))
    return _save(fig, directory / "orientation.png", directory / "orientation", arrays, payload)


__all__ = [
    "write_densities", "parse_superposition", "write_orientation", "MAX_GREEN_WORK"
]
