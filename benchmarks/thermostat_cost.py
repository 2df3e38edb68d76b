"""What a thermostat costs, measured through the command users run: ``affinebody run``.

The same config run three times, NVE and with ``[thermostat]`` Langevin and Bussi: the lattice
of ``run_scale.py`` (default 8^3 = 512 bodies in a periodic box, d'Alembert translational +
af-is internal kinetic energy, a Morse-like pair potential with a shape coupling cut at 2.5,
neighbour list on, a dilatation term, Strang, dt = 0.002). Reported: the seconds inside
the compiled loop (compilation excluded, the summary line of ``affinebody run``) and the
ratio of each thermostatted run to the NVE one (the goal of issue 15: at most 1.3). Each run
is repeated ``--repeat`` times and the fastest kept (the machine may be shared).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/thermostat_cost.py [--side 8 --steps 1000]
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from run_scale import AFFINEBODY, CONFIG  # noqa: E402 - the same lattice as the scale benchmark

THERMOSTATS = {
    "NVE": "",
    "langevin": '[thermostat]\nkind = "langevin"\ntemperature = 0.1\nfriction = 1.0\n',
    "bussi": '[thermostat]\nkind = "bussi"\ntemperature = 0.1\ntau = 0.1\n',
}


def loop_seconds(config: Path, out: Path) -> float:
    """Seconds inside the compiled loop of one ``affinebody run`` (its summary line)."""
    done = subprocess.run([*AFFINEBODY, "run", str(config), "-o", str(out), "--overwrite"],
                          capture_output=True, text=True, check=True)
    return float(re.search(r"integrating ([\d.]+) s", done.stdout)[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=8)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        seconds = {}
        for name, table in THERMOSTATS.items():
            config = folder / f"{name}.toml"
            config.write_text(CONFIG.format(bodies=args.side**3, side=args.side,
                                            steps=args.steps, every=args.steps) + table)
            seconds[name] = min(loop_seconds(config, folder / f"{name}.h5")
                                for _ in range(args.repeat))
    print(f"{args.side**3} bodies, {args.steps} steps (fastest of {args.repeat}):")
    for name, s in seconds.items():
        ratio = s / seconds["NVE"]
        print(f"  {name:9s} {s:8.3f} s in the loop   ratio to NVE {ratio:5.2f}")


if __name__ == "__main__":
    main()
