"""Benchmark: Ehrenfest for ``affinebody evolve`` of an affine body (af-is, n = 2).

Two packets of the af-is body (I = 1, A = 0.2, B = 0.1), each run through the whole command
``affinebody evolve CONFIG --json`` at several hbar, their means compared with the classical
trajectory of the same body from the simulator (affinebody.simulate.run with the exact af-is
drift; pi of the state is the transpose of the packet's pi0, docs/theory/conventions.md).
Printed per hbar: the time of the command, the captured part, the eigenvalue error estimate
weighted by the packet, and the largest distances over the run between the means of q1, q2
(q = ln Q, Q the singular values), det phi, Tr G and their classical values.

``at`` (the body of tests/test_quantum_evolution.py::test_affine_ehrenfest_against_the_simulator,
carried to smaller hbar): the sector spin = vorticity = 0 packet ``--at q1,q2`` of width
sqrt(hbar/3) at rest at (sigma, x) = (q1 + q2, q1 - q2) = (0.3, 2.0) in
V = (sigma)^2/2 + (x - 1.5)^2/2 + 0.05 (x - 1.5)^4 (in the quantum config as an expression in
q1, q2; for the simulator in det and trG: sigma = ln det, x = acosh(trG/(2 det))),
t in [0, 10]; the classical body starts at phi = diag(e^q0) at rest and stays diagonal.

``phi`` (the body of tests/test_quantum_evolution.py::test_affine_matrix_packet_energy_and_rate):
V = (det - 3.5)^2/2 + (trG - 7.3)^2/4, a Gaussian in phi (times det phi) around
phi0 = [[1.9, 0.3], [-0.3, 1.8]] with momentum pi0 = [[0.1, 0.3], [-0.2, 0.1]] (spin and
vorticity both nonzero), of width w = 0.3 sqrt(hbar / 0.5), ``--phi ... --pi ...`` (hundreds
of sector blocks), t in [0, 3].

``n3`` (measured for docs/quantum-transitions.md, n = 3): the sector (0, 0) packet
``--at q1,q2,q3`` (the Weyl-symmetrised Gaussian in q, width sqrt(hbar/2.5)) at rest at
q0 = (0.567, 0.037, -0.403) in V = sigma^2/2 + 0.03 (sum cosh 2y - A*)^2 + 0.3 (sum sinh 2y)^2
(y = q - sigma/3 the traceless part, minimum at y = 0.35 (1, 0, -1), A* its sum cosh 2y; for the
simulator sum e^{2y} = K1/det^(2/3) and sum e^{-2y} = (K1^2 - K2)/(2 det^(4/3))), degree 12,
14, 16 at hbar 0.2, 0.14, 0.1 with the basis Gaussian matched to the packet (scale sqrt2 w,
scale_sigma sqrt6 w), t in [0, 10]; the classical body starts at diag(e^q0) at rest.

Run: .venv/bin/python benchmarks/evolve_ehrenfest.py [at|phi|n3] [hbar ...]   (default: at)
"""

from __future__ import annotations

