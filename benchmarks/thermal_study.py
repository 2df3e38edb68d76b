"""Thermal expansion, heat capacity and equation of state of the demo crystal (issue 15, item 6),
by two ``affinebody sweep`` commands on one local Dask cluster (docs/thermal-study.md).

The crystal: the 2D demo crystal (``affinebody demo``: Morse bonds, the affine pair term in D
(75) and M1 (30), the dilatation and St Venant-Kirchhoff one-body energies, af-is internal and
d'Alembert translational kinetic energies) with 36 bodies on a triangular lattice in a
periodic box, pair cut-offs at r = 2 (a square lattice stays, at kT = 0.05, in a state about
0.34 higher in potential energy per body, and reorders only at higher kT). Both scans are
NPT (Langevin thermostat, isotropic stochastic cell rescaling):

- thermal expansion and heat capacity: P0 = 0.5, kT from 0.05 to 0.30;
- equation of state: kT = 0.2, P0 from 0 to 4.

Each point has SAMPLES independent samples (thermostat and barostat noise from the sweep seed and
the sample index; the same noise at every point: common random numbers). Every sample is
equilibrated for EQUILIBRATION steps, then its observables are averaged every run.every steps;
error bars are standard errors across the samples. The derivatives d<V>/dT, d<H>/dT and d<V>/dP
are finite differences between neighbouring points taken sample by sample (the common noise
makes them sharp), with the standard error of those differences.

Run (11.6 min on the 2-core machine, loaded by other jobs): ``make study``, i.e.
``.venv/bin/python benchmarks/thermal_study.py --out docs/figures/thermal``. It writes the two
configs, each sweep's samples.csv and summary.json, study.json (derived quantities, timings) and
three PNG plots into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

AFFINEBODY = str(Path(sys.executable).parent / "affinebody")  # the installed command
COLUMNS, ROWS = 6, 6  # a triangular lattice (even ROWS: periodic in the rectangular box)
BODIES, N_DIM = COLUMNS * ROWS, 2
SPACING = 0.9  # nearest-neighbour distance of the initial lattice (<V>/N about 0.70 at 0.2)
#: time step and measurement interval: at dt = 0.005 the NPT step's error shows (at kT = 0.2,
#: P0 = 0.5: <T_int> 2.5 % above kT, var(E + P0 V) 30 % low); at 0.0025 both agree with kT and
#: with d<E + P0 V>/dT within their errors
DT, EVERY = 0.0025, 20
P_EXPANSION, KT_EOS = 0.5, 0.2
TEMPERATURES = [0.05, 0.10, 0.15, 0.20, 0.25, 0.30]
PRESSURES = [0.0, 0.5, 1.0, 2.0, 3.0, 4.0]
HARMONIC = N_DIM + N_DIM**2  # quadratic terms per body in the harmonic limit: C/N -> 6

CONFIG = """# The demo crystal (affinebody demo) with {bodies} bodies in a periodic box, NPT.
[system]
n = 2
group = "GL+"
bodies = {bodies}
box = {box}

[body]
mass = 1.0
radius = 0.35

[kinetic]
translational = "dalembert"
internal = "af-is"
I = 0.5
A = 0.1
B = 0.05

[[potential]]
kind = "morse"
depth = 1.0
alpha = 3.0
r0 = 1.0
r_cut = 2.0

[[potential]]
kind = "pair"
expr = "0.5 * exp(-D**2 / 4) * (M1 - 2)**2"
r_cut = 2.0

[[potential]]
kind = "dilatation"
stiffness = 5.0

[[potential]]
kind = "elastic"
lam = 0.5
mu = 1.0

[initial]
x = {x}

[run]
dt = {dt}
steps = {steps}
every = {every}

[thermostat]
kind = "langevin"
temperature = {kt}
friction = 1.0

[barostat]
pressure = {pressure}
tau = 1.0
compressibility = 0.1

