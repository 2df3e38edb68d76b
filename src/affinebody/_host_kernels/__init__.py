"""Numba kernels of the host (CPU) paths, as modules with a block of constants that
:func:`affinebody._host.specialized` sets per specialization (see there)."""
