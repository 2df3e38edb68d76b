"""Process settings that must be in place before JAX creates its CPU backend."""

from __future__ import annotations

import os


def pin_to_one_cpu(index: int = 0) -> None:
    """Restrict this process to one CPU (the ``index``-th allowed one) before JAX starts.

    XLA sizes its CPU intra-op thread pool from the affinity mask. jaxlib's batched LAPACK
    kernels (linalg.solve/inv/det/svd on large vmapped batches) fan out over that same pool
    with ``ParallelBatchMap`` and block on a counter; when XLA runs two such kernels at once on
    a pool of two threads, both threads wait for sub-tasks that no free thread can run: a
    deadlock with the CPU idle (seen here with gdb: two ``tf_XLAEigen`` threads in
    ``TriMatrixEquationSolverKernel`` -> ``ParallelBatchMap`` -> ``BlockingCounter::Wait``).
    With one CPU the pool has one thread and ``ParallelBatchMap`` runs the batch inline.
    Used by the test suite (one core per pytest-xdist worker). Processes spawned later
    inherit the mask. The library's n <= 3 det/inv/solve/expm avoid LAPACK altogether through
    :mod:`affinebody._linalg`; pinning remains the safeguard for svd/eigh batches.
    """
    allowed = sorted(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {allowed[index % len(allowed)]})


#: XLA:CPU flags that the command line and its sweep workers set for their own process before
#: JAX starts: the MLIR fusion emitters off (XLA fuses with its elemental IR emitter instead).
#: Compilation takes about two thirds of the time for the same speed of the compiled loop
#: (``affinebody run`` on the demo: 4.5-4.9 s -> 3.2-3.7 s of compiling, the loop the same;
#: docs/performance.md).
FAST_COMPILATION = ("--xla_cpu_use_fusion_emitters=false",)
#: jaxlib versions (major, minor) below this are known to have those flags: XLA aborts the
#: process on a flag it does not know, so a newer jaxlib gets none.
FLAGS_KNOWN_BELOW = (0, 11)


def with_flags(current: str, flags: tuple[str, ...]) -> str:
    """``current`` (the text of XLA_FLAGS) with ``flags`` put in front, except those whose name
    it sets already (the user's choice stays). In front: XLA stops reading XLA_FLAGS at the
    first word that is not a flag."""
    names = {word.split("=")[0] for word in current.split()}
    new = [flag for flag in flags if flag.split("=")[0] not in names]
    return " ".join([*new, current]).strip()


def flags_known() -> bool:
    """Whether the installed jaxlib is a version below :data:`FLAGS_KNOWN_BELOW` (read from
    its metadata: JAX is not imported)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        major, minor = (int(part) for part in version("jaxlib").split(".")[:2])
    except (PackageNotFoundError, ValueError):
        return False
    return (major, minor) < FLAGS_KNOWN_BELOW


def compile_faster() -> None:
    """Add :data:`FAST_COMPILATION` to this process's XLA_FLAGS (:func:`with_flags`) where
    :func:`flags_known`. XLA reads XLA_FLAGS once, when JAX creates its first backend: call it
    before any JAX computation (later it changes nothing)."""
    if flags_known():
        os.environ["XLA_FLAGS"] = with_flags(os.environ.get("XLA_FLAGS", ""), FAST_COMPILATION)


#: The environment variables that size XLA's CPU client thread pool (the first one set wins;
#: neither set: one thread per core the process may use).
POOL_SIZE_VARIABLES = ("PJRT_NPROC", "NPROC")


def single_xla_thread() -> bool:
    """Give XLA's CPU client a pool of one thread (``PJRT_NPROC=1``), unless the user sized
    it (:data:`POOL_SIZE_VARIABLES`); True when set here. For a process whose parallel work
    the host kernels do on threads of their own (:mod:`affinebody._host`): XLA's idle pool
    threads then no longer compete with them for the cores (about 5 % on two contended cores,
    nothing measurable on idle ones: docs/performance.md, "Two cores: XLA's threads and the
    host kernels'"), and the pool has the one
    thread that :func:`pin_to_one_cpu` relies on against jaxlib's LAPACK deadlock. Not for
    work that XLA itself spreads over the cores (all-pairs sums: 1.6x slower on two cores).
    XLA reads it when JAX creates its CPU backend: call it before any JAX computation."""
    if any(os.environ.get(name, "").strip() for name in POOL_SIZE_VARIABLES):
        return False
    os.environ["PJRT_NPROC"] = "1"
    return True
