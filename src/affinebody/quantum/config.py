"""Quantum spectrum configs (TOML): ``[system] n`` and ``[quantum]``, validated by pydantic.

Example (the names are part of the public contract)::

    [system]
    n = 2
    [quantum]
    hbar = 1.0
    kinetic = "dalembert"      # or "af-is" (74), "is-af" (73), "af-af" (72), "af-J" with J = I Id
    inertia = 1.0              # d'Alembert: J = inertia * Id
    potential = "0.5*trG + 0.1*(det - 1)**2"

The affine models take ``I``, ``A``, ``B`` as in the classical ``[kinetic]`` table (af-af: ``A``,
``B``). The potential is an expression (restricted grammar of :mod:`affinebody.expressions`) in
the deformation invariants q1..qn (q_a = ln |Q_a|), Q1..Qn (signed singular values, Q_n carries
the sign of det phi), trG = Tr G, K1..Kn (K_a = Tr G^a, eq. (17)) and det = det phi.

Discretisation settings, all optional: ``levels`` (default 10), ``sectors`` ("auto", "all" for
n = 2 and 3; for n = 3 also "scalar", "spin1", "scalar+spin1"; "auto" is "all"),
``basis_size``, ``scale``, ``scale_sigma``, ``centre``, ``tolerance``, ``max_spin`` (the last
shell the sector search may reach: n = 2 |m1| + |m2| for d'Alembert, max(|s|, |k|) for the
affine models, max(j, j') for n = 3; an n = 2 search stops earlier once certified complete,
docs/theory/two-polar.md, "Lower bounds of a sector"); for ``affinebody density`` also
``density_points`` and ``density_tolerance`` (1e-8, relative to the peak of each density).
Every error is one line naming the field, e.g.
``config error: quantum.hbar must be > 0 (got -1.0)``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from affinebody.config import ConfigError, load_toml, one_line_error
from affinebody.quantum.intervals import ExpressionPotential, invariant_names
from affinebody.quantum.levels import Settings

KINETIC_NAMES = ("dalembert", "af-is", "is-af", "af-af", "af-J")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class QuantumSystem(_Section):
    n: int = Field(description="spatial dimension (2 or 3)")


class QuantumSection(_Section):
    hbar: float = 1.0
    kinetic: str = "dalembert"
    inertia: float | None = None
    I: float | None = None  # noqa: E741
    A: float | None = None
    B: float | None = None
    potential: str
    levels: int = 10
    sectors: Literal["auto", "all", "scalar", "spin1", "scalar+spin1"] = "auto"
    basis_size: int | None = None
    scale: float | None = None
    scale_sigma: float | None = None
    centre: float | None = None
    tolerance: float = 1e-7
    max_spin: int = 40
    #: n = 3 d'Alembert: radial functions per harmonic of degree <= basis_size
    #: (n3.harmonic_block; default DEFAULT_RADIAL_SIZE over every sector, 0: the Gaussian x
    #: polynomial basis instead)
    radial_size: int | None = None
    #: ``affinebody density``: output points per density (default densities.POINTS: 301 for
    #: n = 2, 101 for n = 3) and the quadrature error allowed, relative to each density's peak
    density_points: int | None = None
    density_tolerance: float = 1e-8


class QuantumConfig(_Section):
    system: QuantumSystem
    quantum: QuantumSection


VARIABLES_DOC = "q1..qn, Q1..Qn, trG, K1..Kn, det"


def _positive(value: float | None, name: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ConfigError(f"quantum.{name} must be > 0 (got {value})")


#: The most shells |spin|, |vorticity| a spectrum may search (n = 2; n = 3 stops at 6).
MAX_SPIN = 1000
#: Magnitudes of the physical constants and basis scales the solvers handle in float64 (their
#: squares, products and inverses stay finite): choose units in which they are nearer 1.
MAGNITUDES = (1e-100, 1e100)
_SCALED = ("hbar", "inertia", "I", "A", "B", "scale", "scale_sigma", "centre")


def check_magnitude(value: float, label: str, *, small_too: bool = True) -> None:
    """A one-line ConfigError, ``{label} is beyond what the solvers handle ...``, for a
    nonzero ``value`` outside :data:`MAGNITUDES` (above it only, unless ``small_too``): for
    the constants of a config and the numbers of a command's flags."""
    low, high = MAGNITUDES
    if value != 0 and not (low if small_too else 0) <= abs(value) <= high:
        limits = f"from {low:g} to {high:g} in size, or 0" if small_too else f"at most {high:g}"
        raise ConfigError(f"{label} is beyond what the solvers handle in float64 ({limits}): "
                          f"choose units in which it is nearer 1")


