"""Results of the quantum spectra and their bookkeeping (bottom of :mod:`affinebody.quantum`).

Sectors, levels (with multiplicity = the sum of the dimensions of the sectors listed), the solved
blocks, the :class:`Spectrum`; the discretisation :class:`Settings` and the kinetic constants
:class:`AffineInertia` of the affine models (paper, (72)-(74), (86); docs/theory/two-polar.md);
convergence, merging of degenerate levels and the counting of states (:class:`LevelCollector`).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

#: A potential as a function of the signed singular values Q [..., n] (Q_n carries sign det).
Potential = Callable[[np.ndarray], np.ndarray]

MODELS = ("dalembert", "af-is", "is-af", "af-af")


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Sector:
    """An SO(n) x SO(n) sector: spin s (L-rotations), vorticity k (R-rotations), parity.

    ``parity`` is the eigenvalue of Psi(phi) -> Psi(-phi) where that is a symmetry, else None.
    """

    spin: int
    vorticity: int
    parity: int | None = None
    #: number of states: 1 for the SO(2) x SO(2) characters (n = 2), dim(j) dim(j') =
    #: (2j + 1)(2j' + 1) for the n = 3 sector (spin j, vorticity j')
    dimension: int = 1

    def as_dict(self) -> dict:
        return {"spin": self.spin, "vorticity": self.vorticity, "parity": self.parity,
                "dimension": self.dimension}


def state_count(sectors: tuple[Sector, ...]) -> int:
    """Number of states of the sectors listed (the sum of their dimensions)."""
    return sum(sec.dimension for sec in sectors)


@dataclass(frozen=True)
class Level:
    """One energy level: value, multiplicity (= sum of the dimensions of the sectors listed),
    convergence. ``converged`` False: a candidate whose error estimate exceeds the tolerance
    (its energy is only an estimate; it still holds its place among the states)."""

    energy: float
    multiplicity: int
    sectors: tuple[Sector, ...]
    error: float
    block: tuple  # key of the reduced block the eigenvector lives in
    index: int  # index of the eigenvector within that block
    converged: bool = True
    #: (block key, index, sectors) of every eigenvector merged into the level, in the order of
    #: ``sectors`` (empty: the one eigenvector ``block``, ``index`` of all of them). A level
    #: can hold two eigenvectors of one block: the R^4 oscillator's N = 2 level has two of
    #: the sector (0, 0), |z|^2 and |w|^2 in their combinations
    parts: tuple = ()

    def eigenvectors(self) -> tuple[tuple[tuple, int, tuple[Sector, ...]], ...]:
        """(block key, index, sectors) of each eigenvector of the level (:attr:`parts`)."""
        return self.parts or ((self.block, self.index, self.sectors),)

    def as_dict(self) -> dict:
        first = self.sectors[0]
        return {
            "energy": self.energy,
            "multiplicity": self.multiplicity,
            "spin": first.spin,
            "vorticity": first.vorticity,
            "parity": first.parity,
            "sectors": [s.as_dict() for s in self.sectors],
            "error": self.error,
            "converged": self.converged,
        }


@dataclass
class Block:
    """A reduced eigenproblem (one radial problem shared by the sectors listed)."""

    key: tuple
    sectors: tuple[Sector, ...]
    basis: object  # an affinebody.quantum.bases.Basis
    energies: np.ndarray
    vectors: np.ndarray
    errors: np.ndarray


@dataclass
class Spectrum:
    """The lowest ``requested`` states: converged levels and unconverged candidates (each list
    ascending; together, in energy order, they are the states), and the solved blocks.

    ``certified``: the sector search provably holds the ``requested`` lowest states (every
    sector not searched has a certified lower bound above the last of them,
    :mod:`affinebody.quantum.bounds`); ``certificate`` says how, or why the list is conditional.
    """

    levels: list[Level]
    unconverged: list[Level]
    blocks: dict[tuple, Block]
    model: str
    n: int
    sectors: str  # "all", or for n = 3 "scalar", "spin1", "scalar+spin1"
    settings: dict = field(default_factory=dict)
    #: False where the sector sum is unbounded below (af-af): the levels are then only those of
    #: the sectors explored (|s|, |k| <= max_spin) and not the lowest of the body
    bounded_below: bool = True
    warnings: list[str] = field(default_factory=list)
    certified: bool = False
    certificate: str = ""
    requested: int | None = None

    def states(self) -> list[Level]:
        """Converged levels and unconverged candidates in energy order (a level once, with its
        multiplicity)."""
        return sorted(self.levels + self.unconverged, key=lambda lv: (lv.energy, not lv.converged))

    def energies(self, count: int | None = None) -> list[float]:
        """Energies of the states in ascending order, each repeated by its multiplicity (first
        ``count``); an unconverged state is NaN in its place, never replaced by a higher level."""
        values = [lv.energy if lv.converged else math.nan
                  for lv in self.states() for _ in range(lv.multiplicity)]
        return values if count is None else values[:count]

    def unknown_states(self, count: int | None = None) -> list[int]:
        """Indices (0-based, into :meth:`energies`) of the unconverged states."""
        return [i for i, v in enumerate(self.energies(count)) if math.isnan(v)]

    def complete(self, count: int | None = None) -> bool:
        """The first ``count`` (default ``requested``) states are all known: the search is
        certified, the body bounded below, and each of them converged."""
        return self.incomplete_because(count) is None

    def incomplete_because(self, count: int | None = None) -> str | None:
        """Why the first ``count`` (default ``requested``) states are not all known, in a few
        words (None when they are, :meth:`complete`)."""
        count = count if count is not None else self.requested
        values = self.energies(count)
        if not self.bounded_below:
            return "the body's energy is unbounded below"
        if not self.certified:
            return f"the sector search is not certified ({self.certificate})"
        if count is None or len(values) < count:
            return f"only {len(values)} states were computed"
        unknown = [i for i, v in enumerate(values) if math.isnan(v)]
        if unknown:
            return f"states {unknown} among them are unconverged candidates"
        return None

    def numbered(self) -> list[tuple[int | None, range, Level]]:
        """Each entry of :meth:`states` with its two numbers: its level number, its index in
        :attr:`levels` (as ``affinebody transitions`` numbers levels, ``--from`` and ``F``,
        and ``spectrum --json`` lists them as ``states``; None for an unconverged candidate),
        and its state numbers, its indices into :meth:`energies` (as ``density --state`` and
        ``--superpose`` number states: a level of multiplicity m holds m of them)."""
        out, level, first = [], 0, 0
        for lv in self.states():
            out.append((level if lv.converged else None,
                        range(first, first + lv.multiplicity), lv))
            level += lv.converged
            first += lv.multiplicity
        return out

    def state_range(self, level: int) -> range:
        """The state numbers (indices into :meth:`energies`) of ``self.levels[level]``."""
        return next(states for number, states, _ in self.numbered() if number == level)

    def level_of_state(self, k: int) -> Level:
        """The level holding the k-th entry (0-based) of :meth:`energies`."""
        return self._converged_entry(k)[1]

    def _converged_entry(self, k: int) -> tuple[range, Level]:
        """(state numbers, level) of the :meth:`numbered` entry holding state k; ValueError
        when k is past the states computed or its level is an unconverged candidate."""
        seen = 0
        for _, states, lv in self.numbered():
            seen = states.stop
            if k in states:
                if not lv.converged:
                    raise ValueError(
                        f"--state {k} is not converged: its candidate at {lv.energy:.9g} has the "
                        f"error estimate {lv.error:.1e} above quantum.tolerance (raise "
                        f"quantum.basis_size)")
                return states, lv
        raise ValueError(f"--state {k} is beyond the {seen} states computed")

    def state_eigenvector(self, k: int) -> tuple[Level, Sector]:
        """The k-th state (0-based, as :meth:`energies` counts them) as the level of its own
        eigenvector (``block``, ``index``; ``sectors`` those of that eigenvector, the level's
        energy and error) and its own sector. The states of a level are its eigenvectors'
        sectors in order (:meth:`Level.eigenvectors`), each repeated by its dimension; a
        state is never another state's eigenvector, even where one block holds two of them
        at the level's energy. ValueError as :meth:`level_of_state`."""
        states, level = self._converged_entry(k)
        offset = k - states.start
        for key, index, sectors in level.eigenvectors():
            for sector in sectors:
                if offset < sector.dimension:
                    return replace(level, multiplicity=state_count(sectors), sectors=sectors,
                                   block=key, index=index, parts=()), sector
                offset -= sector.dimension
        raise AssertionError(f"level at {level.energy} holds fewer states than its multiplicity")