import argparse
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
QUANTUM = """[system]
n = {n}
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
CLASSICAL = """
[system]
n = {n}
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
expr = "{expr}"
[initial]
x = [{x}]
phi = [{phi}]
phi_momentum = [{pi}]
[run]
dt = {dt}
steps = {steps}
every = {every}
"""

# the sector (0, 0) packet at rest
AT_S0, AT_X0, AT_QUARTIC = 0.0, 1.5, 0.05
AT_START = (0.3, 2.0)  # (sigma, x)
AT_EXPR = (f"0.5*(q1 + q2 - {AT_S0})**2 + 0.5*(q1 - q2 - {AT_X0})**2 "
           f"+ {AT_QUARTIC}*(q1 - q2 - {AT_X0})**4")
AT_CLASSICAL = (f"0.5*(log(det) - {AT_S0})**2 + 0.5*(acosh(trG/(2*det)) - {AT_X0})**2 "
                f"+ {AT_QUARTIC}*(acosh(trG/(2*det)) - {AT_X0})**4")
# n = 3: the sector (0, 0) packet at rest
N3_A, N3_ALPHA, N3_BETA = 0.35, 0.03, 0.3
N3_TARGET = float(np.sum(np.cosh(2 * N3_A * np.array([1.0, 0.0, -1.0]))))  # sum cosh 2y at min
N3_START = (0.2 / 3 + 0.5, 0.2 / 3 - 0.03, 0.2 / 3 - 0.47)
_Y = [f"2*(q{a} - (q1 + q2 + q3)/3)" for a in (1, 2, 3)]
N3_EXPR = (f"0.5*(q1 + q2 + q3)**2 "
           f"+ {N3_ALPHA}*({' + '.join(f'cosh({y})' for y in _Y)} - {N3_TARGET!r})**2 "
           f"+ {N3_BETA}*({' + '.join(f'sinh({y})' for y in _Y)})**2")
_UP, _DOWN = "(K1/det**(2/3))", "((K1**2 - K2)/(2*det**(4/3)))"
N3_CLASSICAL = (f"0.5*log(det)**2 + {N3_ALPHA}*(({_UP} + {_DOWN})/2 - {N3_TARGET!r})**2 "
                f"+ {N3_BETA}*(({_UP} - {_DOWN})/2)**2")
# the packet with angular momentum
PHI_EXPR = "0.5*(det - 3.5)**2 + 0.25*(trG - 7.3)**2"
PHI0 = np.array([[1.9, 0.3], [-0.3, 1.8]])
PI0 = np.array([[0.1, 0.3], [-0.2, 0.1]])


def classical(expr: str, phi0: np.ndarray, pi0: np.ndarray, T: float, steps: int
              ) -> tuple[np.ndarray, dict]:
    """The simulator's trajectory at ``steps`` + 1 frames over [0, T] (dt = 0.001)."""
    from affinebody._checks import enable_x64

    enable_x64()
    from affinebody.config import build, parse_config
    from affinebody.simulate import run

    n = len(phi0)
    dt, every = 0.001, int(round(T / steps / 0.001))
    cfg = parse_config(textwrap.dedent(CLASSICAL.format(
        n=n, x=[0.0] * n, expr=expr, phi=phi0.tolist(), pi=pi0.T.tolist(), dt=dt,
        steps=steps * every, every=every)))
    built = build(cfg)
    traj = run(built.system, built.state, dt, steps * every, every=every)
    phi = np.asarray(traj.states.phi)[:, 0]
    Q = np.linalg.svd(phi, compute_uv=False)
    out = {f"q{a + 1}": np.log(Q[:, a]) for a in range(n)}
    out.update(det=np.linalg.det(phi), trG=np.sum(phi * phi, (1, 2)))
    return np.asarray(traj.times), out


def command(hbar: float, basis: int, scales: tuple, expr: str, args: list[str], n: int = 2
            ) -> tuple[float, subprocess.CompletedProcess]:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "packet.toml"
        path.write_text(QUANTUM.format(n=n, hbar=hbar, expr=expr, basis=basis, scale=scales[0],
                                       scale_sigma=scales[1], centre=scales[2]))
        start = time.perf_counter()
        out = subprocess.run([AFFINEBODY, "evolve", str(path), *args, "--json"],
                             capture_output=True, text=True, env=env)
        return time.perf_counter() - start, out


def report(hbar: float, basis: int, width: float, seconds: float, out, times, cl) -> None:
    if out.returncode:
        print(f"{hbar:<6} {basis:<6} {width:<6.3f} {seconds:8.1f}  {out.stdout.strip()}"
              f"{out.stderr.strip()}")
        return
    data = json.loads(out.stdout)
    assert np.allclose(data["times"], times)
    errors = [np.max(np.abs(np.array(data["mean"][k]) - cl[k])) for k in data["mean"]]
    print(f"{hbar:<6} {basis:<6} {width:<6.3f} {seconds:8.1f}  {data['captured']:.10f}  "
          f"{data['energy_error']:.1e}   " + "   ".join(f"{e:10.4f}" for e in errors))


