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