# ------------------------------------------------------------------------- solver
@dataclass(frozen=True)
class Settings:
    """Discretisation settings (see :mod:`affinebody.quantum.config` for the config names)."""

    basis_size: int = 24  # per reduced coordinate (n = 2); polynomial degree (n = 3)
    scale: float | None = None  # None: variational choice
    scale_sigma: float | None = None
    centre: float | None = None
    tolerance: float = 1e-7  # absolute error allowed per level (relative to max(1, |E|))
    check_shrink: int = 4  # the nested check basis has basis_size - check_shrink functions
    check_widen: float = 1.3  # the widened check basis has scale x check_widen
    max_spin: int = 40  # last shell searched: n = 2 |m1| + |m2| (d'Alembert), max(|s|, |k|)
    merge: float = 1e-8  # levels closer than merge * max(1,|E|) are one degenerate level
    #: n = 3 d'Alembert: radial functions per harmonic (n3.harmonic_block); None: the
    #: Gaussian x polynomial basis of total degree basis_size (n3.sector_block)
    radial_size: int | None = None

@dataclass(frozen=True)
class AffineInertia:
    """Inertial constants of (72)-(74) as they enter the reduced Hamiltonian (n = 2)."""

    model: str
    I: float  # noqa: E741
    A: float
    B: float

    @property
    def M(self) -> float:
        return (0.0 if self.model == "af-af" else self.I) + self.A

    @property
    def inv_I_tilde(self) -> float:
        """1/I~ of (86); 0 for af-af."""
        if self.model == "af-af":
            return 0.0
        return self.I / (self.I**2 - self.A**2)

    @property
    def dilatation(self) -> float:
        """M + nB (n = 2): the coefficient of the dilatational kinetic term."""
        return self.M + 2 * self.B