def check(config: QuantumConfig) -> QuantumConfig:
    """Meaning checks beyond types; raises :class:`ConfigError` (one line)."""
    n, qc = config.system.n, config.quantum
    if n not in (2, 3):
        raise ConfigError(f"system.n must be 2 or 3 for quantum spectra (got {n})")
    _positive(qc.hbar, "hbar")
    for name in ("scale", "scale_sigma", "tolerance", "density_tolerance"):
        _positive(getattr(qc, name), name)
    for name in _SCALED:
        value = getattr(qc, name)
        if value is not None and not math.isfinite(value):
            raise ConfigError(f"quantum.{name} must be finite (got {value})")
        if value is not None:
            check_magnitude(value, f"quantum.{name} = {value:g}")
    if qc.kinetic not in KINETIC_NAMES:
        raise ConfigError(f"quantum.kinetic must be one of {', '.join(KINETIC_NAMES)} "
                          f"(got {qc.kinetic!r})")
    if qc.levels < 1:
        raise ConfigError(f"quantum.levels must be >= 1 (got {qc.levels})")
    low, high = (8, 80) if n == 2 else (4, 16)  # n = 3: the polynomial degree
    if qc.basis_size is not None and not low <= qc.basis_size <= high:
        raise ConfigError(f"quantum.basis_size must be between {low} and {high} for n = {n} "
                          f"(got {qc.basis_size})")
    if qc.radial_size is not None and qc.radial_size != 0:
        if n != 3 or qc.kinetic != "dalembert":
            raise ConfigError(f"quantum.radial_size is for n = 3 with kinetic 'dalembert' only "
                              f"(got n = {n}, kinetic {qc.kinetic!r}); remove it")
        if qc.sectors not in ("auto", "all"):
            raise ConfigError(f"quantum.radial_size needs quantum.sectors = 'all' (got "
                              f"{qc.sectors!r})")
        if not 4 <= qc.radial_size <= 60:
            raise ConfigError(f"quantum.radial_size must be between 4 and 60, or 0 for the "
                              f"Gaussian x polynomial basis (got {qc.radial_size})")
    if qc.density_points is not None and not 11 <= qc.density_points <= 100001:
        raise ConfigError(f"quantum.density_points must be between 11 and 100001 (got "
                          f"{qc.density_points})")
    if not 0 <= qc.max_spin <= MAX_SPIN:
        raise ConfigError(f"quantum.max_spin must be between 0 and {MAX_SPIN} (got "
                          f"{qc.max_spin})")
    if qc.kinetic == "af-af" and "max_spin" not in qc.model_fields_set:
        raise ConfigError("quantum.kinetic = 'af-af' (72) is indefinite: its Hamiltonian has no "
                          "lowest level (the sectors s = -k bind without bound), so a search for "
                          "the lowest levels cannot end; set quantum.max_spin to the shells to "
                          "solve (their levels are then reported, marked unbounded below)")
    if qc.kinetic == "dalembert":
        _positive(qc.inertia, "inertia")
        for name in ("I", "A", "B"):
            if getattr(qc, name) is not None:
                raise ConfigError(f"quantum.{name} is not a parameter of kinetic 'dalembert' "
                                  f"(it uses inertia)")
    else:
        if qc.inertia is not None and qc.kinetic != "af-J":
            raise ConfigError(f"quantum.inertia is not a parameter of kinetic {qc.kinetic!r} "
                              f"(it uses I, A, B)")
        I, A, B = _affine_constants(qc)
        if qc.kinetic in ("af-is", "is-af", "af-J"):
            if not I > abs(A):
                raise ConfigError(f"quantum.I must be > |quantum.A| for {qc.kinetic} to be "
                                  f"positive definite (got I={I}, A={A})")
        elif A <= 0:
            raise ConfigError(f"quantum.A must be > 0 for af-af (got A={A})")
        if not I + A + n * B > 0:
            raise ConfigError(f"quantum.B must be > -(I + A)/n for {qc.kinetic} (got I={I}, "
                              f"A={A}, B={B}, n={n})")
    if n == 3 and qc.max_spin > 6 and "max_spin" in qc.model_fields_set:
        raise ConfigError(f"quantum.max_spin must be <= 6 for n = 3 (got {qc.max_spin}): "
                          f"sectors up to (6, 6) are supported")
    if n == 2 and qc.sectors not in ("auto", "all"):
        raise ConfigError(f"quantum.sectors must be 'auto' or 'all' for n = 2 (got "
                          f"{qc.sectors!r})")
    compile_potential(qc.potential, n)
    return config


