"""Benchmark: the whole ``affinebody transitions`` and ``affinebody evolve`` commands.

Rows: the start-up of the command line (``affinebody --version``), ``affinebody spectrum`` of
the config below (the solve that ``transitions`` starts with), ``affinebody transitions``
of phi11 and of G11 - trG/2 over the lowest 60 states of d'Alembert n = 2 with
V = trG/2 + 0.8 exp(-trG/2) (the solve included), and ``affinebody evolve`` of a packet of the
body of tests/test_quantum_evolution.py at hbar = 0.1 (basis 24) and 0.05 (basis 32), 400 time
points, the solve of the sector included; ``affinebody evolve --phi`` of the af-is packet with
angular momentum of tests/test_quantum_evolution.py (230 blocks of sectors, 61 times); and
``affinebody evolve`` for n = 3 (the sector (0, 0) of tests/test_quantum_evolution3.py,
anharmonic, hbar = 1 at degree 12 and hbar = 0.5 at degree 16, 401 times). Each row is timed
as a subprocess, as a user runs it.

Run: .venv/bin/python benchmarks/quantum_dynamics.py
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

AFFINEBODY = str(Path(sys.executable).parent / "affinebody")  # the installed command
SPECTRUM = """[system]
n = 2
[quantum]
hbar = 1.0
kinetic = "dalembert"
inertia = 1.0
potential = "0.5*trG + 0.8*exp(-trG/2)"
levels = 60
"""
PACKET = """[system]
n = 2
[quantum]
hbar = {hbar}
kinetic = "dalembert"
inertia = 1.0
potential = "0.5*(det - 0.5)**2 + 0.25*(trG - 4.25)**2"
basis_size = {basis}
"""


AFFINE = """[system]
n = 2
[quantum]
hbar = 0.5
kinetic = "af-is"
I = 1.0
A = 0.2
B = 0.1
potential = "0.5*(det - 3.5)**2 + 0.25*(trG - 7.3)**2"
basis_size = 14
scale = 0.4
scale_sigma = 0.3
centre = 1.0
"""
PACKET3 = """[system]
n = 3
[quantum]
hbar = {hbar}
kinetic = "dalembert"
inertia = 1.0
potential = "0.5*trG + 0.02*trG**2"
basis_size = {basis}
scale = {scale}
"""


def timed(args: list[str]) -> float:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    start = time.perf_counter()
    subprocess.run([AFFINEBODY, *args], check=True, capture_output=True, env=env)
    return time.perf_counter() - start


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        spectrum = Path(tmp) / "spectrum.toml"
        spectrum.write_text(SPECTRUM)
        rows = [("affinebody --version (start-up)", ["--version"]),
                ("spectrum (60 states; what transitions solves first)",
                 ["spectrum", str(spectrum), "--json"])]
        for op in ("phi11", "G11 - trG/2"):
            rows.append((f"transitions --operator '{op}' (60 states)",
                         ["transitions", str(spectrum), "--operator", op, "--json"]))
        for hbar, basis in ((0.1, 24), (0.05, 32)):
            packet = Path(tmp) / f"packet{basis}.toml"
            packet.write_text(PACKET.format(hbar=hbar, basis=basis))
            rows.append((f"evolve hbar = {hbar}, basis {basis}, 401 times",
                         ["evolve", str(packet), "--at", "1.85,0.45", "--time", "40",
                          "--steps", "400", "--width", f"{(hbar / 4) ** 0.5:.6f}", "--json"]))
        affine = Path(tmp) / "affine.toml"
        affine.write_text(AFFINE)
        rows.append(("evolve --phi af-is hbar = 0.5, 230 blocks, 61 times",
                     ["evolve", str(affine), "--phi", "1.9,0.3,-0.3,1.8", "--pi",
                      "0.1,0.3,-0.2,0.1", "--width", "0.3", "--time", "3", "--steps", "60",
                      "--json"]))
        for hbar, basis in ((1.0, 12), (0.5, 16)):
            packet = Path(tmp) / f"packet3_{basis}.toml"
            packet.write_text(PACKET3.format(hbar=hbar, basis=basis, scale=hbar**0.5))
            rows.append((f"evolve n = 3 hbar = {hbar}, degree {basis}, 401 times",
                         ["evolve", str(packet), "--at", "1.5,0.9,0.3", "--momentum",
                          "0,0.2,-0.1", "--time", "40", "--steps", "400", "--json"]))
        print(f"load average before: {os.getloadavg()[0]:.1f}")
        for name, args in rows:
            print(f"{name:<54} {timed(args):7.2f} s")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.parse_args()  # --help: this text, not the benchmark
    main()
