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

import math
from collections.abc import Callable

import numpy as np

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

__all__ = ["MODELS", "SECTORS3", "Level", "Sector", "Settings", "Spectrum", "solve",
    "require_bounded_below",
]


#: The most states one solve may ask for (a bound on the work a request implies).
MAX_LEVELS = 5000


def require_bounded_below(potential: Potential, n: int) -> None:
    """ValueError when V runs to -infinity along a ray of the reduced domain: then H has no
    lowest level (a wave packet of fixed shape carried out along the ray keeps its kinetic
    energy while its potential energy decreases without bound), and no sector search can end.

    The evidence is sampled, not proved: V at Q = exp(t u), for unit directions u of the
    log singular values (and, for d'Alembert's Lebesgue domain, det phi < 0 too) and
    t = 4, 8, ..., 64, must fall below -1e8 (1 + |V(Id)|) and keep falling along the ray. A
    potential unbounded below only more slowly passes this check (the solver then runs to
    ``max_spin`` and reports its list as conditional)."""
    angles = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    if n == 2:
        directions = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    else:
        rng = np.random.default_rng(0)
        directions = rng.normal(size=(48, n))
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    t = 2.0 ** np.arange(2, 7)
    q = t[:, None, None] * directions[None]  # [T, D, n]
    signs = np.ones(n)
    signs[-1] = -1.0
    reference = float(np.asarray(potential(np.ones((1, n))))[0])
    floor = -1e8 * (1.0 + abs(reference))
    for flip in (np.ones(n), signs):
        Q = np.sort(np.exp(q), axis=-1)[..., ::-1] * flip
        with np.errstate(all="ignore"):
            V = np.asarray(potential(Q.reshape(-1, n)), dtype=float).reshape(q.shape[:2])
        falling = np.all(np.diff(V[-3:], axis=0) < 0, axis=0) & (V[-1] < floor)
        if np.any(falling):
            d = int(np.argmax(falling))
            point = ", ".join(f"{v:.3g}" for v in Q[-1, d])
            raise ValueError(
                f"quantum.potential is unbounded below: V = {V[-1, d]:.3g} at Q = ({point}) "
                f"and still falling along that ray, so the Hamiltonian has no lowest level; "
                f"add a confining term")


def solve(model: str, n: int, potential: Potential, hbar: float, *, inertia: float = 1.0,
          I: float = 1.0, A: float = 0.0, B: float = 0.0, levels: int = 10,  # noqa: E741
          settings: Settings | None = None, sectors: str = "auto",
          progress: Callable[[str], None] | None = None) -> Spectrum:
    """The lowest ``levels`` states (counted with multiplicity) of the reduced problem.
    ``progress`` receives a line per sector (n = 3, all sectors) or per shell (n = 2) as it starts.

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
    if not (math.isfinite(hbar) and hbar > 0):  # hbar = 0 returned unconverged candidates
        raise ValueError(f"quantum.hbar must be a finite number > 0 (got {hbar})")
    for name, value in (("inertia", inertia), ("I", I), ("A", A), ("B", B)):
        if not math.isfinite(value):
            raise ValueError(f"quantum.{name} must be finite (got {value})")
    if model == "dalembert" and not inertia > 0:  # was a ZeroDivisionError
        raise ValueError(f"quantum.inertia must be > 0 for d'Alembert (got {inertia})")
    if not levels >= 1:
        raise ValueError(f"levels must be >= 1 (got {levels})")
    if n not in (2, 3):
        raise ValueError(f"system.n must be 2 or 3 for quantum spectra (got {n})")
    if levels > MAX_LEVELS:
        raise ValueError(
            f"--levels {levels} is more than this solver is built for (at most {MAX_LEVELS} "
            f"states: every sector is solved densely, and {levels} states need thousands of "
            f"sectors, hours of work): ask for fewer levels")
    require_bounded_below(potential, n)
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
                       settings, progress)
