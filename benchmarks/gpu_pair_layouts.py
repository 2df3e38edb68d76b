"""Which layout of the pair sum suits a GPU: the product's half list with scatter-adds against
variants, timed as ``system.forces`` of run_scale.py's system (a decision aid, not a figure).

- ``half list (product)``: pair_kernels.energy_and_gradients as the product runs it, and
  with ``--against FILE`` the same function of another version of pair_kernels.py;
- ``no scatter``: the same pair arithmetic with its per-pair results summed instead of
  scattered (not a force: how much of the time the float64 scatter-adds take);
- ``full dense list``: every body's partners in a row of a [N, K] table (each pair twice), only
  the body's own side of each pair computed and summed along the row: no scatter at all.

    python benchmarks/gpu_pair_layouts.py --bodies 1000000
    git show REV:src/affinebody/pair_kernels.py > /tmp/pk_rev.py
    python benchmarks/gpu_pair_layouts.py --bodies 1000000 --against /tmp/pk_rev.py
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run_scale import write_config  # noqa: E402
from step_phases import timed  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=int, default=4096)
    parser.add_argument("--rows", type=int, nargs="*", default=[15],
                        help="log2 of bodies per pass of the dense variant")
    parser.add_argument("--pair-chunks", type=int, nargs="*", default=[20, 22],
                        help="log2 of pairs per pass of the half-list variants")
    parser.add_argument("--against", help="another pair_kernels.py (an earlier version) whose "
                        "JAX kernel to time beside the product's")
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp
    from jax import lax

    jax.config.update("jax_enable_x64", True)
    from affinebody import pair_kernels as pk
    from affinebody.config import build, load_config
    from affinebody.runner import prepare_process

    side = round(args.bodies ** (1 / 3))
    with tempfile.TemporaryDirectory() as tmp:
        config = load_config(write_config(Path(tmp), side, steps=10, every=10))
    prepare_process(config)
    built = build(config)
    system, state = built.system, built.state
    _, lst = built.neighbors
    bodies = state.x.shape[0]
    print(f"{bodies} bodies on {jax.devices()[0].device_kind}, {int(lst.count)} pairs", flush=True)

    pk.host_kernel_in_use = lambda: False  # the JAX kernel, as on a GPU
    product = pk.energy_and_gradients
    reference = jax.jit(system.forces)(state, lst)

    def report(name, result, first, median):
        error = max(float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(b)))
                    for a, b in zip(result, reference, strict=True))
        print(f"  {name:<30} {median * 1e3:9.3f} ms  (first {first:.1f} s, "
              f"rel. difference {error:.1e})", flush=True)

    def time_variant(name, kernel):
        pk.energy_and_gradients = kernel
        try:
            function = jax.jit(lambda s, nbrs: system.forces(s, nbrs))
            result = function(state, lst)
            report(name, result, *timed(function, state, lst))
        finally:
            pk.energy_and_gradients = product

    for log2 in args.pair_chunks:
        time_variant(f"half list (product), 2^{log2}", partial(product, chunk=1 << log2))
    if args.against:
        spec = importlib.util.spec_from_file_location("previous_pair_kernels", args.against)
        previous = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(previous)
        for log2 in args.pair_chunks:
            time_variant(f"{Path(args.against).name}, 2^{log2}",
                         partial(previous.energy_and_gradients, chunk=1 << log2))

    def no_scatter(pot, space, x, phi, i, j, count, chunk=None, cell=None):
        bodies, n, binv, det, (i_all, j_all, index) = pk._pair_pass(pot, x, phi, i, j, chunk)

        def step(carry, block):
            ii, jj, valid = pk._valid_pairs(*block, count, bodies)
            e, parts = pk._chunk_contributions(pot, space, n, x, phi, binv, det, ii, jj, valid,
                                               cell)
            return carry + e + sum(jnp.sum(p) for p in parts) * 1e-300, None

        energy, _ = lax.scan(step, jnp.zeros(()), (i_all, j_all, index))
        return energy, jnp.zeros_like(x) + energy * 0, jnp.zeros_like(phi)

    for log2 in args.pair_chunks:
        time_variant(f"no scatter (not a force), 2^{log2}", partial(no_scatter, chunk=1 << log2))

    # the full list as a dense table [N, K]: partners of body b in row b, padding = N
    count = int(lst.count)
    first = jnp.concatenate([lst.i[:count], lst.j[:count]])
    second = jnp.concatenate([lst.j[:count], lst.i[:count]])
    order = jnp.argsort(first, stable=True)
    first, second = first[order], second[order]
    per_body = jnp.bincount(first, length=bodies)
    starts = jnp.cumsum(per_body) - per_body
    column = jnp.arange(first.shape[0]) - starts[first]
    width = int(jnp.max(per_body))
    table = jnp.full((bodies, width), bodies, jnp.int32).at[first, column].set(second)
    print(f"  dense table: {bodies} x {width} ({2 * count / bodies:.1f} partners per body)",
          flush=True)

    for log2 in args.rows:
        rows = min(1 << log2, bodies)

        def dense(pot, space, x, phi, i, j, count, chunk=None, cell=None, rows=rows):
            bodies, n = x.shape
            binv, det = pk.linalg.inv(phi), pk.linalg.det(phi)
            blocks = -(-bodies // rows)
            padded = jnp.concatenate(
                [table, jnp.full((blocks * rows - bodies, width), bodies, jnp.int32)])

            def block(start):
                partners = lax.dynamic_slice_in_dim(padded, start, rows).reshape(-1)
                own = (start + jnp.arange(rows)).repeat(width)
                valid = (partners < bodies) & (own < bodies)
                ii = jnp.where(valid, own, 0)
                jj = jnp.where(valid, partners, jnp.minimum(1, bodies - 1))
                e, (g_u, d_phik, _) = pk._chunk_contributions(
                    pot, space, n, x, phi, binv, det, ii, jj, valid, cell)
                fold = lambda a: jnp.sum(a.reshape((rows, width) + a.shape[1:]), 1)  # noqa
                return 0.5 * e, fold(g_u), fold(d_phik)

            e, g_x, g_phi = lax.map(block, jnp.arange(blocks) * rows)
            cut = lambda a: a.reshape((-1,) + a.shape[2:])[:bodies]  # noqa: E731
            return jnp.sum(e), cut(g_x), cut(g_phi)

        time_variant(f"full dense list, 2^{log2} rows", dense)


if __name__ == "__main__":
    main()
