"""Sweep throughput vs the number of Dask workers and the batch size (samples per task).

Workload: af-is (I = 1, A = 0.5) geodesics on SL(2) with normal random Omega_hat, 400 steps of
an exact drift, bound 1e3 (about 5 % of the samples run the whole horizon, the rest stop at
bound^2). Each (workers, batch) cell first runs a warm-up sweep of the same task shape on the
same cluster, so compile time (one per worker and task shape) is excluded; the timed sweep has
SAMPLES samples. A local cluster is started per worker count (spawn, one thread per worker).

Run: ``.venv/bin/python benchmarks/sweep_scaling.py [--samples 4000] [--workers 1 2]``
"""

from __future__ import annotations

import argparse
import os
import time

import jax

jax.config.update("jax_enable_x64", True)

from affinebody.studies import sweep_config  # noqa: E402
from affinebody.sweep import dask_client, run_sweep  # noqa: E402


def config(samples: int, batch: int):
    return sweep_config(internal="af-is", kinetic={"I": 1.0, "A": 0.5}, dt=0.25, steps=400,
                        samples=samples, batch=batch)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=4000)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, os.cpu_count() or 1])
    parser.add_argument("--batch", type=int, nargs="+", default=[16, 64, 256])
    args = parser.parse_args()
    print(f"Sweep throughput, {args.samples} samples x 400 steps, SL(2) af-is "
          f"({os.cpu_count()} cores)\n")
    print("| workers | batch | tasks | wall s | samples/s | warm-up (compile) s |")
    print("|---|---|---|---|---|---|")
    for workers in args.workers:
        with dask_client(workers=workers) as client:
            for batch in args.batch:
                start = time.perf_counter()
                run_sweep(config(batch * workers, batch), client=client)
                warm = time.perf_counter() - start
                start = time.perf_counter()
                result = run_sweep(config(args.samples, batch), client=client)
                wall = time.perf_counter() - start
                tasks = -(-args.samples // batch)
                print(f"| {workers} | {batch} | {tasks} | {wall:.2f} | "
                      f"{args.samples / wall:.0f} | {warm:.1f} |", flush=True)
                assert result.summary["failed"] == 0


if __name__ == "__main__":
    main()
