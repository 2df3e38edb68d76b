"""Where a step of ``affinebody run`` goes: the parts of the loop timed as compiled functions.

The system is the one of ``run_scale.py`` (3D lattice, d'Alembert + af-is, the affine pair
potential with D and M1, a dilatation term, neighbour list on), built by the same
``config.build`` that ``affinebody run`` calls, in a process set up as that command sets up
its own (``runner.prepare_process``, ``_host.keep_freed_memory``). Timed, each as a jitted
function of the product, median of repeated calls after one warm-up (compile excluded,
reported apart):

- ``forces``: all generalised forces (the pair kernel of the backend and the one-body terms);
- ``list build``: a full neighbour-list build (``neighbors.build``);
- ``list check``: the displacement test run every step (``neighbors.needs_rebuild``);
- ``step``: one whole integrator step as the loop runs it (``affinebody run``'s summary line
  over a longer run is the reference; this isolates one step);
- ``loop``: ``simulate.run`` (what ``affinebody run`` compiles) over ``--loop-steps`` steps with
  two frames, per step (median of three runs after a warm-up), and the time spent inside the
  host kernels' callbacks in it (pair forces, drift; wall time of the callbacks, summed):
  the rest of a step runs in XLA on one thread.

``--profile``: the loop once more under JAX's profiler, and what XLA ran on its thread per
step outside the host kernels' callbacks: the time of its operations (summed, without the
wrappers of the while loops and conditionals that hold them), their number, and the ten
longest; on a GPU the kernels its streams ran instead, the fifteen longest (the Triton
kernels by their names, ``affinebody_pair_scalars`` and ``affinebody_pair_rows``); named as
in the optimised HLO (dumped with
``XLA_FLAGS=--xla_dump_to=DIR --xla_dump_hlo_as_text`` to see what they compute).

``--npt``: the same system under the barostat of ``run_scale.py --npt`` (a move every step),
and instead of ``step`` and ``loop``, ``npt loop``: the compiled NPT loop
(``barostat.advance``, what ``affinebody run`` compiles with a ``[barostat]``) over
``--loop-steps`` steps, per step (median of seven runs after a warm-up); with
``--metropolis`` the moves pass the Metropolis test (``barostat.metropolis = true``).

``--against FILE``: ``forces`` again with the JAX pair kernel of another version of
``pair_kernels.py`` (``git show REV:src/affinebody/pair_kernels.py > FILE``) in place of the
product's, in the same process: an A/B of a kernel change on a GPU (where the product runs
that kernel; on a CPU it runs the host kernel, so force it with ``--jax-kernel``).

``--pair-program NAME``: ``forces`` again with the JAX pair kernel's passes over pairs run by
program NAME (``pair_kernels.pair_program``: ``xla`` or, on a GPU, ``triton``) instead of the
backend's default, in the same process: an A/B of the product's two programs on a GPU. The
largest difference of their forces, relative, is printed after it.

``--triton-blocks B ...``: ``forces`` again with the Triton program at B pairs per program of
its kernels (``_pair_triton.BLOCK``, one pair per thread: B / 32 warps), on a GPU (on a CPU in
Pallas' interpreter, a smoke test only): how ``BLOCK`` is to be chosen there; each with the
largest difference of its forces from ``forces``. tests/test_benchmarks.py runs these options
(the first command of ``gpu_session.sh run``) on the CPU at 512 bodies.

``--f-in-xla``: ``forces`` again with the Triton program's f and its partials computed by XLA
between its two kernels (``pair_kernels.F_IN_TRITON`` off: the scalars kernel first) instead
of inside its first kernel (the partials kernel), with the largest difference of its forces.

``--no-padding-skip``: ``forces`` again with a pass over every chunk of the list, those that
hold only its padding (its spare capacity) included (``pair_kernels.SKIP_PADDING_PASSES``
off): what the skip saves, and what its conditional per pass costs, on a GPU.

``--pair-parts``: on a GPU, the parts of one pass of the Triton program over its first chunk
of pairs (``pair_kernels.pair_chunk`` pairs), each a jitted function of its inputs timed
apart: the scalars kernel and f and its partials (XLA), or instead the partials kernel that
does both (the product's where f allows), the rows kernel, and the two scatters of the rows
to the bodies (K's run sums, L's rows); with the whole pass for comparison (its parts
overlap nothing, so they should add up to it, with the partials kernel in place of the
first two).

``--pair-chunks`` and ``--candidate-chunks`` time the forces and the build at other pass sizes
of the JAX kernels (how ``pair_kernels.ACCELERATOR_PAIR_CHUNK`` and
``neighbors._ACCELERATOR_CANDIDATES_PER_CHUNK`` were chosen on a GPU).

    .venv/bin/python benchmarks/step_phases.py --bodies 4096
    .venv/bin/python benchmarks/step_phases.py --bodies 4096 --profile
    python benchmarks/step_phases.py --bodies 1000000 --pair-chunks 18 20 22 24   # on a GPU
    python benchmarks/step_phases.py --bodies 1000000 --loop-steps 0 --against /tmp/pk_old.py
    python benchmarks/step_phases.py --bodies 1000000 --loop-steps 0 --pair-program xla  # GPU
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from run_scale import write_config  # noqa: E402


def timed(function, *args, repeats: int = 5) -> tuple[float, float]:
    """(first call s, median of ``repeats`` later calls s), results waited for."""
    import jax

    start = time.perf_counter()
    jax.block_until_ready(function(*args))
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function(*args))
        times.append(time.perf_counter() - start)
    return first, statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=int, default=4096)
    parser.add_argument("--pair-chunks", type=int, nargs="*", default=[],
                        help="log2 of pair-kernel pass sizes to compare")
    parser.add_argument("--candidate-chunks", type=int, nargs="*", default=[],
                        help="log2 of list-build pass sizes to compare")
    parser.add_argument("--loop-steps", type=int, default=200,
                        help="steps of the simulate.run loop timed (0: skip it)")
    parser.add_argument("--against", help="another pair_kernels.py whose JAX kernel to time "
                        "in the forces beside the product's")
    parser.add_argument("--pair-program", help="time the forces again with this program of "
                        "the JAX kernel (one of pair_kernels.PAIR_PROGRAMS)")
    parser.add_argument("--triton-blocks", type=int, nargs="*", default=[],
                        help="pairs per program of the Triton kernels to compare")
    parser.add_argument("--f-in-xla", action="store_true",
                        help="time the forces again with the Triton program's f in XLA "
                             "between its kernels (pair_kernels.F_IN_TRITON off)")
    parser.add_argument("--no-padding-skip", action="store_true",
                        help="time the forces again with every pass over the list's chunks, "
                             "padding-only ones included (pair_kernels.SKIP_PADDING_PASSES "
                             "off)")
    parser.add_argument("--pair-parts", action="store_true",
                        help="the parts of one pass of the Triton program over pairs (GPU)")
    parser.add_argument("--jax-kernel", action="store_true",
                        help="the JAX pair kernel on a CPU too (as on a GPU)")
    parser.add_argument("--profile", action="store_true",
                        help="the loop's XLA operations per step, from JAX's profiler")
    parser.add_argument("--npt", action="store_true",
                        help="the barostat's system and its NPT loop")
    parser.add_argument("--metropolis", action="store_true",
                        help="--npt: the barostat's moves pass the Metropolis test")
    args = parser.parse_args()

    import jax

    jax.config.update("jax_enable_x64", True)
    from affinebody import _host
    from affinebody import neighbors as nb
    from affinebody import pair_kernels as pk
    from affinebody.config import build, load_config
    from affinebody.integrators import get_integrator
    from affinebody.runner import pair_forces, prepare_process

    side = round(args.bodies ** (1 / 3))
    with tempfile.TemporaryDirectory() as tmp:
        config = load_config(write_config(Path(tmp), side, steps=10, every=10, npt=args.npt,
                                          metropolis=args.metropolis))
    prepare_process(config)  # the process as `affinebody run` sets it up
    _host.keep_freed_memory()
    start = time.perf_counter()
    built = build(config)
    stages = ", ".join(f"{k} {v:.2f}" for k, v in built.timings.items())
    print(f"{side**3} bodies on {jax.devices()[0].device_kind}; set-up "
          f"{time.perf_counter() - start:.2f} s ({stages})")
    system, state = built.system, built.state
    spec, lst = built.neighbors
    print(f"list: capacity {lst.i.shape[0]} pairs, {int(lst.count)} in use "
          f"({int(lst.count) / side**3:.1f} per body)")
    print(pair_forces(system, config.n, listed=True))  # the kernel (and program) timed

    def report(name, first, median):
        print(f"  {name:<34} {median * 1e3:10.3f} ms   (first call {first:.2f} s)", flush=True)

    if args.jax_kernel:
        pk.host_kernel_in_use = lambda: False
    forces = jax.jit(system.forces)
    report("forces", *timed(forces, state, lst))

    def forces_again(label):
        """``forces`` timed again under a patch of the kernels: a new function object, so
        that jit traces it anew with the patch."""
        again = jax.jit(lambda s, nbrs: system.forces(s, nbrs))
        report(label, *timed(again, state, lst))
        return again

    def difference_to_forces(other):
        """The same forces by another program: their largest difference, relative, printed."""
        difference = max(float(jax.numpy.max(abs(a - b)) / jax.numpy.max(abs(a)))
                         for a, b in zip(forces(state, lst), other(state, lst), strict=True))
        print(f"  {'(largest difference, relative)':<34} {difference:10.1e}", flush=True)

    if args.against:
        import importlib.util

        spec_of = importlib.util.spec_from_file_location("other_pair_kernels", args.against)
        other = importlib.util.module_from_spec(spec_of)
        spec_of.loader.exec_module(other)
        product = pk.energy_and_gradients
        # the forces only (no virial): an older kernel may not take the argument
        pk.energy_and_gradients = lambda *a, virial=False, **k: other.energy_and_gradients(*a,
                                                                                         **k)
        forces_again(f"forces, {Path(args.against).name}")
        pk.energy_and_gradients = product
    if args.pair_program:
        default = pk.pair_program
        pk.pair_program = lambda *_: args.pair_program
        other = forces_again(f"forces, pair program {args.pair_program}")
        pk.pair_program = default
        difference_to_forces(other)
    if args.triton_blocks:
        from affinebody import _pair_triton

        default = pk.pair_program, _pair_triton.BLOCK, _pair_triton.WARPS
        program = "triton" if jax.default_backend() == "gpu" else "triton-interpret"
        pk.pair_program = lambda *_: program
        for block in args.triton_blocks:
            _pair_triton.BLOCK, _pair_triton.WARPS = block, max(1, block // 32)
            _pair_triton._calls.cache_clear()  # kernels of the new block
            difference_to_forces(forces_again(f"forces, Triton block {block}"))
        pk.pair_program, _pair_triton.BLOCK, _pair_triton.WARPS = default
        _pair_triton._calls.cache_clear()
    if args.f_in_xla:
        default = pk.pair_program, pk.F_IN_TRITON
        program = "triton" if jax.default_backend() == "gpu" else "triton-interpret"
        pk.pair_program, pk.F_IN_TRITON = (lambda *_: program), False
        difference_to_forces(forces_again("forces, Triton with f in XLA"))
        pk.pair_program, pk.F_IN_TRITON = default
    if args.no_padding_skip:
        pk.SKIP_PADDING_PASSES = False
        difference_to_forces(forces_again("forces, no pass skipped"))
        pk.SKIP_PADDING_PASSES = True
    if args.pair_parts:
        pair_parts(system, config.n, state, lst, report)
    for log2 in args.pair_chunks:
        pk.ACCELERATOR_PAIR_CHUNK = pk.PAIR_CHUNK = 1 << log2
        forces_again(f"forces, pair pass 2^{log2}")
    build_jit = jax.jit(nb.build, static_argnums=0)
    report("list build", *timed(build_jit, spec, state.x, state.phi))
    for log2 in args.candidate_chunks:
        nb._ACCELERATOR_CANDIDATES_PER_CHUNK = nb._CANDIDATES_PER_CHUNK = 1 << log2
        report(f"list build, pass 2^{log2}",
               *timed(jax.jit(lambda x, phi: nb.build(spec, x, phi)), state.x, state.phi))
    check = jax.jit(nb.needs_rebuild, static_argnums=0)
    report("list check", *timed(check, spec, lst, state.x, state.phi))
    method = get_integrator(config.run.integrator)
    f0 = system.forces(state, lst)

    @jax.jit
    def step(s, f):
        return method.advance(system, s, f, config.run.dt, spec, lst)

    if args.npt:  # the list of a barostat's run follows a cell: its loop instead
        if args.loop_steps:
            npt_loop(config, system, state, built.neighbors, args.loop_steps)
        return
    report("step (kick, drift, list, forces)", *timed(step, state, f0))
    if args.loop_steps:
        loop(system, state, config.run.dt, built.neighbors, args.loop_steps)
        if args.profile:
            xla_operations(system, state, config.run.dt, built.neighbors, args.loop_steps)


def pair_parts(system, n: int, state, lst, report) -> None:
    """The parts of the Triton program's pass over the list's first chunk of pairs, each
    jitted and timed apart (``--pair-parts``), for the first pair term of ``system``."""
    import jax
    import jax.numpy as jnp

    from affinebody import _linalg, _pair_triton
    from affinebody import pair_kernels as pk
    from affinebody.potentials import PairTerm, terms_of

    pot = next(t for t in terms_of(system.potential) if isinstance(t, PairTerm))
    interpret = jax.default_backend() != "gpu"
    chunk = min(pk.pair_chunk(), lst.i.shape[0]) // _pair_triton.BLOCK * _pair_triton.BLOCK
    bodies = state.x.shape[0]
    i, j, valid = pk._valid_pairs(lst.i[:chunk], lst.j[:chunk], jnp.arange(chunk), lst.count,
                                  bodies)
    layout, padding = pk._triton_layout(pot, n)
    table = _pair_triton.table(state.phi, _linalg.inv(state.phi), _linalg.det(state.phi))
    u = pot.space.displacement(state.x[i], state.x[j], None)
    args = (u.reshape(-1), i.astype(jnp.int32), j.astype(jnp.int32), valid.astype(jnp.int32),
            table)
    values_and_partials = pk._scalar_values_and_partials(pot, n)

    def partials_of(s):
        energies, flat = _pair_triton.partials_of(layout, values_and_partials, s)
        return jnp.sum(energies), flat

    width = n + n * n
    zero = jnp.zeros((bodies, width))
    scalars, second = _pair_triton._calls(layout, chunk, bodies, padding, interpret)
    s = jax.jit(scalars)(*args)
    _, flat = jax.jit(partials_of)(s)
    side_k, k, side_l = jax.jit(second)(*args, flat)
    report(f"pass of {chunk} pairs: scalars kernel", *timed(jax.jit(scalars), *args))
    report("  f and partials (XLA)", *timed(jax.jit(partials_of), s))
    energy = pk.triton_energy(pot, n, "triton-interpret" if interpret else "triton")
    if energy is not None:  # the product's first kernel: scalars, f and partials in one
        first, _ = _pair_triton._calls(layout, chunk, bodies, padding, interpret, energy)
        report("  or instead partials kernel", *timed(jax.jit(first), *args))
    report("  rows kernel", *timed(jax.jit(second), *args, flat))
    report("  scatter of K's run sums", *timed(jax.jit(
        lambda t, rows, k: t.at[k].add(rows.reshape(-1, width), mode="drop")), zero, side_k, k))
    report("  scatter of L's rows", *timed(jax.jit(
        lambda t, rows, j, valid: t.at[jnp.where(valid, j, bodies)].add(
            rows.reshape(-1, width), mode="drop")), zero, side_l, j, valid))

    def whole(t, x, table, i, j, valid):  # arguments, not constants: XLA would fold them
        _, _, side_k, k, side_l = pk._triton_chunk(pot, pot.space, n, x, table, i, j, valid,
                                                   None, interpret)
        return t.at[k].add(side_k, mode="drop").at[jnp.where(valid, j, bodies)].add(
            side_l, mode="drop")

    report("  the whole pass (u, kernels, scatters)",
           *timed(jax.jit(whole), zero, state.x, table, i, j, valid))


def xla_operations(system, state, dt, neighbors, steps: int) -> None:
    """What XLA ran per step of ``simulate.run`` outside the host callbacks, from a trace of
    JAX's profiler (its Perfetto export), summed and counted by name: on a CPU the leaf
    operations of XLA's threads (not the while loops, conditionals and executors around
    them); on a GPU the kernels of the device's streams (the processes named after the GPU;
    where the trace has none, the process names it has are printed instead)."""
    import collections
    import gzip
    import json

    import jax

    from affinebody import simulate

    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder, create_perfetto_trace=True):
            simulate.run(system, state, dt, steps, every=steps // 2, neighbors=neighbors)
        with gzip.open(next(Path(folder).rglob("perfetto_trace.json.gz"))) as f:
            trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace

    def named(kind):
        return {(e["pid"], e.get("tid")) if kind == "thread_name" else e["pid"]:
                e["args"]["name"] for e in events
                if e.get("ph") == "M" and e.get("name") == kind}

    threads, processes = named("thread_name"), named("process_name")
    gpu = jax.default_backend() == "gpu"
    wrappers = ("ThunkExecutor", "cond", "while", "affinebody_host_callback")

    def counted(e) -> bool:
        if e.get("ph") != "X":
            return False
        if gpu:
            return "gpu" in processes.get(e["pid"], "").lower()
        return (threads.get((e["pid"], e["tid"]), "").startswith("tf_XLA")
                and not e["name"].startswith(wrappers))

    time_of, count_of = collections.Counter(), collections.Counter()
    for e in filter(counted, events):
        time_of[e["name"]] += e.get("dur", 0.0)
        count_of[e["name"]] += 1
    if not time_of:
        print(f"  profiler: no {'GPU kernels' if gpu else 'XLA operations'} found; processes "
              f"in the trace: {sorted(set(processes.values()))}", flush=True)
        return
    longest = ", ".join(f"{name} {t / steps:.0f} ({count_of[name] / steps:.3g}x)"
                        for name, t in time_of.most_common(15 if gpu else 10))
    print(f"  {'gpu kernels' if gpu else 'xla operations'} per step (profiler): "
          f"{sum(time_of.values()) / steps:.0f} us in {sum(count_of.values()) / steps:.0f} "
          f"{'kernels' if gpu else 'operations'}; longest, us per step (times per step): "
          f"{longest}", flush=True)


def npt_loop(config, system, state, neighbors, steps: int) -> None:
    """Per step of the compiled NPT loop (``barostat.advance``) over ``steps`` steps."""
    import jax
    import jax.numpy as jnp

    from affinebody import barostat
    from affinebody import neighbors as nb
    from affinebody.integrators import get_integrator
    from affinebody.runner import constant_pressure

    spec, _ = neighbors
    cell = jnp.asarray(spec.space.matrix)
    spec, lst = nb.list_at(spec, state.x, state.phi, cell)
    method = get_integrator(config.run.integrator)
    run = jax.jit(lambda s, lst: barostat.advance(
        system, s, cell, jnp.asarray(0), 1, config.run.dt, lst, steps=steps, method=method,
        barostat=constant_pressure(config, None)[0], space=spec.space, spec=spec)[0])
    first, median = timed(run, state, lst, repeats=7)
    print(f"  npt loop: barostat.advance, {steps} steps: {median / steps * 1e3:.2f} ms per "
          f"step (first call {first:.2f} s)", flush=True)


def loop(system, state, dt, neighbors, steps: int) -> None:
    """Per step of ``simulate.run`` over ``steps`` steps, and the part of it spent inside the
    host kernels' callbacks (on a CPU with Numba)."""
    from affinebody import kinetic, pair_kernels, simulate

    inside: dict[str, float] = {}

    def clocked(module, name, label):
        kernel = getattr(module, name)

        def run(*args, **kwargs):
            start = time.perf_counter()
            try:
                return kernel(*args, **kwargs)
            finally:
                inside[label] = inside.get(label, 0.0) + time.perf_counter() - start
        setattr(module, name, run)

    clocked(pair_kernels, "_host_fused", "pair forces")
    clocked(kinetic, "_host_isotropic_flow", "drift")

    def once():
        inside.clear()
        start = time.perf_counter()
        simulate.run(system, state, dt, steps, every=steps // 2, neighbors=neighbors)
        return time.perf_counter() - start, dict(inside)

    once()  # compiles
    runs = sorted((once() for _ in range(3)), key=lambda run: run[0])
    total, parts = runs[1]
    kernels = ", ".join(f"{k} {v / steps * 1e3:.2f} ms" for k, v in parts.items())
    print(f"  loop: simulate.run, {steps} steps: {total / steps * 1e3:.2f} ms per step; inside "
          f"the host kernels {sum(parts.values()) / steps * 1e3:.2f} ms ({kernels or 'none'})",
          flush=True)


if __name__ == "__main__":
    main()
