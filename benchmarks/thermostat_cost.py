"""What a thermostat costs, measured through the command users run: ``affinebody run``.

The same config run NVE and with ``[thermostat]`` Langevin and Bussi, each with both
``splitting`` choices ("obabo", the default: one drift and one O step per step; "baoab": the O
step inside a drift split in two): the lattice of ``run_scale.py`` (default 8^3 = 512 bodies in
a periodic box, d'Alembert translational + af-is internal kinetic energy, a Morse-like pair
potential with a shape coupling cut at 2.5, neighbour list on, a dilatation term, Strang,
dt = 0.002). Reported: the ratio of each thermostatted run to the NVE one (the goal of issue
15: at most 1.3), two ways:

- wall: the seconds inside the compiled loop (compilation excluded, the summary line of
  ``affinebody run``);
- CPU: the CPU time of the command (user + system, all its threads) at ``--steps`` minus
  that at ``--short`` steps, the same config: start-up and compilation cancel, and CPU time
  is much less disturbed than wall time when other processes share the cores.

The runs are interleaved, one of each config per round, ``--repeat`` rounds, so the ratio of
a round compares runs made under about the same load; the median and the range over the
rounds are printed.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/thermostat_cost.py [--side 8 --steps 1100]
"""

from __future__ import annotations

import argparse
import re
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_scale import AFFINEBODY, write_config  # noqa: E402 - the scale benchmark's lattice

THERMOSTATS = {
    "NVE": "",
    **{f"langevin {splitting}": '[thermostat]\nkind = "langevin"\ntemperature = 0.1\n'
       f'friction = 1.0\nsplitting = "{splitting}"\n' for splitting in ("obabo", "baoab")},
    **{f"bussi {splitting}": '[thermostat]\nkind = "bussi"\ntemperature = 0.1\ntau = 0.1\n'
       f'splitting = "{splitting}"\n' for splitting in ("obabo", "baoab")},
}


def loop_seconds(config: Path, out: Path, steps: int) -> tuple[float, float]:
    """(seconds inside the compiled loop, CPU seconds of the whole command) of one
    ``affinebody run --steps STEPS``."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run([*AFFINEBODY, "run", str(config), "-o", str(out), "--overwrite",
                           "--steps", str(steps)], capture_output=True, text=True, check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return float(re.search(r"integrating ([\d.]+) s", done.stdout)[1]), cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=8)
    parser.add_argument("--steps", type=int, default=1100)
    parser.add_argument("--short", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        configs = {}
        for name, table in THERMOSTATS.items():
            configs[name] = write_config(folder, args.side, args.steps, args.short,
                                         name=name.replace(" ", "-"))
            configs[name].write_text(configs[name].read_text() + table)
        rounds = []
        for _ in range(args.repeat):  # one run of each config per round
            row = {}
            for name, path in configs.items():
                wall, cpu_long = loop_seconds(path, path.with_suffix(".h5"), args.steps)
                _, cpu_short = loop_seconds(path, path.with_suffix(".h5"), args.short)
                row[name] = (wall, cpu_long - cpu_short)
            rounds.append(row)
    print(f"{args.side**3} bodies, {args.steps} steps (CPU: minus {args.short}), "
          f"{args.repeat} rounds:")
    for name in THERMOSTATS:
        line = f"  {name:15s}"
        for k, what in enumerate(("wall", "CPU")):
            seconds = min(r[name][k] for r in rounds)
            ratios = sorted(r[name][k] / r["NVE"][k] for r in rounds)
            line += (f"   {what} {seconds:7.2f} s, ratio {statistics.median(ratios):4.2f} "
                     f"({ratios[0]:4.2f}..{ratios[-1]:4.2f})")
        print(line)


if __name__ == "__main__":
    main()