def is_converged(E: float, err: float, settings: Settings) -> bool:
    """err within tolerance * max(1, |E|), and small against |E| itself: pseudo-levels of a
    continuous spectrum in a wide basis (E ~ hbar^2 / (I b^2) -> 0) move by a fixed fraction
    of E when the basis is widened, however small E is."""
    return bool(err <= settings.tolerance * max(1.0, abs(E)) and err <= 1e-2 * abs(E) + 1e-12)


def same_level(E: float, level_energy: float, merge: float) -> bool:
    """Whether a state of energy E belongs to the degenerate level of energy ``level_energy``
    (its first, lowest state's): |E - level_energy| <= merge * max(1, |E|), with
    ``merge`` = :attr:`Settings.merge`. The one rule that joins states into levels."""
    return abs(E - level_energy) <= merge * max(1.0, abs(E))


def states_text(states: range) -> str:
    """State numbers as the tables print them: ``3`` or ``3-4``."""
    return str(states.start) if len(states) == 1 else f"{states.start}-{states.stop - 1}"


def level_starts(energies: np.ndarray, merge: float) -> np.ndarray:
    """Indices at which a new degenerate level begins in ascending ``energies``
    (:func:`same_level`)."""
    starts: list[int] = []
    for k, E in enumerate(energies):
        if not starts or not same_level(E, energies[starts[-1]], merge):
            starts.append(k)
    return np.array(starts, dtype=int)


def merge_levels(entries: list[tuple[float, float, tuple[Sector, ...], tuple, int]],
                 settings: Settings) -> list[Level]:
    """Levels (ascending) from entries (energy, error, sectors, block key, index): energies
    of one level (:func:`same_level`) are one degenerate level listing every sector."""
    entries = sorted(entries, key=lambda e: e[0])
    levels: list[Level] = []
    for E, err, sectors, key, idx in entries:
        if levels and same_level(E, levels[-1].energy, settings.merge):
            last = levels[-1]
            levels[-1] = Level(last.energy, last.multiplicity + state_count(sectors),
                               last.sectors + sectors, max(last.error, err), last.block,
                               last.index, parts=last.eigenvectors() + ((key, idx, sectors),))
        else:
            levels.append(Level(E, state_count(sectors), sectors, err, key, idx))
    return levels

