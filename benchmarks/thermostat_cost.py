"""What a thermostat costs, measured through the command users run: ``affinebody run``.

The same config run NVE and with ``[thermostat]`` Langevin and Bussi, each with both
``splitting`` choices ("obabo", the default: one drift and one O step per step; "baoab": the O
step inside a drift split in two): the lattice of ``run_scale.py`` (default 8^3 = 512 bodies in
a periodic box, d'Alembert translational + af-is internal kinetic energy, a Morse-like pair
potential with a shape coupling cut at 2.5, neighbour list on, a dilatation term, Strang,
dt = 0.002). Reported: the seconds inside the compiled loop (compilation excluded, the summary
line of ``affinebody run``) and the ratio of each thermostatted run to the NVE one (the goal of
issue 15: at most 1.3). The runs are interleaved, one of each config per round, ``--repeat``
rounds: the ratio of a round compares runs made under about the same load (the machine may be
shared), and the spread over the rounds is printed with the fastest and the median.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/thermostat_cost.py [--side 8 --steps 2000]
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_scale import AFFINEBODY, CONFIG  # noqa: E402 - the same lattice as the scale benchmark

THERMOSTATS = {
    "NVE": "",
    **{f"langevin {splitting}": '[thermostat]\nkind = "langevin"\ntemperature = 0.1\n'
       f'friction = 1.0\nsplitting = "{splitting}"\n' for splitting in ("obabo", "baoab")},
    **{f"bussi {splitting}": '[thermostat]\nkind = "bussi"\ntemperature = 0.1\ntau = 0.1\n'
       f'splitting = "{splitting}"\n' for splitting in ("obabo", "baoab")},
}


def loop_seconds(config: Path, out: Path) -> float:
    """Seconds inside the compiled loop of one ``affinebody run`` (its summary line)."""
    done = subprocess.run([*AFFINEBODY, "run", str(config), "-o", str(out), "--overwrite"],
                          capture_output=True, text=True, check=True)
    return float(re.search(r"integrating ([\d.]+) s", done.stdout)[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=8)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        configs = {}
        for name, table in THERMOSTATS.items():
            configs[name] = folder / f"{name.replace(' ', '-')}.toml"
            configs[name].write_text(CONFIG.format(bodies=args.side**3, side=args.side,
                                                   steps=args.steps, every=args.steps) + table)
        rounds = []
        for _ in range(args.repeat):  # one run of each config per round
            rounds.append({name: loop_seconds(path, path.with_suffix(".h5"))
                           for name, path in configs.items()})
    print(f"{args.side**3} bodies, {args.steps} steps, {args.repeat} rounds:")
    for name in THERMOSTATS:
        seconds = [r[name] for r in rounds]
        ratios = sorted(r[name] / r["NVE"] for r in rounds)
        print(f"  {name:15s} loop {min(seconds):7.3f} s (fastest)   ratio to NVE: median "
              f"{statistics.median(ratios):5.2f}, range {ratios[0]:5.2f} .. {ratios[-1]:5.2f}")


if __name__ == "__main__":
    main()