HEADER = ("hbar   basis  width   time(s)  captured        E-error   max|<q1>-q1| max|<q2>-q2| "
          "max|<det>-det| max|<trG>-trG|")


def at_packets(hbars: list[float]) -> None:
    T, steps = 10.0, 100
    s, x = AT_START
    q0 = np.array([(s + x) / 2, (s - x) / 2])
    times, cl = classical(AT_CLASSICAL, np.diag(np.exp(q0)), np.zeros((2, 2)), T, steps)
    print(f"sector (0, 0) packet at q0 = {q0.tolist()} at rest, t in [0, {T}]; "
          f"load average before: {os.getloadavg()[0]:.1f}")
    print(HEADER)
    for hbar in hbars:
        r = np.sqrt(hbar / 0.1)
        basis = min(int(round(20 / r)), 48)
        width = float(np.sqrt(hbar / 3))
        seconds, out = command(hbar, basis, (0.57 * r, 0.35 * r, AT_S0), AT_EXPR,
                               ["--at", ",".join(map(str, q0)), "--width", f"{width:.8f}",
                                "--time", str(T), "--steps", str(steps)])
        report(hbar, basis, width, seconds, out, times, cl)


def phi_packets(hbars: list[float]) -> None:
    T, steps = 3.0, 60
    times, cl = classical(PHI_EXPR, PHI0, PI0, T, steps)
    print(f"packet around phi0 = {PHI0.tolist()}, pi0 = {PI0.tolist()}, t in [0, {T}]; "
          f"load average before: {os.getloadavg()[0]:.1f}")
    print(HEADER)
    for hbar in hbars:
        r = np.sqrt(hbar / 0.5)
        basis = int(round(14 / r))
        width = 0.3 * r
        seconds, out = command(hbar, basis, (0.4 * r, 0.3 * r, 1.0), PHI_EXPR,
                               ["--phi", ",".join(map(str, PHI0.ravel())), "--pi",
                                ",".join(map(str, PI0.ravel())), "--width", f"{width:.6f}",
                                "--time", str(T), "--steps", str(steps)])
        report(hbar, basis, width, seconds, out, times, cl)


def n3_packets(hbars: list[float]) -> None:
    T, steps = 10.0, 100
    q0 = np.array(N3_START)
    times, cl = classical(N3_CLASSICAL, np.diag(np.exp(q0)), np.zeros((3, 3)), T, steps)
    print(f"n = 3 sector (0, 0) packet at q0 = {q0.round(4).tolist()} at rest, t in [0, {T}]; "
          f"load average before: {os.getloadavg()[0]:.1f}")
    print(HEADER.replace("max|<det>", "max|<q3>-q3| max|<det>"))
    degrees = {0.2: 12, 0.14: 14, 0.1: 16}
    for hbar in hbars:
        degree = degrees.get(hbar, 16)
        width = float(np.sqrt(hbar / 2.5))
        seconds, out = command(hbar, degree, (np.sqrt(2) * width, np.sqrt(6) * width, 0.0),
                               N3_EXPR, ["--at", ",".join(map(str, q0)), "--width",
                                         f"{width:.8f}", "--time", str(T), "--steps",
                                         str(steps)], n=3)
        report(hbar, degree, width, seconds, out, times, cl)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", nargs="?", choices=("at", "phi", "n3"), default="at",
                        help="packets of --at (n = 2), of --phi (af-is), or n = 3")
    parser.add_argument("hbars", nargs="*", type=float, help="hbar values (default: a row each)")
    args = parser.parse_args()
    kind, hbars = args.kind, args.hbars
    if kind == "at":
        at_packets(hbars or [0.1, 0.07, 0.05, 0.035, 0.025])
    elif kind == "n3":
        n3_packets(hbars or [0.2, 0.14, 0.1])
    else:
        phi_packets(hbars or [0.5, 0.4, 0.3])


if __name__ == "__main__":
    main()
