"""Benchmark: `affinebody density` end to end, the command users run, on oscillators whose
densities are known in closed form.

n = 2 d'Alembert oscillator (V = Tr G, inertia 1.3, hbar 0.8: phi's four entries in the ground
state independent normals of variance s^2 = hbar / (2 I omega), omega = sqrt(2 / I)):

- ``--state 0``: the invariants (Q1, Q2, det phi, Tr G); Tr G / s^2 is chi-square with 4
  degrees of freedom;
- ``--state 0 --orientation``: adds the angles of L, R and the components of G; G11 is
  exponential with mean 2 s^2, G12 Laplace exp(-|y| / s^2) / (2 s^2);
- ``--state 5 --orientation``: an excited level (its G densities have no closed form here:
  only the integrals are checked);
- ``--temperature 0.3``: the thermal mixture; G11 exponential with mean 2 s_T^2,
  s_T^2 = s^2 coth(hbar omega / 2T);
- ``--temperature 0.3`` of the anharmonic V = Tr G + 0.25 (Tr G)^2 (:data:`QUARTIC`): no
  closed form (integrals only); its eigenvectors fill the basis, where the oscillator's occupy
  its first functions, so it times the thermal mixture of a general potential.

n = 3 d'Alembert oscillator (V = Tr G / 2, inertia 1, hbar 1; s^2 = 1/2): ``--state 0``
(Tr G / s^2 chi-square with 9 degrees of freedom) and ``--state 0 --orientation``.

Each command runs as a subprocess (OPENBLAS_NUM_THREADS=1); reported: the whole command
(start-up included), the start-up alone (a Python process importing the modules the command
imports, JAX float64 on: ``density --help`` imports none of them), the largest
|integral - 1| of its densities with the largest stated ``integral_error`` (G densities) and
the largest deviation from the closed forms relative to the density's peak.

Run: .venv/bin/python benchmarks/quantum_densities.py [--quick]   (--quick: n = 2 state 0 only)
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import stats

AFFINEBODY = str(Path(sys.executable).parent / "affinebody")  # the installed command
CONFIG = """[system]
n = {n}
[quantum]
kinetic = "dalembert"
inertia = {inertia}
hbar = {hbar}
potential = "{potential}"
"""
#: (n, inertia, hbar, potential, K): V = K Tr G / 2
OSCILLATORS = {2: (2, 1.3, 0.8, "trG", 2.0), 3: (3, 1.0, 1.0, "0.5*trG", 1.0)}
#: the n = 2 anharmonic potential of the last case
QUARTIC = "trG + 0.25*trG**2"


def command(args: list[str]) -> float:
    """Wall time of one `affinebody` command; exit 3 (a density flagged) is a result too."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    out = subprocess.run([AFFINEBODY, *args], capture_output=True, text=True, env=env)
    elapsed = time.perf_counter() - t0
    if out.returncode not in (0, 3):
        raise SystemExit(f"affinebody {' '.join(args)} failed:\n{out.stderr}")
    return elapsed


def startup() -> float:
    """Wall time of a process that imports what `affinebody density` imports and turns on JAX's
    float64 mode: the start-up of every command, before it reads its config."""
    code = ("import affinebody.cli, affinebody.quantum.cli as cli, affinebody.quantum.config, "
            "affinebody.quantum.spectra, affinebody.quantum.density_files; cli.enable_x64()")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True,
                   env=dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1"))
    return time.perf_counter() - t0


def variance(n: int, temperature: float | None = None) -> float:
    """s^2 of each entry of phi: hbar / (2 I omega), times coth(hbar omega / 2T) at T."""
    _, inertia, hbar, _, K = OSCILLATORS[n]
    omega = math.sqrt(K / inertia)
    s2 = hbar / (2 * inertia * omega)
    return s2 if temperature is None else s2 / math.tanh(hbar * omega / (2 * temperature))


def closed_forms(n: int, s2: float) -> dict:
    """The densities known in closed form, name -> f(x)."""
    forms = {"trG": lambda y: stats.chi2.pdf(y / s2, n * n) / s2}
    if n == 2:
        forms["G11"] = lambda y: np.exp(-y / (2 * s2)) / (2 * s2)
        forms["G12"] = lambda y: np.exp(-np.abs(y) / s2) / (2 * s2)
    return forms


def summarise(files: list[Path], forms: dict) -> tuple[float, float, float]:
    """max |integral - 1|, max stated integral_error, max |p - exact| / peak over the files."""
    deviation, stated, shape = 0.0, 0.0, 0.0
    for path in files:
        for name, d in json.loads(path.read_text())["densities"].items():
            p = np.asarray(d["density"], float)
            if "integral" in d:
                deviation = max(deviation, abs(d["integral"] - 1))
            stated = max(stated, d.get("integral_error", 0.0))
            if name in forms:
                exact = forms[name](np.asarray(d["x"], float))
                shape = max(shape, float(np.max(np.abs(p - exact)) / np.max(exact)))
    return deviation, stated, shape


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n = 2, state 0 only")
    quick = parser.parse_args().quick
    started = startup()
    cases = [(2, "state 0", ["--state", "0"], None),
             (2, "state 0 --orientation", ["--state", "0", "--orientation"], None)]
    if not quick:
        cases += [(2, "state 5 --orientation", ["--state", "5", "--orientation"], None),
                  (2, "--temperature 0.3", ["--temperature", "0.3"], 0.3),
                  (2, "--temperature 0.3 quartic", ["--temperature", "0.3"], None),
                  (3, "state 0", ["--state", "0"], None),
                  (3, "state 0 --orientation", ["--state", "0", "--orientation"], None)]
    print(f"`affinebody density CONFIG ... -o DIR` on the d'Alembert oscillator (one BLAS "
          f"thread); start-up alone {started:.2f} s")
    print(" n  arguments                  command[s]   max|integral-1|   stated   "
          "max|p-exact|/peak")
    with tempfile.TemporaryDirectory() as tmp:
        for n, label, args, temperature in cases:
            n_, inertia, hbar, potential, _ = OSCILLATORS[n]
            potential = QUARTIC if "quartic" in label else potential
            config = Path(tmp) / f"osc{n}-{len(label)}.toml"
            config.write_text(CONFIG.format(n=n_, inertia=inertia, hbar=hbar,
                                            potential=potential))
            out = Path(tmp) / f"out-{n}-{len(label)}"
            elapsed = command(["density", str(config), *args, "-o", str(out)])
            files = [f for f in (out / "densities.json", out / "orientation.json") if f.exists()]
            # closed forms: the ground state and the thermal mixture (n = 2); state 5 has none
            known = "state 0" in label or temperature is not None
            forms = closed_forms(n, variance(n, temperature)) if known else {}
            deviation, stated, shape = summarise(files, forms)
            shape_text = f"{shape:17.1e}" if forms else f"{'-':>17s}"
            print(f"{n:2d}  {label:26s} {elapsed:9.1f} {deviation:17.1e} {stated:8.0e}   "
                  f"{shape_text}", flush=True)


if __name__ == "__main__":
    main()
