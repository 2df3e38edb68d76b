"""Benchmark: Ehrenfest for ``affinebody evolve --phi`` of an affine body (af-is, n = 2).

The body of tests/test_quantum_evolution.py::test_affine_matrix_packet_energy_and_rate (af-is,
I = 1, A = 0.2, B = 0.1, V = (det - 3.5)^2/2 + (trG - 7.3)^2/4) starts as a Gaussian in phi
(times det phi) around phi0 = [[1.9, 0.3], [-0.3, 1.8]] with momentum pi0 = [[0.1, 0.3],
[-0.2, 0.1]] (spin and vorticity both nonzero), of width w = 0.3 sqrt(hbar / 0.5). For each
hbar the whole command ``affinebody evolve CONFIG --phi ... --pi ... --json`` runs (hundreds of
sector blocks), and its means of q = ln Q (the singular values) and of det phi, Tr G are compared
with the classical trajectory of the same body from the simulator (affinebody.simulate.run,
the exact af-is drift, dt = 0.001; pi of the state is the transpose of the packet's pi0,
docs/theory/conventions.md). Printed per hbar: the time of the command, the captured part, the
eigenvalue error estimate weighted by the packet, and the largest distances over t in [0, 3].

Run: .venv/bin/python benchmarks/evolve_ehrenfest.py [hbar ...]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

AFFINEBODY = str(Path(sys.executable).parent / "affinebody")  # the installed command
EXPR = "0.5*(det - 3.5)**2 + 0.25*(trG - 7.3)**2"
PHI0 = np.array([[1.9, 0.3], [-0.3, 1.8]])
PI0 = np.array([[0.1, 0.3], [-0.2, 0.1]])
T, STEPS = 3.0, 60
QUANTUM = """[system]
n = 2
[quantum]
hbar = {hbar}
kinetic = "af-is"
I = 1.0
A = 0.2
B = 0.1
potential = "{expr}"
basis_size = {basis}
scale = {scale}
scale_sigma = {scale_sigma}
centre = {centre}
"""


def classical() -> tuple[np.ndarray, dict]:
    from affinebody._checks import enable_x64

    enable_x64()
    from affinebody.config import build, parse_config
    from affinebody.simulate import run

    dt, every = 0.001, int(round(T / STEPS / 0.001))
    cfg = parse_config(textwrap.dedent(f"""
        [system]
        n = 2
        bodies = 1
        [body]
        mass = 1.0
        inertia = 1.0
        [kinetic]
        internal = "af-is"
        I = 1.0
        A = 0.2
        B = 0.1
        [[potential]]
        kind = "one-body"
        expr = "{EXPR}"
        [initial]
        x = [[0.0, 0.0]]
        phi = [{PHI0.tolist()}]
        phi_momentum = [{PI0.T.tolist()}]
        [run]
        dt = {dt}
        steps = {STEPS * every}
        every = {every}
        """))
    built = build(cfg)
    traj = run(built.system, built.state, dt, STEPS * every, every=every)
    phi = np.asarray(traj.states.phi)[:, 0]
    Q = np.linalg.svd(phi, compute_uv=False)
    return np.asarray(traj.times), {"q1": np.log(Q[:, 0]), "q2": np.log(Q[:, 1]),
                                    "det": np.linalg.det(phi),
                                    "trG": np.sum(phi * phi, (1, 2))}


def main() -> None:
    hbars = [float(h) for h in sys.argv[1:]] or [0.5, 0.4, 0.3]
    times, cl = classical()
    print(f"load average before: {os.getloadavg()[0]:.1f}")
    print("hbar  basis  width   time(s)  captured      E-error   max|<q1>-q1| max|<q2>-q2| "
          "max|<det>-det| max|<trG>-trG|")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    for hbar in hbars:
        r = np.sqrt(hbar / 0.5)
        basis = int(round(14 / r))
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "packet.toml"
            path.write_text(QUANTUM.format(hbar=hbar, expr=EXPR, basis=basis, scale=0.4 * r,
                                           scale_sigma=0.3 * r, centre=1.0))
            start = time.perf_counter()
            out = subprocess.run(
                [AFFINEBODY, "evolve", str(path), "--phi", ",".join(map(str, PHI0.ravel())),
                 "--pi", ",".join(map(str, PI0.ravel())), "--width", f"{0.3 * r:.6f}",
                 "--time", str(T), "--steps", str(STEPS), "--json"],
                capture_output=True, text=True, env=env)
            seconds = time.perf_counter() - start
        if out.returncode:
            print(f"{hbar:<5} {basis:<6} {0.3 * r:<6.3f} {seconds:8.1f}  {out.stdout.strip()}"
                  f"{out.stderr.strip()}")
            continue
        data = json.loads(out.stdout)
        assert np.allclose(data["times"], times)
        errors = [np.max(np.abs(np.array(data["mean"][k]) - cl[k]))
                  for k in ("q1", "q2", "det", "trG")]
        print(f"{hbar:<5} {basis:<6} {0.3 * r:<6.3f} {seconds:8.1f}  {data['captured']:.8f}  "
              f"{data['energy_error']:.1e}   " + "   ".join(f"{e:10.4f}" for e in errors))


if __name__ == "__main__":
    main()