[sweep]
samples = {samples}
batch = {samples}
seed = 2026
equilibration = {equilibration}
scan = {scan}
"""


def triangular(spacing: float) -> tuple[list[list[float]], list[float]]:
    """Centres of a COLUMNS x ROWS triangular lattice (nearest neighbours ``spacing`` apart)
    and the rectangular periodic box it fills."""
    height = float(spacing * np.sqrt(3.0) / 2.0)
    x = [[round(spacing * (c + 0.5 * (r % 2)), 6), round(height * r, 6)]
         for r in range(ROWS) for c in range(COLUMNS)]
    return x, [round(spacing * COLUMNS, 6), round(height * ROWS, 6)]


def write_config(path: Path, scan: str, args, kt: float, pressure: float) -> None:
    x, box = triangular(SPACING)
    path.write_text(CONFIG.format(bodies=BODIES, box=box, x=x, dt=DT, every=EVERY,
                                  steps=args.steps, kt=kt,
                                  pressure=pressure, samples=args.samples,
                                  equilibration=args.equilibration, scan=scan),
                    encoding="utf-8")


def sweep(config: Path, address: str, folder: Path) -> tuple[dict, float]:
    """``affinebody sweep CONFIG --scheduler ADDRESS``: its summary and wall seconds."""
    started = time.perf_counter()
    done = subprocess.run([AFFINEBODY, "sweep", str(config), "--scheduler", address,
                           "-o", str(folder), "--json"], capture_output=True, text=True)
    if done.returncode != 0:
        sys.exit(f"affinebody sweep {config} failed: {done.stderr.strip()}")
    return json.loads(done.stdout), time.perf_counter() - started


def per_sample(folder: Path, column: str) -> np.ndarray:
    """samples.csv column as [points, samples]."""
    import csv

    with (folder / "samples.csv").open(encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    points = 1 + max(int(r["point"]) for r in rows)
    samples = 1 + max(int(r["sample"]) for r in rows)
    out = np.full((points, samples), np.nan)
    for r in rows:
        if r["status"] == "sampled":
            out[int(r["point"]), int(r["sample"])] = float(r[column])
    return out


def mean_error(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error over the last axis (samples), NaN (failed) left out."""
    count = np.sum(np.isfinite(values), axis=-1)
    mean = np.nanmean(values, axis=-1)
    return mean, np.nanstd(values, axis=-1, ddof=1) / np.sqrt(count)


def paired_derivative(x, y: np.ndarray):
    """(midpoints, d y/d x, its standard error): differences of neighbouring points taken
    sample by sample (common random numbers), then averaged over the samples."""
    x = np.asarray(x, dtype=float)
    slopes = np.diff(y, axis=0) / np.diff(x)[:, None]
    mean, error = mean_error(slopes)
    return 0.5 * (x[1:] + x[:-1]), mean, error


def analyse(out: Path) -> dict:
    exp, eos = out / "expansion", out / "eos"
    s = json.loads((exp / "summary.json").read_text())["points"]
    kt = np.asarray([p["temperature"] for p in s])
    volume = per_sample(exp, "mean_volume")
    enthalpy = per_sample(exp, "mean_total_energy") + P_EXPANSION * volume
    v_mean, v_err = mean_error(volume / BODIES)
    t_mid, alpha, alpha_err = paired_derivative(kt, np.log(volume))
    _, dhdt, dhdt_err = paired_derivative(kt, enthalpy)
    expansion = {
        "pressure": P_EXPANSION, "temperature": kt.tolist(),
        "volume_per_body": v_mean.tolist(), "volume_per_body_error": v_err.tolist(),
        "alpha_temperature": t_mid.tolist(), "alpha": alpha.tolist(),
        "alpha_error": alpha_err.tolist(),
        "heat_capacity_fluctuations_per_body": [p["heat_capacity"] / BODIES for p in s],
        "heat_capacity_fluctuations_per_body_error": [p["heat_capacity_error"] / BODIES
                                                      for p in s],
        "heat_capacity_derivative_per_body": (dhdt / BODIES).tolist(),
        "heat_capacity_derivative_per_body_error": (dhdt_err / BODIES).tolist(),
        "translational_temperature": [p["mean_translational_temperature"] for p in s],
        "translational_temperature_error": [p["mean_translational_temperature_error"]
                                            for p in s],
        "internal_temperature": [p["mean_internal_temperature"] for p in s],
        "internal_temperature_error": [p["mean_internal_temperature_error"] for p in s],
        "failed": sum(p["failed"] for p in s),
    }
    s = json.loads((eos / "summary.json").read_text())["points"]
    p0 = np.asarray([p["pressure_target"] for p in s])
    volume = per_sample(eos, "mean_volume")
    v_mean, v_err = mean_error(volume / BODIES)
    p_mid, dlnv, dlnv_err = paired_derivative(p0, np.log(volume))
    eos_data = {
        "temperature": KT_EOS, "pressure": p0.tolist(),
        "volume_per_body": v_mean.tolist(), "volume_per_body_error": v_err.tolist(),
        "instantaneous_pressure": [p["mean_pressure"] for p in s],
        "instantaneous_pressure_error": [p["mean_pressure_error"] for p in s],
        "compressibility_pressure": p_mid.tolist(),
        "compressibility_derivative": (-dlnv).tolist(),
        "compressibility_derivative_error": dlnv_err.tolist(),
        "compressibility_fluctuations": [p["compressibility"] for p in s],
        "compressibility_fluctuations_error": [p["compressibility_error"] for p in s],
        "failed": sum(p["failed"] for p in s),
    }
    return {"expansion": expansion, "equation_of_state": eos_data}