def truncate_levels(levels: list[Level], count: int) -> list[Level]:
    """The lowest levels that hold the first ``count`` states (the last may hold more)."""
    out, total = [], 0
    for lv in levels:
        if total >= count:
            break
        out.append(lv)
        total += lv.multiplicity
    return out


def eigen_parity(vector: np.ndarray, parity: np.ndarray) -> int | None:
    """Parity of an eigenvector in a basis of functions of definite ``parity`` (+1 / -1):
    +1 or -1 when its weight lies (to 1e-8) on one class, None when it mixes them."""
    even = float(np.sum(vector[parity == 1] ** 2))
    return 1 if even > 1 - 1e-8 else (-1 if even < 1e-8 else None)


@dataclass
class LevelCollector:
    """The solved blocks of a spectrum being assembled, their converged levels (as entries for
    :func:`merge_levels`) and the unconverged candidates."""

    settings: Settings
    blocks: dict = field(default_factory=dict)
    entries: list = field(default_factory=list)
    unconverged: list = field(default_factory=list)
    #: (energy, states) of every candidate, converged or not, ascending, and their states in
    #: all: kept as candidates come, since the search asks for the K-th energy before each
    #: block (recounting every candidate each time made a search of every shell, ~900 blocks
    #: at max_spin = 40, spend 30 of its 37 s counting)
    ladder: list = field(default_factory=list)
    states: int = 0

    def _add(self, E: float, err: float, sectors: tuple, key: tuple, index: int) -> None:
        states = state_count(sectors)
        if is_converged(E, err, self.settings):
            self.entries.append((float(E), float(err), sectors, key, index))
        else:
            self.unconverged.append(Level(float(E), states, sectors, float(err), key, index,
                                          converged=False))
        bisect.insort(self.ladder, (float(E), states))
        self.states += states

    def record(self, key: tuple, sectors: tuple, basis, E, vec, err) -> None:
        """One block whose eigenvectors all belong to ``sectors`` (level i: index i)."""
        self.blocks[key] = Block(key, sectors, basis, E, vec, err)
        for i in range(len(E)):
            self._add(E[i], err[i], sectors, key, i)

    def record_each(self, key: tuple, sectors_of: Callable[[int | None], tuple], basis,
                    E, vec, err, parity: np.ndarray) -> None:
        """One block per eigenvector, keyed ``key + (i,)``, its sectors labelled by its parity
        (:func:`eigen_parity` over the basis functions' ``parity``)."""
        for i in range(len(E)):
            sec = sectors_of(eigen_parity(vec[:, i], parity))
            one = key + (i,)
            self.blocks[one] = Block(one, sec, basis, E[i:i + 1], vec[:, i:i + 1], err[i:i + 1])
            self._add(E[i], err[i], sec, one, 0)

    def state_count(self) -> int:
        """Number of states of every candidate found, converged or not."""
        return self.states

    def kth_energy(self, count: int) -> float:
        """The ``count``-th lowest candidate energy, converged or not, counted with
        multiplicity (inf if fewer): a bound on what is still missing; from the ladder in
        O(count)."""
        total = 0
        for energy, states in self.ladder:
            total += states
            if total >= count:
                return energy
        return np.inf

    def levels(self, count: int | None) -> tuple[list[Level], list[Level]]:
        """(converged levels, unconverged candidates), each ascending, that together hold the
        lowest ``count`` states of every candidate found: an unconverged candidate keeps its
        place, so no level above it replaces it; ``count`` None: every level and candidate."""
        merged = merge_levels(self.entries, self.settings)
        pending = sorted(self.unconverged, key=lambda lv: lv.energy)
        if count is None:
            return merged, pending
        kept = truncate_levels(sorted(merged + pending, key=lambda lv: (lv.energy,
                                                                        not lv.converged)), count)
        return [lv for lv in kept if lv.converged], [lv for lv in kept if not lv.converged]


__all__ = [
    "Potential", "MODELS", "Sector", "state_count", "Level", "Block", "Spectrum", "Settings",
    "AffineInertia", "is_converged", "same_level", "states_text", "level_starts", "merge_levels",
    "truncate_levels", "eigen_parity", "LevelCollector"
]
