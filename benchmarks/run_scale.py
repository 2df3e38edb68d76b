"""The simulator at scale, measured through the command users run: ``affinebody run``.

System (issue "The simulator at scale"): a 3D simple cubic lattice of affine bodies, spacing 1,
in a periodic box; d'Alembert translational + af-is internal kinetic energy (I, A, B = 1, 0.2,
0.1); the pair potential ``(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2`` cut at
r = 2.5 (skin 0.3, neighbour list on) and a dilatation term; Strang, dt = 0.002.

``--lammps`` (default): 16^3 = 4096 bodies, 1000 steps, against LAMMPS Gay-Berne ellipsoids
(``in.gb`` of the shared benchmark inputs, the same 16^3 lattice, 1000 steps), each pinned to
the same core in the same run (``taskset -c 0``, one thread); then ours on both cores.
Reported: body-steps/s inside the loop (the summary line of ``affinebody run``, compilation
excluded), the whole command's wall time (start-up, set-up, compilation and output included),
and the ratios. Without ``lmp`` on the PATH (``apt-get install lammps``) it says so and still
runs ours.

``--memory N1 N2 ...``: peak resident memory of ``affinebody run`` (a few steps, one frame at
the end) for each N, and the memory per body.

``--bodies N --steps S``: one run at N bodies on whatever JAX backend is installed (a GPU
when there is one: the same command, nothing else to change), printing body-steps/s.

``--faults``: minor page faults per step of the loop of ``affinebody run`` on one core
(``--side``, ``--steps``; a run of steps / 5 steps subtracted, so set-up and output cancel).

``--pool-of-cores``: our runs with XLA's CPU pool of one thread per core (PJRT_NPROC, kept by
the command), as before ``runner.prepare_process`` gave such runs one thread: the A/B of that
choice.

``--families``: the pair term's Morse part as the built-in family (``kind = "morse"``) and as
the same f written as an expression, each on one core and on all (``--repeat`` rounds,
interleaved), printing body-steps/s: a built-in family runs the same fused host kernel.

``--renumbered``: the loop's rate from the lattice and from the same bodies numbered at random
(``--side``, ``--steps``, ``--repeat``), one core.

``--npt``: the same lattice (``--side``, ``--steps``) at constant volume and under the
stochastic cell-rescaling barostat (:data:`BAROSTAT`, isotropic; the neighbour list follows
the box) moving the box every step and every 10 steps (``--barostat-interval``), all on all
the cores, printing steps/s in the loop and their ratios to NVT; with ``--metropolis`` also
each interval with the Metropolis test of the moves (``barostat.metropolis = true``).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/run_scale.py            # vs LAMMPS, 2 cores
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/run_scale.py --repeat 3 # + the ratio's spread
    .venv/bin/python benchmarks/run_scale.py --memory 1000 10000 100000 1000000
    .venv/bin/python benchmarks/run_scale.py --npt --steps 200         # NPT vs NVT, 4096
    .venv/bin/python benchmarks/run_scale.py --npt --steps 200 --metropolis  # + tested moves
    .venv/bin/python benchmarks/run_scale.py --faults --steps 1000     # page faults per step
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/run_scale.py --families --repeat 3
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/run_scale.py --repeat 3 --pool-of-cores
    .venv/bin/python benchmarks/run_scale.py --renumbered --side 46 --steps 40 --repeat 3
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# the installed command; where only the package is on the path (a bare GPU machine with the
# package in PYTHONPATH), the same entry point through the interpreter
_SCRIPT = Path(sys.executable).parent / "affinebody"
AFFINEBODY = ([str(_SCRIPT)] if _SCRIPT.is_file() else
              [sys.executable, "-c", "import sys; from affinebody.cli import main; "
               "sys.argv[0] = 'affinebody'; main()"])
LAMMPS_INPUT = ROOT.parent / "shared" / "bench" / "lammps" / "in.gb"

CONFIG = """\
[system]
n = 3
group = "GL+"
bodies = {bodies}
box = [{side}.0, {side}.0, {side}.0]

[body]
mass = 1.0
inertia = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]

[kinetic]
translational = "dalembert"
internal = "af-is"
I = 1.0
A = 0.2
B = 0.1

[[potential]]
{pair}

[[potential]]
kind = "dilatation"
stiffness = 5.0

[initial]
generator = "lattice"
spacing = 1.0
jitter = 0.03
phi_noise = 0.05
momentum_scale = 0.1
phi_momentum_scale = 0.05

