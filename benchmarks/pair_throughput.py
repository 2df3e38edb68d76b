"""Pair-interaction throughput: pair evaluations per second per core, forces included, for the
affine pair potential of the demo in 3D, our Lennard-Jones written the same way, and LAMMPS
Gay-Berne ellipsoids and Lennard-Jones, measured in the same run.

Ours: N bodies on a simple cubic lattice of spacing 1 (density 1, jitter 0.05), phi = Id + 0.1
noise, periodic box. Affine pair (the demo's pair terms, ``examples/demo.toml``, in n = 3):

    V_KL = (1 - exp(-3 (r - 1)))^2 - 1 + 0.5 exp(-D^2 / 4) (M1 - 3)^2,

cut-off r_cut = 2.5 on r (C^2 switch from 2.25), neighbour list skin 0.3 (~42 pairs per body in
the half list). LJ: 4 (r^-12 - r^-6) with sigma = 0.9, the same cut-off, list and pairs; it is
the cost of being affine. A pair evaluation is one entry of the half list (within r_cut + skin),
as LAMMPS counts "Total # of neighbors". Each figure is the best of ``--repeats`` evaluations of
energy and all generalised forces (dV/dx, dV/dphi); compile time is reported separately.

LAMMPS: the inputs of ``../shared/bench/lammps`` (32000 LJ atoms; 32768 Gay-Berne ellipsoids),
pair evaluations per second = neighbors * steps / loop time (that README). Without ``lmp`` on
the PATH the LAMMPS columns say so and the ratios are omitted.

Run on one core, with the load stated:

    OMP_NUM_THREADS=1 taskset -c 0 .venv/bin/python benchmarks/pair_throughput.py

Options: ``--sizes 1000 8000 ...``, ``--repeats 3``, ``--gb-steps 200`` (fewer: a shorter GB
run), ``--lammps-dir DIR``, ``--no-jax`` (skip the JAX kernel), ``--json FILE``.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import re
import shutil
import subprocess
import sys
import tempfile
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

from affinebody import neighbors as nb  # noqa: E402
from affinebody import pair_kernels as pk  # noqa: E402
from affinebody import potentials as pot  # noqa: E402
from affinebody import space as sp  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
LAMMPS_DIR = ROOT.parent / "shared" / "bench" / "lammps"
R_CUT, SKIN = 2.5, 0.3
AFFINE_EXPR = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2"


def lattice_system(side: int, seed: int = 0):
    """side^3 bodies on a jittered cubic lattice in a periodic box of edge ``side``."""
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = grid + 0.5 + 0.05 * rng.normal(size=grid.shape)
    phi = np.eye(3) + 0.1 * rng.normal(size=(grid.shape[0], 3, 3))
    return sp.orthorhombic((float(side),) * 3), x, phi


def potentials(box):
    affine = pot.PairPotential.from_expression(AFFINE_EXPR, 3, cutoff=pot.Cutoff(R_CUT), box=box)
    lj = pot.LennardJones(1.0, 0.9, cutoff=pot.Cutoff(R_CUT), box=box)
    return {"affine": affine, "lj": lj}


def best_time(call, repeats: int) -> tuple[float, float]:
    """(first call incl. compilation, best of ``repeats`` further calls), seconds."""
    t0 = time.perf_counter()
    call()
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - t0)
    return first, best


def measure_ours(side: int, repeats: int, use_jax: bool) -> dict:
    box, x, phi = lattice_system(side)
    n_bodies = x.shape[0]
    t0 = time.perf_counter()
    spec, nbrs = nb.allocate(box, x, phi, R_CUT, "r", SKIN)
    allocate_s = time.perf_counter() - t0
    xj, phij = jnp.asarray(x), jnp.asarray(phi)
    _, build_s = best_time(lambda: jax.block_until_ready(nb.build_jit(spec, xj, phij)), 1)
    pairs = int(nbrs.count)
    i_np, j_np = np.asarray(nbrs.i), np.asarray(nbrs.j)
    row = {"N": n_bodies, "pairs": pairs, "pairs_per_body": pairs / n_bodies,
           "allocate_s": allocate_s, "build_s": build_s}
    for name, potential in potentials(box).items():
        first, best = best_time(
            lambda p=potential: pk.energy_and_gradients_numba(p, box, x, phi, i_np, j_np, pairs),
            repeats)
        row[f"{name}_numba_s"] = best
        row[f"{name}_numba_first_s"] = first
        row[f"{name}_numba_pairs_per_s"] = pairs / best
        if use_jax:
            first, best = best_time(lambda p=potential: jax.block_until_ready(
                pk.energy_and_gradients_jit(p, box, xj, phij, nbrs.i, nbrs.j, nbrs.count)),
                repeats)
            row[f"{name}_jax_s"] = best
            row[f"{name}_jax_compile_s"] = first - best
            row[f"{name}_jax_pairs_per_s"] = pairs / best
    return row


def run_lammps(input_name: str, steps: int | None, directory: pathlib.Path) -> dict | None:
    """Run one LAMMPS input on one thread; None if ``lmp`` is missing."""
    lmp = shutil.which("lmp") or shutil.which("lmp_serial")
    if lmp is None:
        return None
    text = (directory / input_name).read_text()
    if steps is not None:
        text = re.sub(r"^run\s+\d+", f"run {steps}", text, flags=re.M)
    with tempfile.TemporaryDirectory() as work:
        path = pathlib.Path(work) / input_name
        path.write_text(text)
        env = dict(os.environ, OMP_NUM_THREADS="1")
        out = subprocess.run([lmp, "-in", str(path), "-log", "none"], cwd=work, env=env,
                             capture_output=True, text=True, check=True).stdout
    loop = re.search(r"Loop time of ([0-9.eE+-]+) on \d+ procs for (\d+) steps with (\d+) atoms",
                     out)
    neighbors = re.search(r"Total # of neighbors = (\d+)", out)
    if loop is None or neighbors is None:
        raise RuntimeError(f"could not read the LAMMPS output of {input_name}:\n{out[-2000:]}")
    seconds, n_steps, atoms = float(loop.group(1)), int(loop.group(2)), int(loop.group(3))
    pairs = int(neighbors.group(1))
    return {"input": input_name, "atoms": atoms, "steps": n_steps, "loop_s": seconds,
            "pairs": pairs, "pairs_per_s": pairs * n_steps / seconds,
            "atom_steps_per_s": atoms * n_steps / seconds}


def fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+",
                        default=[1000, 8000, 64000, 512000, 1000000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--gb-steps", type=int, default=None)
    parser.add_argument("--lammps-dir", type=pathlib.Path, default=LAMMPS_DIR)
    parser.add_argument("--no-jax", action="store_true")
    parser.add_argument("--json", type=pathlib.Path, default=None)
    args = parser.parse_args(argv)
    if not pk.numba_available():
        sys.exit("numba is not installed: pip install numba (the compiled CPU kernel)")
    affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    print(f"# pair throughput, one thread, CPUs allowed {affinity}, "
          f"load average before {os.getloadavg()}")
    results = {"load_before": os.getloadavg(), "cpus": affinity, "ours": [], "lammps": {}}
    lammps_found = shutil.which("lmp") or shutil.which("lmp_serial")
    if not lammps_found:
        print("# LAMMPS (lmp) not found on the PATH: install it (apt-get install lammps) for the "
              "peer columns; ratios are omitted")
    else:
        for name, steps in (("in.lj", None), ("in.gb", args.gb_steps)):
            results["lammps"][name] = run_lammps(name, steps, args.lammps_dir)
            r = results["lammps"][name]
            print(f"# LAMMPS {name}: {r['atoms']} atoms, {r['steps']} steps, {r['pairs']} pairs, "
                  f"loop {r['loop_s']:.3f} s -> {r['pairs_per_s']:.3g} pairs/s")
    for n_bodies in args.sizes:
        side = round(n_bodies ** (1 / 3))
        row = measure_ours(side, args.repeats, not args.no_jax)
        results["ours"].append(row)
        print(f"# N={row['N']}: {row['pairs']} pairs, affine {row['affine_numba_pairs_per_s']:.3g}"
              f"/s, LJ {row['lj_numba_pairs_per_s']:.3g}/s", flush=True)
    if lammps_found:  # the peers once more, after ours: the load may have changed
        for name, steps in (("in.lj", None), ("in.gb", args.gb_steps)):
            again = run_lammps(name, steps, args.lammps_dir)
            first = results["lammps"][name]
            if again["pairs_per_s"] > first["pairs_per_s"]:
                results["lammps"][name] = again
            results["lammps"][name]["pairs_per_s_runs"] = [first["pairs_per_s"],
                                                           again["pairs_per_s"]]
    results["load_after"] = os.getloadavg()
    gb = results["lammps"].get("in.gb")
    lj = results["lammps"].get("in.lj")
    gb_rate = gb["pairs_per_s"] if gb else None
    lj_rate = lj["pairs_per_s"] if lj else None
    print()
    print("| N | pairs/body | ours affine pairs/s | ours LJ pairs/s | LAMMPS GB pairs/s | "
          "LAMMPS LJ pairs/s | affine / GB (goal >= 2) | LAMMPS LJ / ours LJ (goal <= 3) | "
          "LJ / affine (ours) | JAX affine pairs/s | JAX LJ pairs/s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for row in results["ours"]:
        affine, ljr = row["affine_numba_pairs_per_s"], row["lj_numba_pairs_per_s"]
        print(f"| {row['N']} | {row['pairs_per_body']:.1f} | {fmt(affine)} | {fmt(ljr)} | "
              f"{fmt(gb_rate)} | {fmt(lj_rate)} | "
              f"{fmt(affine / gb_rate) if gb_rate else 'n/a'} | "
              f"{fmt(lj_rate / ljr) if lj_rate else 'n/a'} | {fmt(ljr / affine)} | "
              f"{fmt(row.get('affine_jax_pairs_per_s'))} | {fmt(row.get('lj_jax_pairs_per_s'))} |")
    print()
    print("| N | list allocate s | list build s | affine numba first call s | "
          "LJ numba first call s | JAX affine compile s | JAX LJ compile s |")
    print("|---|---|---|---|---|---|---|")
    for row in results["ours"]:
        print(f"| {row['N']} | {row['allocate_s']:.2f} | {row['build_s']:.3f} | "
              f"{row['affine_numba_first_s']:.2f} | {row['lj_numba_first_s']:.2f} | "
              f"{fmt(row.get('affine_jax_compile_s'))} | {fmt(row.get('lj_jax_compile_s'))} |")
    print(f"\n# load average after {results['load_after']}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
