"""Benchmark: completeness of the n = 2 af-is spectrum of issue 20.

af-is, I = 1, A = 0.2, B = 0.1, hbar = 1, V = 0.5 (q1 + q2)^2 - 24 Q1 Q2 / (Q1 + Q2)^2: a
harmonic well in ln det phi plus an attractive well in the shear x = q1 - q2, whose lowest level
per shell max(|s|, |k|) is not monotone. The exact spectrum is the closed form (the sigma
oscillator plus the Poeschl-Teller levels of the shear operator, docs/theory/two-polar.md; the
same closed form is checked against finite volumes in tests/test_quantum_completeness.py).

For K = 30 and 60 at the default basis (24) and at basis 40, and for K = 60 with max_spin = 80:
time, shells searched, blocks skipped by their bound, whether the list is certified, the
number of unconverged states (NaN in their place), the worst error of the converged ones, and
the number of genuine levels among the K lowest that are missing or replaced (must be 0).

Run: .venv/bin/python benchmarks/quantum_completeness.py [--quick]
(each row is the whole ``affinebody spectrum`` command, start-up included)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_quantum_completeness import SHEAR_WELL, shear_well_exact  # noqa: E402

AFFINEBODY = str(Path(sys.executable).parent / "affinebody")  # the installed command
CONFIG = """[system]
n = 2
[quantum]
hbar = 1.0
kinetic = "af-is"
I = 1.0
A = 0.2
B = 0.1
potential = "{potential}"
basis_size = {basis}
max_spin = {max_spin}
"""
ROWS = [(30, 24, 40), (60, 24, 40), (60, 24, 80), (30, 40, 40), (60, 40, 80)]


def main() -> None:
    """``affinebody spectrum CONFIG --levels K --json`` for each row (``--quick``: the first and
    third), timed as a whole command, its list compared with the closed form."""
    exact = np.array([E for E, _, _ in shear_well_exact(max_shell=90, top=3.0)])
    rows = [ROWS[0], ROWS[2]] if "--quick" in sys.argv else ROWS
    print(f"{'K':>3} {'basis':>5} {'max_spin':>8} {'command s':>9} {'certified':>9} "
          f"{'unknown':>7} {'worst err':>9} {'wrong':>5}")
    with tempfile.TemporaryDirectory() as tmp:
        for K, basis, max_spin in rows:
            path = Path(tmp) / f"c{K}_{basis}_{max_spin}.toml"
            path.write_text(CONFIG.format(potential=SHEAR_WELL, basis=basis,
                                          max_spin=max_spin))
            t0 = time.perf_counter()
            done = subprocess.run([AFFINEBODY, "spectrum", str(path), "--levels", str(K),
                                   "--json"], capture_output=True, text=True, check=True,
                                  env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
            elapsed = time.perf_counter() - t0
            data = json.loads(done.stdout)
            got = np.array([np.nan if e is None else e for e in data["energies"]], dtype=float)
            known = ~np.isnan(got)
            diff = np.abs(got[known] - exact[: len(got)][known])
            worst = float(diff.max()) if known.any() else np.nan
            wrong = int(np.sum(diff > 1e-6)) + (K - len(got))
            print(f"{K:>3} {basis:>5} {max_spin:>8} {elapsed:>9.1f} {data['certified']!s:>9} "
                  f"{int((~known).sum()):>7} {worst:>9.1e} {wrong:>5}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="only the first and third rows")
    parser.parse_args()  # --help: this text, not the benchmark
    main()