[run]
dt = 0.002
steps = {steps}
integrator = "strang"
every = {every}
neighbor_list = "on"
"""


#: The pair term of the benchmark system (the issue's affine potential).
PAIR = """kind = "pair"
expr = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 3)**2"
r_cut = 2.5"""
#: ``--families``: its Morse part as the built-in family, and the same f as an expression.
MORSE_FAMILY = """kind = "morse"
depth = 1.0
alpha = 3.0
r0 = 1.0
r_cut = 2.5"""
MORSE_EXPRESSION = """kind = "pair"
expr = "(1 - exp(-3*(r - 1)))**2 - 1"
r_cut = 2.5"""

#: The barostat of ``--npt`` (appended to :data:`CONFIG`).
BAROSTAT = """
[barostat]
pressure = 0.0
tau = 1.0
compressibility = 0.05
temperature = 0.01
coupling = "isotropic"
"""


def write_config(folder: Path, side: int, steps: int, every: int, npt: bool = False,
                 pair: str = PAIR, name: str = "lattice", interval: int = 1,
                 metropolis: bool = False) -> Path:
    tag = f"-npt{interval}{'-tested' if metropolis else ''}" if npt else ""
    path = folder / f"{name}{side}{tag}.toml"
    barostat = (BAROSTAT + (f"interval = {interval}\n" if interval != 1 else "")
                + ("metropolis = true\n" if metropolis else ""))
    path.write_text(CONFIG.format(bodies=side**3, side=side, steps=steps, every=every,
                                  pair=pair) + (barostat if npt else ""))
    return path


def timed(command: list[str], env: dict | None = None) -> tuple[float, str, int, int | None]:
    """(wall seconds, stdout + stderr, peak RSS of the command in kB, its minor page faults),
    from GNU time; without /usr/bin/time, the largest peak of any child so far (getrusage)
    and no fault count."""
    gnu_time = Path("/usr/bin/time").is_file()
    start = time.perf_counter()
    done = subprocess.run(["/usr/bin/time", "-f", "MAXRSS_KB %M FAULTS %R", *command]
                          if gnu_time else command, capture_output=True, text=True, env=env,
                          check=False)
    wall = time.perf_counter() - start
    if done.returncode:
        raise SystemExit(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
    if gnu_time:
        peak, faults = map(int, re.findall(r"MAXRSS_KB (\d+) FAULTS (\d+)", done.stderr)[-1])
        return wall, done.stdout + done.stderr, peak, faults
    return wall, done.stdout + done.stderr, resource.getrusage(
        resource.RUSAGE_CHILDREN).ru_maxrss, None


def pinned(cores: str, command: list[str]) -> list[str]:
    """``taskset -c CORES COMMAND`` where taskset exists, else the command itself."""
    return ["taskset", "-c", cores, *command] if shutil.which("taskset") else command


#: ``--pool-of-cores``: give XLA's CPU client one thread per core in our runs (its size before
#: ``runner.prepare_process`` gave such runs one thread), through PJRT_NPROC, which the
#: command keeps.
POOL_OF_CORES = False


def ours(config: Path, out: Path, cores: str, threads: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    if POOL_OF_CORES:
        env["PJRT_NPROC"] = str(threads)
    out.unlink(missing_ok=True)
    wall, text, peak, faults = timed(pinned(cores, [*AFFINEBODY, "run", str(config), "-o",
                                                    str(out), "--verbose"]), env)
    match = re.search(r"compiling ([\d.]+) s, integrating ([\d.]+) s \(([\d.e+]+) steps/s, "
                      r"([\d.e+]+) body-steps/s\)", text)
    if not match:
        raise SystemExit(f"no summary line in the output of affinebody run:\n{text}")
    return {"wall": wall, "compile": float(match[1]), "loop": float(match[2]),
            "rate": float(match[4]), "peak_kb": peak, "faults": faults, "text": text}


def lammps(folder: Path, side: int, steps: int) -> dict | None:
    if shutil.which("lmp") is None or not LAMMPS_INPUT.is_file():
        return None
    text = LAMMPS_INPUT.read_text()
    text = re.sub(r"region box block .*", f"region box block 0 {side} 0 {side} 0 {side}", text)
    text = re.sub(r"^run \d+", f"run {steps}", text, flags=re.M)
    script = folder / "in.gb"
    script.write_text(text)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    wall, output, *_ = timed(["taskset", "-c", "0", "lmp", "-in", str(script), "-log", "none"],
                             env)
    loop = float(re.search(r"Loop time of ([\d.]+)", output)[1])
    atoms = int(re.search(r"with (\d+) atoms", output)[1])
    return {"wall": wall, "loop": loop, "rate": atoms * steps / loop}


def versus_lammps(side: int, steps: int, repeat: int = 1) -> None:
    """Ours on one core, LAMMPS on the same core, ours on both cores; then, for ``repeat``
    (one core, two cores) pairs of our runs in all, ``repeat`` - 1 more pairs, each run back
    to back (the spread of the two-core ratio)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        config = write_config(folder, side, steps, every=steps // 10)
        one = ours(config, folder / "one.h5", "0", 1)
        peer = lammps(folder, side, steps)
        two = ours(config, folder / "two.h5", "0,1", 2)
        pairs = [(one, two)]
        for k in range(1, repeat):
            pairs.append((ours(config, folder / f"one{k}.h5", "0", 1),
                          ours(config, folder / f"two{k}.h5", "0,1", 2)))
    bodies = side**3
    print(f"affinebody run, {bodies} bodies, {steps} steps (phases of the one-core run):")
    print("\n".join(line for line in one["text"].splitlines() if line.startswith("  ")))
    print()
    print("| run | body-steps/s in the loop | whole command (s) | compile (s) |")
    print("|---|---|---|---|")
    print(f"| affinebody, 1 core | {one['rate']:.3g} | {one['wall']:.1f} | {one['compile']:.1f} |")
    print(f"| affinebody, 2 cores | {two['rate']:.3g} | {two['wall']:.1f} | {two['compile']:.1f} |")
    if peer is None:
        print("| LAMMPS Gay-Berne | not measured: `lmp` not found (apt-get install lammps) | | |")
    else:
        print(f"| LAMMPS Gay-Berne, 1 core | {peer['rate']:.3g} | {peer['wall']:.1f} | |")
        print()
        print(f"in the loop, ours / Gay-Berne (1 core): {one['rate'] / peer['rate']:.2f} "
              "(goal >= 2)")
        print(f"whole command, lmp / ours (1 core): {peer['wall'] / one['wall']:.2f} (goal >= 1)")
    ratios = [b["rate"] / a["rate"] for a, b in pairs]
    print(f"2 cores / 1 core (ours, in the loop): {ratios[0]:.2f} (goal >= 1.7)")
    if repeat > 1:
        print("every pair (1 core, 2 cores, ratio): " + "; ".join(
            f"{a['rate']:.3g}, {b['rate']:.3g}, {r:.2f}" for (a, b), r in zip(pairs, ratios,
                                                                             strict=True)))
        print(f"median ratio of {repeat} pairs: {statistics.median(ratios):.2f}")


def memory(sizes: list[int]) -> None:
    print("| N | peak RSS | per body | whole command (s) | body-steps/s |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for bodies in sizes:
            side = round(bodies ** (1 / 3))
            config = write_config(folder, side, steps=4, every=4)
            result = ours(config, folder / f"m{side}.h5", ",".join(map(str, sorted(
                os.sched_getaffinity(0)))), len(os.sched_getaffinity(0)))
            peak = result["peak_kb"] * 1024
            print(f"| {side**3} | {peak / 2**30:.2f} GiB | {peak / side**3 / 1024:.1f} kB | "
                  f"{result['wall']:.1f} | {result['rate']:.3g} |", flush=True)


def page_faults(side: int, steps: int) -> None:
    """Minor page faults per step of the loop on one core: the faults of a run of ``steps``
    steps minus those of a run of ``steps // 5``, over the steps between (set-up, compilation
    and output cancel)."""
    counts = {}
    with tempfile.TemporaryDirectory() as tmp:
        for length in (steps // 5, steps):
            config = write_config(Path(tmp), side, length, every=length)
            counts[length] = ours(config, Path(tmp) / f"f{length}.h5", "0", 1)["faults"]
    if None in counts.values():
        raise SystemExit("page faults need GNU time (/usr/bin/time)")
    per_step = (counts[steps] - counts[steps // 5]) / (steps - steps // 5)
    print(f"{side**3} bodies, one core: {counts[steps // 5]} minor page faults in "
          f"{steps // 5} steps, {counts[steps]} in {steps}: {per_step:.1f} per step")


def single(bodies: int, steps: int) -> None:
    side = round(bodies ** (1 / 3))
    with tempfile.TemporaryDirectory() as tmp:
        config = write_config(Path(tmp), side, steps, every=steps)
        cores = ",".join(map(str, sorted(os.sched_getaffinity(0))))
        result = ours(config, Path(tmp) / "s.h5", cores, len(os.sched_getaffinity(0)))
    device = re.search(r"^device: (.*)$", result["text"], re.M)[1]
    print(f"{side**3} bodies, {steps} steps on {device}: "
          f"{result['rate']:.3g} body-steps/s in the loop, whole command {result['wall']:.1f} s, "
          f"compile {result['compile']:.1f} s")
    print(result["text"])


def npt_versus_nvt(side: int, steps: int, intervals: list[int], metropolis: bool) -> None:
    cores = ",".join(map(str, sorted(os.sched_getaffinity(0))))
    threads = len(os.sched_getaffinity(0))
    rates = {}
    runs = [(interval, tested) for interval in intervals
            for tested in ((False, True) if metropolis else (False,))]
    with tempfile.TemporaryDirectory() as tmp:
        for interval, tested in [(None, False), *runs]:  # None: constant volume
            config = write_config(Path(tmp), side, steps, every=steps // 2,
                                  npt=interval is not None, interval=interval or 1,
                                  metropolis=tested)
            rates[interval, tested] = ours(config, Path(tmp) / f"{interval}{tested}.h5", cores,
                                           threads)
    nvt = rates[None, False]["rate"]
    print(f"affinebody run, {side**3} bodies, {steps} steps, {threads} cores, neighbour list on:")
    print("| ensemble | steps/s in the loop | whole command (s) | compile (s) | / NVT |")
    print("|---|---|---|---|---|")
    for (interval, tested), r in rates.items():
        name = ("NVT (constant box)" if interval is None else
                f"NPT (c-rescale, isotropic, barostat.interval = {interval}"
                f"{', metropolis = true' if tested else ''})")
        print(f"| {name} | {r['rate'] / side**3:.3g} | {r['wall']:.1f} | {r['compile']:.1f} "
              f"| {r['rate'] / nvt:.2f} |")


def families(side: int, steps: int, repeat: int) -> None:
    """The pair term as a built-in family (``kind = "morse"``) and as the same f written as an
    expression, each on one core and on two, ``repeat`` rounds interleaved: a family runs the
    fused host kernel as an expression does (``potentials.library``'s ``expression``)."""
    cores = ",".join(map(str, sorted(os.sched_getaffinity(0))))
    threads = len(os.sched_getaffinity(0))
    rates: dict[tuple[str, int], list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        configs = {name: write_config(folder, side, steps, every=steps // 10, pair=pair,
                                      name=name)
                   for name, pair in (("family", MORSE_FAMILY),
                                      ("expression", MORSE_EXPRESSION))}
        for k in range(repeat):
            for name, config in configs.items():
                for used, count in (("0", 1), (cores, threads)):
                    out = folder / f"{name}-{count}-{k}.h5"
                    rates.setdefault((name, count), []).append(
                        ours(config, out, used, count)["rate"])
    print(f"affinebody run, {side**3} bodies, {steps} steps, Morse pair term + dilatation "
          f"(body-steps/s in the loop, {repeat} runs each, median):")
    print("| pair term | 1 core | all cores | all / 1 |")
    print("|---|---|---|---|")
    for name, label in (("family", 'kind = "morse"'), ("expression", "the same expr")):
        one, all_ = (statistics.median(rates[(name, count)]) for count in (1, threads))
        print(f"| {label} | {one:.3g} | {all_:.3g} | {all_ / one:.2f} |")
    for count in sorted({1, threads}):
        family, expression = (statistics.median(rates[(name, count)])
                              for name in ("family", "expression"))
        print(f"family / expression, {count} core(s): {family / expression:.2f}")


def one_core_medians(folder: Path, configs: dict[str, Path], repeat: int) -> list[float]:
    """The median body-steps/s in the loop of ``affinebody run`` on one core for each config,
    ``repeat`` rounds of all of them in turn (interleaved, so drifts of the machine fall on
    every config alike), in the order of ``configs``."""
    rates: dict[str, list[float]] = {name: [] for name in configs}
    for k in range(repeat):
        for name, config in configs.items():
            rates[name].append(ours(config, folder / f"{name}-{k}.h5", "0", 1)["rate"])
    return [statistics.median(rates[name]) for name in configs]


def generators(side: int, steps: int, repeat: int) -> None:
    """The same crystal's config started by ``generator = "lattice"`` and by ``"random"``
    (positions drawn in the box, numbered cell by cell as the lattice numbers its sites), on
    one core, ``repeat`` rounds interleaved: the loop's rate should not depend on the start
    (numbered in the order drawn, the random start ran 2.4x slower at 46^3 bodies)."""
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lattice = write_config(folder, side, steps, every=steps)
        random = folder / f"random{side}.toml"
        random.write_text(lattice.read_text().replace('generator = "lattice"',
                                                      'generator = "random"')
                          .replace("\njitter = 0.03", ""))  # a key of the lattice only
        lattice_rate, random_rate = one_core_medians(
            folder, {"lattice": lattice, "random": random}, repeat)
    print(f"affinebody run, {side**3} bodies, {steps} steps, one core (body-steps/s in the loop, "
          f"{repeat} runs each, median): lattice start {lattice_rate:.3g}, random start "
          f"{random_rate:.3g}, random / lattice {random_rate / lattice_rate:.2f}")


def renumbered(side: int, steps: int, repeat: int) -> None:
    """``--renumbered``: the loop's rate of ``affinebody run`` from a lattice start and from the
    same bodies numbered at random (a two-step run's last frame, every per-body dataset of its
    H5MD file permuted alike, started from by ``[initial] file``): a liquid's numbering after
    it has diffused. One core, ``repeat`` rounds interleaved."""
    import h5py
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        lattice = write_config(folder, side, steps, every=steps)
        seed = write_config(folder, side, 2, every=2, name="seed")
        ours(seed, folder / "seed.h5", "0", 1)
        bodies = side ** 3
        permutation = np.random.default_rng(0).permutation(bodies)
        with h5py.File(folder / "seed.h5", "r+") as f:
            for item in f["particles/bodies"].values():
                if isinstance(item, h5py.Group) and "value" in item:
                    value = item["value"]
                    if value.ndim >= 2 and value.shape[1] == bodies:
                        value[...] = value[...][:, permutation]
        text = lattice.read_text()
        initial = text[text.index("[initial]"):text.index("[run]")]
        shuffled = folder / f"renumbered{side}.toml"
        shuffled.write_text(text.replace(initial, f'[initial]\nfile = "{folder / "seed.h5"}"\n\n'))
        first, other = one_core_medians(folder, {"lattice": lattice, "renumbered": shuffled},
                                        repeat)
    print(f"affinebody run, {bodies} bodies, {steps} steps, one core (body-steps/s in the loop, "
          f"{repeat} runs each, median): lattice start {first:.3g}, the same bodies numbered at "
          f"random {other:.3g}, renumbered / lattice {other / first:.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=16)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--memory", type=int, nargs="*")
    parser.add_argument("--bodies", type=int)
    parser.add_argument("--npt", action="store_true")
    parser.add_argument("--barostat-interval", type=int, nargs="+", default=[1, 10],
                        help="--npt: the barostat.interval values to run (default 1 10)")
    parser.add_argument("--metropolis", action="store_true",
                        help="--npt: also each interval with barostat.metropolis = true")
    parser.add_argument("--faults", action="store_true",
                        help="minor page faults per step of the loop (one core)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="(one core, two cores) pairs of our runs, for the ratio's spread")
    parser.add_argument("--pool-of-cores", action="store_true",
                        help="XLA's CPU pool of one thread per core in our runs (as before "
                             "runner.prepare_process)")
    parser.add_argument("--generators", action="store_true",
                        help="the loop's rate from a lattice start and from a random one")
    parser.add_argument("--renumbered", action="store_true",
                        help="the loop's rate from a lattice start and from the same bodies "
                             "numbered at random (a diffused liquid's numbering)")
    parser.add_argument("--families", action="store_true",
                        help="the Morse pair term as a built-in family and as an expression")
    args = parser.parse_args()
    global POOL_OF_CORES
    POOL_OF_CORES = args.pool_of_cores
    if args.generators:
        generators(args.side, args.steps, args.repeat)
    elif args.renumbered:
        renumbered(args.side, args.steps, args.repeat)
    elif args.families:
        families(args.side, args.steps, args.repeat)
    elif args.npt:
        npt_versus_nvt(args.side, args.steps, args.barostat_interval, args.metropolis)
    elif args.faults:
        page_faults(args.side, args.steps)
    elif args.memory:
        memory(args.memory)
    elif args.bodies:
        single(args.bodies, args.steps)
    else:
        versus_lammps(args.side, args.steps, args.repeat)


if __name__ == "__main__":
    main()
