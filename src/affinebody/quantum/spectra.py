"""Energy levels of one quantum affine body, sector by sector, in bases orthonormal under the
measure of the two-polar reduction (paper, last section; docs/theory/two-polar.md).

The configuration phi = L diag(Q) R^T is split into its SO(n) x SO(n) orbit (L, R) and the
signed singular values Q (d'Alembert, Lebesgue measure prod_{a<b} |Q_a^2 - Q_b^2|, domain
Q_1 >= ... >= |Q_n|: det phi = 0 is *not* a wall) or their logarithms q (affine models on GL+,
Haar measure prod_{a<b} |sinh(q_a - q_b)|). Each irreducible (spin, vorticity) sector is a
separate eigenproblem on the reduced space, solved densely (no Lanczos, so no copy of a
degenerate level is lost); levels of different sectors that coincide are merged and their
sectors listed, so multiplicities can be checked against the group theory.

The n = 2 discretisations (d'Alembert on (|z|, |w|), affine models on (x, sigma)) are described
in :mod:`affinebody.quantum.n2`; n = 3 (every SO(3) x SO(3) sector (j, j')) in
:mod:`affinebody.quantum.n3`, the dedicated scalar / spin = vorticity = 1 bases in
:mod:`affinebody.quantum.channels3`.

Honesty: every sector is solved with the main basis, with a smaller nested basis and
(n = 2) with a wider one (scale x 1.3); the spread is the per-level error estimate, and levels
whose estimate exceeds the tolerance (e.g. pseudo-levels of a continuous spectrum) are
reported separately as unconverged, never as levels.

Partition functions and the classical limit (n = 2, af-is / is-af) are in
:mod:`affinebody.quantum.thermal`.
"""

from __future__ import annotations

from collections.abc import Callable

from affinebody.quantum import channels3, n2, n3
from affinebody.quantum.levels import (
    MODELS,
    AffineInertia,
    Level,
    Potential,
    Sector,
    Settings,
    Spectrum,
)

SECTORS3 = ("all", "scalar", "spin1", "scalar+spin1")

__all__ = ["MODELS", "SECTORS3", "Level", "Sector", "Settings", "Spectrum", "solve"]


def solve(model: str, n: int, potential: Potential, hbar: float, *, inertia: float = 1.0,
          I: float = 1.0, A: float = 0.0, B: float = 0.0, levels: int = 10,  # noqa: E741
          settings: Settings | None = None, sectors: str = "auto",
          progress: Callable[[str], None] | None = None) -> Spectrum:
    """The lowest ``levels`` states (counted with multiplicity) of the reduced problem.
    ``progress`` (n = 3, all sectors) receives a line per sector as it starts.

    ``model`` in :data:`MODELS`; d'Alembert uses J = inertia * Id, the affine models (I, A, B).
    ``sectors``: "all" (every sector: n = 2 the characters (s, k), n = 3 the SO(3) x SO(3)
    sectors (j, j') by :mod:`affinebody.quantum.n3`), "auto" = "all"; for n = 3 also "scalar"
    (spin = vorticity = 0), "spin1" (spin = vorticity = 1, 9 states per level) or
    "scalar+spin1" (the dedicated bases of those sectors; the result warns that the other
    sectors are left out).
    """
    settings = settings or Settings()
    if model not in MODELS:
        raise ValueError(f"quantum.kinetic must be one of {MODELS} (got {model!r})")
    if n not in (2, 3):
        raise ValueError(f"system.n must be 2 or 3 for quantum spectra (got {n})")
    if sectors == "auto":
        sectors = "all"
    if n == 2 and sectors != "all":
        raise ValueError(f"quantum.sectors must be 'all' or 'auto' for n = 2 (got {sectors!r})")
    if n == 3 and sectors not in SECTORS3:
        raise ValueError(f"quantum.sectors must be one of {', '.join(SECTORS3)} for n = 3 (got "
                         f"{sectors!r})")
    if n == 3:
        if sectors == "all":
            return n3.solve_all_sectors(model, potential, hbar, inertia,
                                        AffineInertia(model, I, A, B), levels, settings,
                                        progress)
        if model == "dalembert" and sectors == "scalar":
            return channels3.solve_dalembert_scalar(potential, hbar, inertia, levels, settings)
        return channels3.solve_channels(model, potential, hbar, inertia,
                                        AffineInertia(model, I, A, B), levels, settings, sectors)
    return n2.solve_n2(model, potential, hbar, inertia, AffineInertia(model, I, A, B), levels,
                       settings)
