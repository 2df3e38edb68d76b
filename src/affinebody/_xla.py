"""XLA CPU settings that must be in place before JAX creates its CPU backend."""

from __future__ import annotations

import os

EIGEN_FLAG = "--xla_cpu_multi_thread_eigen=false"


def single_threaded_eigen() -> None:
    """Turn off XLA CPU's multi-threaded Eigen pool for this process (unless XLA_FLAGS sets it).

    That pool intermittently wedges when materialising large vmap results: the main thread
    waits in ``Array._value`` with the CPU idle, for ever (seen here in the test suite after
    ~10 minutes; reported upstream by other projects, where this flag took hangs from 14/16
    runs to 0/12). The cost is intra-op parallelism inside one XLA kernel, which affinebody's
    small per-body matrices barely use. Must run before the first JAX computation.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_multi_thread_eigen" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} {EIGEN_FLAG}".strip()
