"""Compiled host (CPU) code: whether the product runs it.

On a CPU backend with Numba installed, the pair kernel (``pair_kernels``) and the neighbour
list build (``neighbors``) run compiled CPU loops reached through ``jax.pure_callback``; on
a GPU (or without Numba) they run their JAX versions, so nothing leaves the device inside the
time loop. Both versions of each are tested against each other and against all-pairs sums.
"""

from __future__ import annotations

import jax

try:  # optional at import: the JAX paths work without it (pyproject installs it)
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is missing
    numba = None


def in_use() -> bool:
    """True when compiled host code runs: a CPU backend and Numba installed."""
    return numba is not None and jax.default_backend() == "cpu"