def plot(results: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e, q = results["expansion"], results["equation_of_state"]
    written = []
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.errorbar(e["temperature"], e["volume_per_body"], yerr=e["volume_per_body_error"],
                  fmt="o-", capsize=3)
    left.set(xlabel="kT", ylabel="<V> / N", title=f"volume per body at P0 = {e['pressure']}")
    right.errorbar(e["alpha_temperature"], e["alpha"], yerr=e["alpha_error"], fmt="s-",
                   capsize=3, color="C1")
    right.axhline(0.0, color="0.7", lw=0.8)
    right.set(xlabel="kT", ylabel="alpha = d ln<V> / dT",
              title="thermal expansion coefficient (paired differences)")
    fig.tight_layout()
    written.append(out / "thermal_expansion.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.errorbar(e["temperature"], e["heat_capacity_fluctuations_per_body"],
                yerr=e["heat_capacity_fluctuations_per_body_error"], fmt="o", capsize=3,
                label="var(E + P0 V) / (N kT^2)")
    ax.errorbar(e["alpha_temperature"], e["heat_capacity_derivative_per_body"],
                yerr=e["heat_capacity_derivative_per_body_error"], fmt="s", capsize=3,
                label="d<E + P0 V>/dT / N")
    ax.axhline(HARMONIC, color="0.5", ls="--", lw=1, label=f"harmonic limit n + n^2 = {HARMONIC}")
    ax.set(xlabel="kT", ylabel="C_P / (N k_B)",
           title=f"heat capacity per body at P0 = {e['pressure']}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    written.append(out / "heat_capacity.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    left.errorbar(q["volume_per_body"], q["pressure"], xerr=q["volume_per_body_error"],
                  fmt="o-", capsize=3)
    left.set(xlabel="<V> / N", ylabel="P0", title=f"equation of state at kT = {q['temperature']}")
    right.errorbar(q["compressibility_pressure"], q["compressibility_derivative"],
                   yerr=q["compressibility_derivative_error"], fmt="s-", capsize=3,
                   label="-d ln<V>/dP (paired differences)")
    right.errorbar(q["pressure"], q["compressibility_fluctuations"],
                   yerr=q["compressibility_fluctuations_error"], fmt="o", capsize=3,
                   label="var(V) / (kT <V>)")
    right.set(xlabel="P0", ylabel="kappa_T", title="isothermal compressibility")
    right.legend(fontsize=8)
    fig.tight_layout()
    written.append(out / "equation_of_state.png")
    fig.savefig(written[-1], dpi=110)
    plt.close(fig)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="docs/figures/thermal")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--steps", type=int, default=7200)
    parser.add_argument("--equilibration", type=int, default=2400)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from affinebody.sweep import dask_client

    temperatures = json.dumps(TEMPERATURES)
    pressures = json.dumps(PRESSURES)
    scans = {"expansion": (f'{{ "thermostat.temperature" = {temperatures} }}', 0.2,
                           P_EXPANSION),
             "eos": (f'{{ "barostat.pressure" = {pressures} }}', KT_EOS, 0.5)}
    started = time.perf_counter()
    seconds = {}
    with tempfile.TemporaryDirectory() as scratch, dask_client(workers=args.workers) as client:
        address = client.scheduler.address
        for name, (scan, kt, pressure) in scans.items():
            config = out / f"{name}.toml"
            write_config(config, scan, args, kt, pressure)
            summary, seconds[name] = sweep(config, address, Path(scratch) / name)
            (out / name).mkdir(exist_ok=True)
            for file in ("samples.csv", "summary.json"):
                shutil.copy(Path(scratch) / name / file, out / name / file)
            print(f"{name}: {len(summary['points'])} points x {summary['samples']} samples, "
                  f"{summary['failed']} failed, {seconds[name]:.0f} s", flush=True)
    results = analyse(out)
    results["settings"] = {"bodies": BODIES, "lattice": "triangular", "spacing": SPACING,
                           "samples": args.samples, "steps": args.steps,
                           "equilibration": args.equilibration, "every": EVERY, "dt": DT,
                           "workers": args.workers}
    results["seconds"] = {**seconds, "total": time.perf_counter() - started}
    results["cpu"] = {"cores": os.cpu_count()}
    (out / "study.json").write_text(json.dumps(results, indent=1), encoding="utf-8")
    for path in plot(results, out):
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