def _affine_constants(qc: QuantumSection) -> tuple[float, float, float]:
    if qc.kinetic == "af-J":  # af-J with J = I Id is af-is with A = B = 0, eq. (66)
        I = qc.I if qc.I is not None else qc.inertia
        if I is None:
            raise ConfigError("quantum.I (or inertia) is required by kinetic 'af-J'")
        return float(I), 0.0, 0.0
    if qc.kinetic != "af-af" and qc.I is None:
        raise ConfigError(f"quantum.I is required by kinetic {qc.kinetic!r}")
    if qc.A is None:
        if qc.kinetic == "af-af":
            raise ConfigError("quantum.A is required by kinetic 'af-af'")
    return (float(qc.I or 0.0) if qc.kinetic != "af-af" else 0.0, float(qc.A or 0.0),
            float(qc.B or 0.0))


def compile_potential(text: str, n: int) -> ExpressionPotential:
    """The potential text as a function V(Q [..., n]) -> [...] (numpy in, numpy out) that keeps
    its text, so that the sector search can certify lower bounds of V
    (:mod:`affinebody.quantum.bounds`)."""
    try:
        return ExpressionPotential(text, n)
    except ValueError as err:
        raise ConfigError(str(err)) from None


def parse(text: str, source: str = "config") -> QuantumConfig:
    data = load_toml(text, source)
    try:
        config = QuantumConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(one_line_error(err)) from None
    return check(config)


def load(path: str | Path) -> QuantumConfig:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read {path}: {err}") from None
    return parse(text, str(path))


def solver_arguments(config: QuantumConfig) -> dict:
    """Keyword arguments of :func:`affinebody.quantum.spectra.solve` for this config."""
    n, qc = config.system.n, config.quantum
    model = "af-is" if qc.kinetic == "af-J" else qc.kinetic
    kwargs = dict(model=model, n=n, potential=compile_potential(qc.potential, n),
                  hbar=qc.hbar, levels=qc.levels, sectors=qc.sectors)
    if model == "dalembert":
        kwargs["inertia"] = 1.0 if qc.inertia is None else qc.inertia
    else:
        kwargs["I"], kwargs["A"], kwargs["B"] = _affine_constants(qc)
    default_size = 24 if n == 2 else (10 if model == "dalembert" else 8)
    kwargs["settings"] = Settings(
        basis_size=qc.basis_size or default_size, scale=qc.scale, scale_sigma=qc.scale_sigma,
        centre=qc.centre, tolerance=qc.tolerance, max_spin=qc.max_spin,
        check_shrink=4 if n == 2 else 2, radial_size=radial_size(config))
    return kwargs


#: Radial functions per harmonic of an n = 3 d'Alembert spectrum over every sector when the
#: config gives none: harmonics x radial functions converge far faster than the Gaussian x
#: polynomial basis of the same degree (README, "Quantum spectra": its example, a potential
#: with a bump, is certified to 5.5e-9 in 3.5 s at degree 10 x 12 radial functions and stays
#: unconverged at 5.0e-5 in 21 s in the polynomial basis).
DEFAULT_RADIAL_SIZE = 12


def radial_size(config: QuantumConfig) -> int | None:
    """The radial functions per harmonic of an n = 3 d'Alembert spectrum: ``quantum.radial_size``,
    else :data:`DEFAULT_RADIAL_SIZE` where that basis applies (sectors "auto" or "all"); None
    (the Gaussian x polynomial basis) for ``radial_size = 0`` and everywhere else."""
    n, qc = config.system.n, config.quantum
    if qc.radial_size is not None:
        return qc.radial_size or None
    if n == 3 and qc.kinetic == "dalembert" and qc.sectors in ("auto", "all"):
        return DEFAULT_RADIAL_SIZE
    return None


__all__ = [
    "DEFAULT_RADIAL_SIZE", "KINETIC_NAMES", "MAGNITUDES", "MAX_SPIN", "check_magnitude",
    "QuantumSystem", "QuantumSection", "QuantumConfig", "VARIABLES_DOC", "invariant_names",
    "check", "compile_potential", "parse", "load", "radial_size", "solver_arguments"
]
