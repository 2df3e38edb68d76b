"""Full time-step cost and memory vs N (expected linear), JIT compile time apart from run time.

System (the demo's model in 3D): N bodies on a jittered cubic lattice of spacing 1 in a periodic
box; d'Alembert translational + af-is internal kinetic energy (I, A, B = 0.5, 0.1, 0.05); the
demo pair potential (1 - exp(-3 (r - 1)))^2 - 1 + 0.5 exp(-D^2/4) (M1 - 3)^2, cut-off 2.5 on r,
skin 0.3, plus the one-body dilatation (k = 5) and St Venant-Kirchhoff (lam = 0.5, mu = 1)
terms. One step = Strang K(h/2) D(h) K(h/2) with the forces of the end of a step reused at the
start of the next (one force evaluation per step) and the neighbour list checked (and rebuilt
when needed) every step.

Two paths:

- ``jax``: the whole run is one compiled ``lax.scan`` (the path for GPUs): pair forces through
  ``PairPotential.energy(x, phi, neighbors)`` (closed-form kernel, ``jax.custom_vjp``) and
  ``neighbors.update`` inside the loop;
- ``numba``: a Python loop over steps calling the compiled CPU pair kernel, with the one-body
  kick, the drift and the list update as jitted JAX functions.

Each size runs in a fresh subprocess, so that its peak resident memory (``ru_maxrss``) is its
own. Run on one core:

    OMP_NUM_THREADS=1 taskset -c 0 .venv/bin/python benchmarks/scaling.py
    (options: --sizes 1000 8000 64000 512000 1000000 --steps 5 --paths numba jax)
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ.setdefault(
    "XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax import lax  # noqa: E402

from affinebody import kinetic as kin  # noqa: E402
from affinebody import neighbors as nb  # noqa: E402
from affinebody import pair_kernels as pk  # noqa: E402
from affinebody import potentials as pot  # noqa: E402
from affinebody import space as sp  # noqa: E402
from affinebody.state import State  # noqa: E402
from affinebody.system import HamiltonianSystem  # noqa: E402

R_CUT, SKIN, DT = 2.5, 0.3, 0.005
DEMO_PAIR = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2"


def make_problem(side: int):
    rng = np.random.default_rng(side)
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    box = sp.orthorhombic((float(side),) * 3)
    pair = pot.PairPotential.from_expression(DEMO_PAIR, 3, cutoff=pot.Cutoff(R_CUT), box=box)
    one_body = pot.total_potential([pot.Dilatation(5.0), pot.StVenantKirchhoff(0.5, 1.0)])
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0),
                                kin.AffineIsotropic(0.5, 0.1, 0.05))
    system = HamiltonianSystem(kinetic, one_body)  # the pair kick is added by the step below
    bodies = grid.shape[0]
    state = State(jnp.asarray(grid + 0.5 + 0.05 * rng.normal(size=grid.shape)),
                  jnp.asarray(np.eye(3) + 0.05 * rng.normal(size=(bodies, 3, 3))),
                  jnp.asarray(0.1 * rng.normal(size=(bodies, 3))),
                  jnp.asarray(0.05 * rng.normal(size=(bodies, 3, 3))))
    return box, pair, system, state


def one_size(side: int, steps: int, path: str) -> dict:
    box, pair, system, state = make_problem(side)
    bodies = side**3
    t0 = time.perf_counter()
    spec, nbrs = nb.allocate(box, state.x, state.phi, R_CUT, "r", SKIN)
    allocate_s = time.perf_counter() - t0
    row = {"N": bodies, "path": path, "pairs": int(nbrs.count), "capacity": spec.capacity,
           "allocate_s": allocate_s, "steps": steps}

    def with_forces(s, gx, gphi, h):
        return s._replace(p=s.p - h * gx, pi=s.pi - h * jnp.swapaxes(gphi, -1, -2))

    if path == "jax":
        def forces(s, lst):
            return jax.grad(lambda x, phi: pair.energy(x, phi, lst), argnums=(0, 1))(s.x, s.phi)

        def step(carry, _):
            s, lst, gx, gphi = carry
            s = system.kick(with_forces(s, gx, gphi, 0.5 * DT), 0.5 * DT)
            s = system.drift(s, DT)
            lst = nb.update(spec, lst, s.x, s.phi)
            gx, gphi = forces(s, lst)
            s = system.kick(with_forces(s, gx, gphi, 0.5 * DT), 0.5 * DT)
            return (s, lst, gx, gphi), None

        @jax.jit
        def run(s, lst):
            gx, gphi = forces(s, lst)
            (s, lst, _, _), _ = lax.scan(step, (s, lst, gx, gphi), None, length=steps)
            return s, lst

        t0 = time.perf_counter()
        compiled = run.lower(state, nbrs).compile()
        row["compile_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        final, last = jax.block_until_ready(compiled(state, nbrs))
        row["run_s"] = time.perf_counter() - t0
        row["overflow"] = int(last.overflow)
    else:
        kick1 = jax.jit(lambda s, h: system.kick(s, h))
        kick_pair = jax.jit(with_forces)
        drift = jax.jit(lambda s: system.drift(s, DT))
        update = jax.jit(nb.update, static_argnums=0)

        def forces(s, lst):
            _, gx, gphi = pk.energy_and_gradients_numba(pair, box, np.asarray(s.x),
                                                        np.asarray(s.phi), np.asarray(lst.i),
                                                        np.asarray(lst.j), int(lst.count))
            return jnp.asarray(gx), jnp.asarray(gphi)

        def run(s, lst, n_steps):
            gx, gphi = forces(s, lst)
            for _ in range(n_steps):
                s = kick1(kick_pair(s, gx, gphi, 0.5 * DT), 0.5 * DT)
                s = drift(s)
                lst = update(spec, lst, s.x, s.phi)
                gx, gphi = forces(s, lst)
                s = kick1(kick_pair(s, gx, gphi, 0.5 * DT), 0.5 * DT)
            return jax.block_until_ready(s), lst

        t0 = time.perf_counter()
        run(state, nbrs, 1)  # compiles everything
        row["compile_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        final, last = run(state, nbrs, steps)
        row["run_s"] = time.perf_counter() - t0
        row["overflow"] = int(last.overflow)
    row["step_s"] = row["run_s"] / steps
    row["body_steps_per_s"] = bodies / row["step_s"]
    row["pairs_per_s"] = row["pairs"] / row["step_s"]
    energy_end = system.hamiltonian(final) + pair.energy(final.x, final.phi, last)
    energy_start = system.hamiltonian(state) + pair.energy(state.x, state.phi, nbrs)
    row["relative_energy_change"] = float(abs(energy_end - energy_start) / abs(energy_start))
    row["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 8000, 64000, 512000,
                                                                 1000000])
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--paths", nargs="+", default=["numba", "jax"])
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(one_size(args.one, args.steps, args.paths[0])))
        return
    print(f"# full step cost vs N, load average before {os.getloadavg()}, "
          f"CPUs {sorted(os.sched_getaffinity(0))}, device {jax.devices()[0].device_kind}")
    rows = []
    for path in args.paths:
        for n_bodies in args.sizes:
            side = round(n_bodies ** (1 / 3))
            out = subprocess.run([sys.executable, __file__, "--one", str(side), "--steps",
                                  str(args.steps), "--paths", path],
                                 capture_output=True, text=True, env=os.environ)
            if out.returncode != 0:
                print(f"# N={side**3} {path}: failed\n{out.stderr[-2000:]}", flush=True)
                continue
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"# {path} N={row['N']}: {row['step_s']:.4g} s/step, "
                  f"{row['peak_rss_mb']:.0f} MB peak", flush=True)
    print("\n| path | N | pairs | s/step | body-steps/s | us/step/body | pairs/s | "
          "compile s | list allocate s | peak RSS MB | RSS/N kB |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['path']} | {r['N']} | {r['pairs']} | {r['step_s']:.4g} | "
              f"{r['body_steps_per_s']:.3g} | {1e6 * r['step_s'] / r['N']:.3g} | "
              f"{r['pairs_per_s']:.3g} | {r['compile_s']:.1f} | {r['allocate_s']:.1f} | "
              f"{r['peak_rss_mb']:.0f} | {1024 * r['peak_rss_mb'] / r['N']:.2f} |")
    print(f"\n# load average after {os.getloadavg()}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    main()
