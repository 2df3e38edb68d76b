"""Simulation configuration files (TOML), validated field by field with pydantic.

A config has the sections ``[system]``, ``[body]`` or ``[[bodies]]``, ``[kinetic]``,
``[[potential]]``, ``[initial]`` and ``[run]`` (README, "Config file", documents every field),
and optionally ``[sweep]`` (an ensemble of runs, read by :mod:`affinebody.sweep` only) and
``[phonons]`` (lattice dynamics, read by ``affinebody phonons`` only).
Loading goes in two passes:

1. :func:`parse_config` checks types and refuses unknown keys (pydantic, ``extra="forbid"``);
2. :func:`check_config` checks meaning: shapes against ``system.n`` and the number of bodies,
   positive masses and inertia, the kinetic model's parameters (e.g. af-is is positive definite
   exactly when I + A > 0, I - A > 0 and I + A + nB > 0, docs/theory/conventions.md), group
   membership of the initial phi, potentials (expressions are compiled by the restricted
   evaluator of :mod:`affinebody.expressions`, so a config can never run code).

Every failure is a :class:`ConfigError` (a ``ValueError``) with one line that names the field,
e.g. ``config error: kinetic.I must be > |kinetic.A| for af-is to be positive definite
(got I=0.2, A=0.5)``.

:func:`build` then turns a checked config into the objects of the dynamics: a
:class:`~affinebody.system.HamiltonianSystem`, the initial :class:`~affinebody.state.State`,
masses and drawing radii.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import tomllib
import warnings
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any, Literal

import jax
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from affinebody import integrators as _integrators
from affinebody import kinetic as _kinetic
from affinebody import units as _units
from affinebody.groups import CONFIGURATION_SPACES

#: Internal kinetic models and the parameters each one takes (paper's names, section 3: the
#: registry ``kinetic.MODELS``, each model class declaring its ``parameters``).
INTERNAL_MODELS: dict[str, tuple[str, ...]] = {
    name: model.parameters for name, model in _kinetic.MODELS.items()}
#: Translational kinetic models: d'Alembert (63) (alias is-af) and af-is (64), (78a); the
#: registry is ``kinetic.TRANSLATIONAL_MODELS``.
TRANSLATIONAL_MODELS = tuple(_kinetic.TRANSLATIONAL_MODELS)
#: Integrator names accepted by run.integrator (the registry ``integrators.INTEGRATORS``).
INTEGRATOR_NAMES = tuple(_integrators.INTEGRATORS)
#: Integrators that can sum pair forces over a neighbour list (the splitting methods).
SPLITTING_INTEGRATORS = _integrators.NEIGHBOR_LIST_INTEGRATORS
#: run.neighbor_list = "auto" uses a list from this many bodies on (if the system allows one).
AUTO_NEIGHBOR_LIST_BODIES = 500
#: Configuration groups accepted by system.group (the paper's list plus all matrices "L").
CONFIG_GROUPS = CONFIGURATION_SPACES
MAX_DIMENSION = 6
#: The most k points per segment of a phonon path (phonons.points and --points).
MOST_PATH_POINTS = 100_000
#: The largest integer a count or a seed may be: H5MD attributes, NumPy and JAX hold int64.
INT64_MAX = 2**63 - 1
#: The names ``system.units`` accepts (``units.UNIT_SYSTEMS``).
UnitSystem = Literal[tuple(_units.UNIT_SYSTEMS)]


class ConfigError(ValueError):
    """A config that cannot be used; the message is one line naming the field."""

    def __init__(self, message: str):
        super().__init__(message if message.startswith("config error") else
                         f"config error: {message}")


# --------------------------------------------------------------------------- schema
class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


Vector = list[float]
Matrix = list[list[float]]
Matrices = list[list[list[float]]]
Tensor4 = list[list[list[list[float]]]]


class SystemSection(_Section):
    """``[system]``: dimension, configuration group, bodies, periodic box."""

    n: int = Field(ge=1, le=MAX_DIMENSION, description="spatial dimension n")
    group: str = Field("GL+", description="configuration group of each phi")
    bodies: int | list[str] | None = Field(None, description="number of bodies or their labels")
    box: Vector | None = Field(None, description="edges of a periodic orthorhombic box")
    units: UnitSystem = Field(
        "reduced", description="unit system of every number: reduced (sigma, m, tau, epsilon) "
                               "or gromacs (nm, u, ps, kJ/mol); written to the H5MD file")


class Constituents(_Section):
    """Point masses making up a body, in material coordinates (eq. (8))."""

    masses: Vector
    positions: Matrix


class BodySection(_Section):
    """``[body]`` (all bodies alike) or one entry of ``[[bodies]]``."""

    mass: float | None = Field(None, description="total mass M")
    inertia: float | Matrix | None = Field(None, description="J of eq. (8), or a scalar for J Id")
    constituents: Constituents | None = None
    radius: float = Field(0.5, description="drawing radius: bodies are phi(ball of this radius)")
    label: str | None = None


class KineticSection(_Section):
    """``[kinetic]``: model names (paper's labels) and their inertial parameters."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, populate_by_name=True)

    translational: str = "dalembert"
    internal: str = "dalembert"
    I: float | None = None  # noqa: E741
    A: float | None = None
    B: float | None = None
    J: float | Matrix | None = None
    H: float | Matrix | None = None
    L: Tensor4 | None = None
    R: Tensor4 | None = None


class PotentialSection(BaseModel):
    """One ``[[potential]]`` entry: a built-in family by ``kind`` with its parameters, and/or an
    ``expr`` in the invariants of that kind. Parameters are checked by :mod:`affinebody.potentials`.
    """

    model_config = ConfigDict(extra="allow", strict=True, frozen=True)

    kind: str
    expr: str | None = None


class InitialSection(_Section):
    """``[initial]``: explicit arrays, or a generator (lattice / random) they override, or a
    frame of a trajectory file (generator "file": :func:`file_frame`)."""

    generator: Literal["explicit", "lattice", "random", "file"] | None = None
    x: Matrix | None = None
    phi: Matrices | None = None
    velocity: Matrix | None = None
    phi_velocity: Matrices | None = None
    momentum: Matrix | None = None
    phi_momentum: Matrices | None = None
    spacing: float = 1.0
    shape: list[int] | None = None
    origin: Vector | None = None
    extent: float | None = None
    jitter: float = 0.0
    phi_noise: float = 0.0
    momentum_scale: float = 0.0
    phi_momentum_scale: float = 0.0
    zero_momentum: bool = True
    seed: int | None = Field(None, ge=0, le=INT64_MAX, description="default: run.seed")
    file: str | None = Field(None, description="an affinebody H5MD trajectory (a path from the "
                                               "working directory) whose frame starts the run "
                                               "(generator 'file', implied)")
    frame: int = Field(-1, description="the file's frame (negative: from the end)")
    file_momenta: bool = Field(True, description="take p and pi from the frame (false: from "
                                                 "the momentum options, as a generator does)")
    rescale: bool = Field(False, description="map the frame's positions from its box into "
                                             "system.box (each coordinate times the ratio of "
                                             "the edges; body shapes phi kept)")


class RunSection(_Section):
    """``[run]``: time step, length, integrator, output and checkpoint intervals, seed, and
    whether pair forces are summed over a cell/neighbour list (:func:`uses_neighbor_list`)."""

    dt: float
    steps: int = Field(ge=1, le=INT64_MAX)
    integrator: str = "strang"
    every: int = Field(1, ge=1, le=INT64_MAX, description="write a frame every k steps")
    checkpoint: int | None = Field(None, ge=1, le=INT64_MAX,
                                   description="checkpoint every m steps")
    seed: int = Field(0, ge=0, le=INT64_MAX, description="initial state and barostat draws")
    neighbor_list: Literal["auto", "on", "off"] = Field(
        "auto", description="sum pair forces over a neighbour list: on, off (all pairs), or "
                            f"auto (on for >= {AUTO_NEIGHBOR_LIST_BODIES} bodies if possible)")
    neighbor_skin: float = Field(0.3, description="skin of the neighbour list (> 0)")
    pressure: bool = Field(False, description="record the pressure tensor and the volume of "
                                              "the periodic box (always with a [barostat])")


class ThermostatSection(_Section):
    """``[thermostat]``: NVT by a Langevin or a stochastic velocity rescaling (Bussi) thermostat
    (:mod:`affinebody.thermostats`, docs/thermostats.md)."""

    kind: Literal["langevin", "bussi"]
    temperature: float = Field(description="kT in energy units (k_B = 1)")
    friction: float | None = Field(None, description="langevin: friction gamma, 1/time")
    tau: float | None = Field(None, description="bussi: relaxation time of the kinetic energy")
    seed: int = Field(0, ge=0, lt=2**32, description="step k draws from fold_in(key(seed), k)")
    splitting: Literal["obabo", "baoab"] = Field(
        "obabo", description="where the O step goes: obabo, after each step (one drift per "
                             "step); baoab, in the middle of the middle drift")


class ScanRange(_Section):
    """A range of values for one scanned field: ``num`` values from ``start`` to ``stop``
    (both included), evenly spaced, or geometrically spaced with ``log = true``."""

    start: float
    stop: float
    num: int = Field(ge=1, le=10_000)
    log: bool = False


class SweepSection(_Section):
    """``[sweep]``: an ensemble of runs of this config (``affinebody sweep``,
    :mod:`affinebody.sweep` documents every field)."""

    samples: int = Field(1, ge=1, le=INT64_MAX, description="samples per parameter point")
    seed: int = Field(0, ge=0, lt=2**32,
                      description="sample k draws from the key fold_in(key(seed), k)")
    initial_velocity: Literal["none", "normal"] = Field(
        "none", description="draw Omega_hat ~ N(0, 1) projected onto the group's Lie algebra")
    velocity_scale: float = Field(1.0, ge=0)
    x_velocity: Literal["none", "normal"] = Field("none", description="draw dx/dt ~ N(0, 1)")
    x_velocity_scale: float = Field(1.0, ge=0)
    bound: float = Field(1000.0, gt=1, description="bounded: sigma_max(phi^+-1) < bound")
    batch: int = Field(64, ge=1, le=100_000, description="samples per task (vmapped)")
    equilibration: int = Field(0, ge=0, le=INT64_MAX,
                               description="thermostatted sweeps: steps run before the time "
                                           "averages start")
    scan: dict[str, list[float | str] | ScanRange] = Field(
        default_factory=dict, description="dotted config field -> values or a range")


class ConstraintsSection(_Section):
    """``[constraints]``: non-holonomic rotationless motion (paper §1)."""

    rotationless: Literal["spatial", "material"] | None = Field(
        None, description="'spatial': Omega symmetric (40); 'material': Omega_hat symmetric (41)")


class PhononsSection(_Section):
    """``[phonons]``: lattice dynamics of the crystal in the periodic box (``affinebody
    phonons``, :mod:`affinebody.phonons`)."""

    relax: bool = Field(False, description="relax positions and shapes phi to the nearest "
                                           "minimum first (the cell is kept)")
    relax_cell: bool = Field(False, description="with relax: relax the orthorhombic cell "
                                                "edges too (zero stress)")
    tolerance: float = Field(1e-6, gt=0, description="largest residual generalized force "
                                                    "accepted as an equilibrium")
    path: list[str] | None = Field(None, description="high-symmetry points, e.g. "
                                                     "['G', 'X', 'M', 'G']")
    points: int = Field(50, ge=2, le=MOST_PATH_POINTS, description="k points per path segment")
    mesh: list[int] | None = Field(None, description="DOS mesh: n positive integers")
    cells: list[int] | None = Field(None, description="primitive cells per box edge "
                                                      "(default: found from the bodies)")


class BarostatSection(_Section):
    """``[barostat]``: constant pressure by stochastic cell rescaling (docs/pressure.md,
    :mod:`affinebody.barostat`)."""

    kind: Literal["c-rescale"] = Field("c-rescale", description="stochastic cell rescaling "
                                                                 "(Bernetti and Bussi 2020)")
    pressure: float | Matrix = Field(description="target pressure P0: a number or an n x n "
                                                 "tensor")
    tau: float = Field(description="time constant of the pressure relaxation")
    compressibility: float = Field(description="isothermal compressibility beta_T (sets the "
                                               "relaxation rate, not the distribution)")
    coupling: Literal["isotropic", "anisotropic"] = Field(
        "isotropic", description="isotropic: the box scales as a whole; anisotropic: each "
                                 "edge of the orthorhombic box moves")
    temperature: float | None = Field(None, description="kT of the barostat's noise (the "
                                                      "temperature of the ensemble); default: "
                                                      "thermostat.temperature")
    interval: int = Field(1, ge=1, le=INT64_MAX,
                          description="steps between two moves of the box, each "
                                      "of length interval * dt (as GROMACS's "
                                      "nstpcouple; about 10 makes an NPT step cost "
                                      "little more than an NVT one)")
    metropolis: bool = Field(False, description="accept or reject each move by a "
                                                 "Metropolis-Hastings test: the ensemble "
                                                 "exact at any interval * dt (docs/pressure.md)")


class Config(_Section):
    """A whole configuration file."""

    system: SystemSection
    body: BodySection | None = None
    bodies: list[BodySection] | None = None
    kinetic: KineticSection = KineticSection()
    potential: list[PotentialSection] = []
    initial: InitialSection = InitialSection()
    run: RunSection
    constraints: ConstraintsSection = ConstraintsSection()
    sweep: SweepSection | None = None
    phonons: PhononsSection | None = None
    barostat: BarostatSection | None = None
    thermostat: ThermostatSection | None = None
    # the text the config was read from (not a TOML key)
    source_text: str = Field("", exclude=True, repr=False)

    @property
    def n(self) -> int:
        return self.system.n

    @property
    def bodies_count(self) -> int:
        return _body_count(self)

    @property
    def checkpoint_every(self) -> int:
        """Steps between checkpoints: run.checkpoint, or by default 10 frames' worth."""
        if self.run.checkpoint is not None:
            return self.run.checkpoint
        return self.run.every * 10

    def _meaning(self) -> dict:
        """The config's values that change a single run: all but run.steps (so a run can be
        extended) and the [sweep] and [phonons] tables."""
        return self.model_dump(exclude={"source_text": True, "sweep": True, "phonons": True,
                                        "run": {"steps"}})

    def hash(self) -> str:
        """SHA-256 of the config's meaning, ignoring run.steps (so a run can be extended) and
        the [sweep] and [phonons] tables (which do not change a single run)."""
        data = self._meaning()
        for key, default in (("neighbor_list", "auto"), ("neighbor_skin", 0.3),
                             ("pressure", False)):
            if data["run"][key] == default:  # hashes of configs written before these keys
                del data["run"][key]
        if data["system"]["units"] == "reduced":  # the same, for system.units
            del data["system"]["units"]
        if data.get("barostat") is None:  # the same, for runs without a barostat
            data.pop("barostat", None)
        if data["thermostat"] is None:  # the same, for NVE configs
            del data["thermostat"]
        canonical = json.dumps(data, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()

    def changes_from(self, other: Config) -> list[str]:
        """The settings in which this config differs from ``other`` where :meth:`hash` sees
        them, each as ``"run.dt = 0.005 -> 0.004"`` (``other``'s value first); empty when
        they mean the same run (run.steps, [sweep] and [phonons] are never listed)."""
        return [f"{key} = {_shown(old)} -> {_shown(new)}"
                for key, old, new in _changed_leaves(other._meaning(), self._meaning(), "")]


def _changed_leaves(old, new, key: str):
    """(dotted key, old value, new value) of every leaf of two model dumps that differs; a
    list of another length, or a table present on one side only, is one leaf."""
    if isinstance(old, dict) and isinstance(new, dict):
        for name in sorted(old.keys() | new.keys()):
            yield from _changed_leaves(old.get(name), new.get(name),
                                       f"{key}.{name}" if key else name)
    elif isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        for i, (a, b) in enumerate(zip(old, new, strict=True)):
            yield from _changed_leaves(a, b, f"{key}[{i}]")
    elif old != new:
        yield key, old, new


def _shown(value) -> str:
    """A config value as a message shows it: TOML-like, None as "(not set)"."""
    return "(not set)" if value is None else json.dumps(value, separators=(", ", " = "))


# --------------------------------------------------------------------------- parsing
_TYPE_WORDS = {
    "float_type": "a number",
    "float_parsing": "a number",
    "int_type": "an integer",
    "int_parsing": "an integer",
    "int_from_float": "an integer",
    "string_type": "a string",
    "bool_type": "true or false",
    "list_type": "an array",
    "model_type": "a table",
    "dict_type": "a table",
}


def _model_names() -> set[str]:
    """The class names of the pydantic models defined so far: the tag pydantic puts in an
    error's location for a model member of a union (``ScanRange``)."""
    seen: set[type] = set()
    stack = [BaseModel]
    while stack:
        for sub in stack.pop().__subclasses__():
            if sub not in seen:
                seen.add(sub)
                stack.append(sub)
    return {cls.__name__ for cls in seen}


def _location(loc: tuple) -> str:
    """Dotted field name from a pydantic location, as TOML writes it: union-member tags
    dropped (a type, ``float``, ``list[list[float]]``, or a model's class name, ``ScanRange``),
    and a table key that is not a bare TOML key quoted (``sweep.scan."kinetic.A".num``)."""
    parts: list[str] = []
    models = None
    for item in loc:
        if isinstance(item, int):
            parts.append(str(item))
            continue
        if not isinstance(item, str) or ("[" in item and item.endswith("]")):
            continue  # a type's tag ("list[union[float,str]]") or a dict key's ("[key]")
        if parts and item in ("int", "float", "str", "bool", "list", "dict"):
            continue
        if parts and item.isidentifier():
            models = _model_names() if models is None else models
            if item in models:
                continue
        bare = item and all(c.isascii() and (c.isalnum() or c in "_-") for c in item)
        parts.append(item if bare else json.dumps(item, ensure_ascii=False))
    return ".".join(parts) or "config"


def one_line_error(err: ValidationError) -> str:
    """The most useful single error of a pydantic ValidationError, as one line."""
    errors = err.errors(include_url=False)
    unknown = [e for e in errors if e["type"] == "extra_forbidden"]
    errors = unknown or errors  # a misspelt key explains the "missing" one it replaces
    # a union reports one error per member: prefer the one that went deepest
    first = max(errors, key=lambda e: len(e["loc"])) if len(
        {_location(e["loc"][:1]) for e in errors}) == 1 else errors[0]
    where = _location(first["loc"])
    kind = first["type"]
    value = first.get("input")
    if kind == "extra_forbidden":
        return f"{where}: unknown key (check the spelling; see the README for the fields)"
    if kind == "missing":
        return f"{where} is required"
    if kind in _TYPE_WORDS:
        union = [e for e in errors if _location(e["loc"]) == where]
        words = sorted({_TYPE_WORDS.get(e["type"], e["type"]) for e in union})
        return f"{where} must be {' or '.join(words)} (got {_show(value)})"
    bounds = {"greater_than_equal": (">=", "ge"), "greater_than": (">", "gt"),
              "less_than_equal": ("<=", "le"), "less_than": ("<", "lt")}
    if kind in bounds:
        symbol, key = bounds[kind]
        return f"{where} must be {symbol} {first.get('ctx', {}).get(key)} (got {_show(value)})"
    if kind == "literal_error":
        return f"{where}: {first['msg'].replace('Input should be', 'must be')} (got {_show(value)})"
    return f"{where}: {first['msg']} (got {_show(value)})"


def _numbers(value: Any) -> list[float]:
    """Every number in a (nested) list, whatever its shape (shapes are checked elsewhere)."""
    return ([v for item in value for v in _numbers(item)] if isinstance(value, list)
            else [float(value)])


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def load_toml(text: str, source: str = "config") -> dict:
    """The TOML document ``text`` as a dict; a syntax error is a one-line :class:`ConfigError`."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{source} is not valid TOML: {err}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise ConfigError(f"{source}: arrays or tables nested too deeply to read (a config "
                          f"needs at most 4 levels)") from None


def parse_config(text: str, source: str = "config") -> Config:
    """Parse TOML ``text`` and check types and keys; raises :class:`ConfigError`."""
    data = load_toml(text, source)
    try:
        config = Config.model_validate({**data, "source_text": text} if "source_text" not in data
                                       else data)
    except ValidationError as err:
        raise ConfigError(one_line_error(err)) from None
    return config


def load_config(path: str | Path) -> Config:
    """Read, parse and check a config file (both passes); raises :class:`ConfigError`."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"cannot read {path}: {err.strerror}") from None
    if raw.startswith(b"\x89HDF\r\n\x1a\n"):
        raise ConfigError(f"{path} is an HDF5 file (a trajectory?), not a TOML config: give the "
                          f"config the run was made from")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ConfigError(f"cannot read {path}: not a UTF-8 text file ({err.reason} at byte "
                          f"{err.start})") from None
    config = parse_config(text, str(path))
    check_config(config)
    return config


# --------------------------------------------------------------------------- meaning
def _array(value, field: str, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a float64 array of exactly ``shape``; ConfigError naming ``field``."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise ConfigError(f"{field} must be a rectangular array of shape {list(shape)} "
                          f"(rows of different lengths)") from None
    if arr.shape != shape:
        raise ConfigError(f"{field} must have shape {list(shape)} (got {list(arr.shape)})")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{field} must be finite")
    return arr


def _initial_generator(i: InitialSection) -> str | None:
    """The generator of ``[initial]``: as given, else "file" with a file, "explicit" with x."""
    if i.generator is not None:
        return i.generator
    return "file" if i.file is not None else "explicit" if i.x is not None else None


@dataclass(frozen=True)
class FileHeader:
    """What ``initial.file`` holds, read without its frames (O(frames), not O(N frames))."""

    bodies: int
    n: int
    frames: int
    boxes: np.ndarray | None  # [frames, n] edges of a periodic run, else None
    units: str


def _file_header(path: str | None) -> FileHeader:
    """The :class:`FileHeader` of ``initial.file``; ConfigError naming the field otherwise."""
    if path is None:
        raise ConfigError("initial.file is required when initial.generator = 'file'")
    try:
        stat = os.stat(path)
    except OSError as err:
        raise ConfigError(f"initial.file: cannot read {path} ({err.strerror}; a path from the "
                          f"working directory)") from None
    return _read_file_header(os.path.abspath(path), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=8)
def _read_file_header(path: str, mtime_ns: int, size: int) -> FileHeader:
    from affinebody.h5md import TrajectoryFileError, open_trajectory

    try:
        with open_trajectory(path) as trajectory:
            boxes = None if trajectory.boxes is None else np.array(trajectory.boxes)
            return FileHeader(trajectory.bodies, trajectory.n, trajectory.frames, boxes,
                              trajectory.units)
    except TrajectoryFileError as err:
        raise ConfigError(f"initial.file: {err}") from None


def _file_frame_index(config: Config) -> int:
    """``initial.frame`` as an index from 0; ConfigError where the file has no such frame."""
    i = config.initial
    header = _file_header(i.file)
    if header.frames == 0:
        raise ConfigError(f"initial.file: {i.file} holds no frame yet")
    if not -header.frames <= i.frame < header.frames:
        raise ConfigError(f"initial.frame = {i.frame} is beyond the {header.frames} frames of "
                          f"{i.file} (-1 is the last)")
    return i.frame % header.frames


def file_frame(config: Config) -> tuple[np.ndarray, ...]:
    """(x [N, n], phi [N, n, n], p [N, n], pi [N, n, n]) of frame ``initial.frame`` of
    ``initial.file`` (generator "file"), read alone (O(N) memory for any file); with
    ``initial.rescale`` the positions are mapped from the frame's box into ``system.box``,
    x_i -> x_i L_i / L'_i, the body shapes phi and the momenta kept (a box change alone: the
    convention of docs/pressure.md, where phi is not scaled with the box)."""
    from affinebody.h5md import TrajectoryFileError, open_trajectory

    i = config.initial
    k = _file_frame_index(config)
    try:
        with open_trajectory(i.file) as trajectory:
            x, phi, p, pi = (np.asarray(getattr(trajectory, name)[k], dtype=np.float64)
                             for name in ("x", "phi", "p", "pi"))
    except TrajectoryFileError as err:
        raise ConfigError(f"initial.file: {err}") from None
    bad = ~(np.all(np.isfinite(x), axis=-1) & np.all(np.isfinite(phi), axis=(-2, -1))
            & np.all(np.isfinite(p), axis=-1) & np.all(np.isfinite(pi), axis=(-2, -1)))
    if np.any(bad):
        raise ConfigError(f"initial.file: frame {k} of {i.file} holds a non-finite state of "
                          f"body {int(np.argmax(bad))}")
    if i.rescale:  # _check_initial_file: both boxes are there
        x = x * (np.asarray(config.system.box, dtype=np.float64) / _file_header(i.file).boxes[k])
    return x, phi, p, pi


def _check_initial_file(config: Config) -> None:
    """The frame of ``initial.file`` fits the config: dimension, units, box (its own or
    ``initial.rescale``), and no array of ``[initial]`` given twice."""
    i, n = config.initial, config.n
    header = _file_header(i.file)
    for name in ("x", "phi"):
        if getattr(i, name) is not None:
            raise ConfigError(f"initial.{name} comes from initial.file: remove initial.{name}")
    for name in ("velocity", "momentum", "phi_velocity", "phi_momentum"):
        if i.file_momenta and getattr(i, name) is not None:
            raise ConfigError(f"initial.{name}: the momenta come from initial.file; set "
                              f"initial.file_momenta = false to give them here")
    if header.n != n:
        raise ConfigError(f"initial.file: {i.file} holds bodies in n = {header.n}, but "
                          f"system.n = {n}")
    if header.units != config.system.units:
        raise ConfigError(f"initial.file: {i.file} is in {header.units} units, but "
                          f"system.units = {config.system.units!r}: set it to "
                          f"{header.units!r}")
    k = _file_frame_index(config)
    box = None if header.boxes is None else header.boxes[k]
    given = None if config.system.box is None else np.asarray(config.system.box, np.float64)
    edges = None if box is None else "[" + ", ".join(f"{e:.17g}" for e in box) + "]"
    if i.rescale:
        if box is None or given is None:
            raise ConfigError("initial.rescale maps the frame's periodic box into system.box: "
                              "it needs both (the file's run had no box, or system.box is "
                              "not set)")
        return
    if box is not None and given is None:
        raise ConfigError(f"initial.file: frame {k} of {i.file} is in a periodic box: set "
                          f"system.box = {edges}")
    if box is not None and not np.allclose(box, given, rtol=1e-12, atol=0.0):
        raise ConfigError(f"initial.file: frame {k} of {i.file} has the box {edges}, not "
                          f"system.box: set system.box to it, or initial.rescale = true to "
                          f"map the positions into system.box")


def _body_count(config: Config) -> int:
    """N from system.bodies, [[bodies]], initial.x or initial.shape (checked to agree)."""
    counts: dict[str, int] = {}
    b = config.system.bodies
    if b is not None:
        counts["system.bodies"] = b if isinstance(b, int) else len(b)
    if config.bodies is not None:
        counts["bodies"] = len(config.bodies)
    if config.initial.x is not None:
        counts["initial.x"] = len(config.initial.x)
    if _initial_generator(config.initial) == "file":
        counts["initial.file"] = _file_header(config.initial.file).bodies
    if not counts:
        raise ConfigError("system.bodies is required (the number of bodies or a list of labels)")
    values = set(counts.values())
    if len(values) > 1:
        described = ", ".join(f"{k} gives {v}" for k, v in counts.items())
        raise ConfigError(f"the number of bodies disagrees: {described}")
    count = values.pop()
    if count < 1:
        raise ConfigError(f"{next(iter(counts))}: need at least one body")
    return count


def _positive(value: float | None, field: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ConfigError(f"{field} must be > 0 (got {value})")


def _spd(value, field: str, n: int) -> np.ndarray:
    """A symmetric positive definite n x n matrix from a scalar s (s Id) or a matrix."""
    if isinstance(value, int | float):
        _positive(value, field)
        return float(value) * np.eye(n)
    arr = _array(value, field, (n, n))
    if not np.allclose(arr, arr.T, rtol=0, atol=1e-12 * max(1.0, np.abs(arr).max())):
        raise ConfigError(f"{field} must be symmetric")
    smallest = float(np.linalg.eigvalsh(arr).min())
    if smallest <= 0:
        raise ConfigError(f"{field} must be positive definite (smallest eigenvalue {smallest:.3g})")
    return arr


@dataclass(frozen=True)
class Inertia:
    """Per-body inertial data: mass [N], J [N, n, n] (or None if not derivable), radius [N]."""

    mass: np.ndarray
    J: np.ndarray
    radius: np.ndarray
    labels: tuple[str, ...]


def _one_body_inertia(field: str, body, n: int) -> tuple[float, np.ndarray, float]:
    """(mass, J of eq. (8), drawing radius) of one [body] / [[bodies]] entry, checked."""
    _positive(body.mass, f"{field}.mass")
    _positive(body.radius, f"{field}.radius")
    mass = body.mass
    J = None
    if body.constituents is not None:
        c = body.constituents
        cm = _array(c.masses, f"{field}.constituents.masses", (len(c.masses),))
        pos = _array(c.positions, f"{field}.constituents.positions", (len(c.masses), n))
        if np.any(cm <= 0):
            raise ConfigError(f"{field}.constituents.masses must all be > 0")
        total = float(cm.sum())
        rel = pos - cm @ pos / total
        J = np.einsum("p,pk,pl->kl", cm, rel, rel)
        if np.linalg.eigvalsh(J).min() <= 1e-12 * max(1.0, np.abs(J).max()):
            raise ConfigError(
                f"{field}.constituents span fewer than n = {n} dimensions, so J of eq. (8) "
                f"is singular (need n + 1 points not in one hyperplane)")
        if mass is not None and not math.isclose(mass, total, rel_tol=1e-12):
            raise ConfigError(f"{field}.mass = {mass} disagrees with the constituents' total "
                              f"mass {total} (drop one of them)")
        if body.inertia is not None:
            raise ConfigError(f"{field}: give inertia or constituents, not both")
        mass = total
    elif body.inertia is not None:
        J = _spd(body.inertia, f"{field}.inertia", n)
    mass = 1.0 if mass is None else mass
    if J is None:  # a uniform ball of the drawing radius, J = M r^2 / (n + 2) Id
        with np.errstate(all="ignore"):  # inf * 0 off the diagonal: refused below
            J = np.float64(mass) * np.float64(body.radius) ** 2 / (n + 2) * np.eye(n)
        if not np.all(np.isfinite(J)):
            raise ConfigError(f"{field}.radius = {body.radius} with mass {mass} gives an inertia "
                              f"M r^2 / (n + 2) beyond float64: give {field}.inertia or a "
                              f"smaller radius")
    return mass, J, body.radius


def body_inertia(config: Config) -> Inertia:
    """Masses, J (eq. (8)) and drawing radii of every body, checked."""
    n, count = config.n, config.bodies_count
    if config.body is not None and config.bodies is not None:
        raise ConfigError("give either [body] (identical bodies) or [[bodies]], not both")
    system_labels = config.system.bodies if isinstance(config.system.bodies, list) else None
    if config.bodies is None:  # identical bodies: check one, broadcast (O(1) Python work)
        body = config.body or BodySection()
        mass, J, radius = _one_body_inertia("body", body, n)
        labels = ((body.label,) * count if body.label else tuple(system_labels) if system_labels
                  else tuple(f"B{k}" for k in range(count)))
        return Inertia(np.full(count, mass), np.broadcast_to(J, (count, n, n)).copy(),
                       np.full(count, radius), labels)
    masses, inertias, radii, labels = [], [], [], []
    for k, body in enumerate(config.bodies):
        mass, J, radius = _one_body_inertia(f"bodies.{k}", body, n)
        masses.append(mass)
        inertias.append(J)
        radii.append(radius)
        labels.append(body.label or (system_labels[k] if system_labels else f"B{k}"))
    return Inertia(np.asarray(masses), np.asarray(inertias), np.asarray(radii), tuple(labels))


def check_kinetic(config: Config) -> None:
    """Model names exist, every parameter the model needs is there, none it ignores is given,
    and the quadratic form is positive definite (docs/theory/conventions.md: (73)/(74) need
    I + A > 0, I - A > 0, I + A + nB > 0; af-af (72) is indefinite by construction and allowed)."""
    k, n = config.kinetic, config.n
    if k.translational not in TRANSLATIONAL_MODELS:
        raise ConfigError(f"kinetic.translational must be one of {', '.join(TRANSLATIONAL_MODELS)} "
                          f"(got {k.translational!r})")
    if k.internal not in INTERNAL_MODELS:
        raise ConfigError(f"kinetic.internal must be one of {', '.join(INTERNAL_MODELS)} "
                          f"(got {k.internal!r})")
    needed = INTERNAL_MODELS[k.internal]
    for name in ("I", "A", "B", "J", "H", "L", "R"):
        value = getattr(k, name)
        if value is not None and not all(map(math.isfinite, _numbers(value))):
            raise ConfigError(f"kinetic.{name} must be finite (got {_show(value)})")
        if name in needed and value is None and name not in ("J", "B"):
            raise ConfigError(f"kinetic.{name} is required by the internal model {k.internal!r}")
        if name not in needed and value is not None:
            uses = ", ".join(needed)
            raise ConfigError(f"kinetic.{name} is not a parameter of the internal model "
                              f"{k.internal!r} (it uses {uses})")
    if k.internal in ("is-af", "af-is"):
        I, A, B = k.I, k.A, 0.0 if k.B is None else k.B
        if not I > abs(A):
            raise ConfigError(f"kinetic.I must be > |kinetic.A| for {k.internal} to be positive "
                              f"definite (got I={I}, A={A})")
        if not I + A + n * B > 0:
            raise ConfigError(f"kinetic.B must be > -(I + A)/n for {k.internal} to be positive "
                              f"definite (got I={I}, A={A}, B={B}, n={n})")
    if k.internal == "af-af" and k.A == 0:
        raise ConfigError("kinetic.A must be nonzero for af-af (72) (got A=0)")
    if k.internal in ("dalembert", "af-J") and k.J is not None:
        _spd(k.J, "kinetic.J", n)
    if k.internal == "H-af":
        _spd(k.H, "kinetic.H", n)
    for name in ("L", "R"):
        value = getattr(k, name)
        if value is not None and name in needed:
            tensor = _array(value, f"kinetic.{name}", (n, n, n, n))
            matrix = tensor.reshape(n * n, n * n)
            if not np.allclose(matrix, matrix.T, atol=1e-12 * max(1.0, np.abs(matrix).max())):
                raise ConfigError(f"kinetic.{name} must be symmetric under exchanging its two "
                                  f"index pairs")
            if np.linalg.eigvalsh(matrix).min() <= 0:
                raise ConfigError(f"kinetic.{name} must be positive definite as an "
                                  f"n^2 x n^2 matrix")


def check_thermostat(config: Config) -> None:
    """``[thermostat]``: its parameters and a positive definite T."""
    t = config.thermostat
    if t is None:
        return
    needed, other = ("friction", "tau") if t.kind == "langevin" else ("tau", "friction")
    for name in ("temperature", needed):
        value = getattr(t, name)
        if value is None:
            raise ConfigError(f"thermostat.{name} is required by the {t.kind} thermostat")
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"thermostat.{name} must be a finite number > 0 (got {value})")
    if getattr(t, other) is not None:
        raise ConfigError(f"thermostat.{other} is not a parameter of the {t.kind} thermostat "
                          f"(it uses temperature, {needed}, seed)")
    hot = _units.kelvin(config.system.units, t.temperature)
    if hot is not None and hot > _units.PLAUSIBLE_KELVIN:
        k_b = _units.BOLTZMANN[config.system.units]
        warnings.warn(f"thermostat.temperature = {t.temperature:g} is kT in "
                      f"{_units.UNIT_LABELS[config.system.units]['energy']} with system.units = "
                      f"\"{config.system.units}\" (k_B = 1), that is {hot:.0f} K; for T in "
                      f"kelvin give T x {k_b:.6g} (300 K: {300 * k_b:.4g})", UserWarning,
                      stacklevel=2)
    if config.kinetic.internal == "af-af":
        raise ConfigError("thermostat: kinetic.internal 'af-af' (72) has an indefinite kinetic "
                          "energy, so no canonical ensemble exists; use a positive definite model")


def build_thermostat(config: Config):
    """The ``thermostats.Langevin`` / ``Bussi`` of ``[thermostat]``, or None (NVE)."""
    from affinebody import thermostats

    t = config.thermostat
    if t is None:
        return None
    if t.kind == "langevin":
        return thermostats.Langevin(t.temperature, t.friction, t.seed, t.splitting)
    return thermostats.Bussi(t.temperature, t.tau, t.seed, t.splitting)


def check_run(config: Config) -> None:
    r = config.run
    if not (math.isfinite(r.dt) and r.dt > 0):
        raise ConfigError(f"run.dt must be > 0 (got {r.dt})")
    if r.integrator not in INTEGRATOR_NAMES:
        raise ConfigError(f"run.integrator must be one of {', '.join(INTEGRATOR_NAMES)} "
                          f"(got {r.integrator!r})")
    rotationless = config.constraints.rotationless
    if rotationless is not None and r.integrator != "nonholonomic-rattle":
        raise ConfigError(f"run.integrator must be 'nonholonomic-rattle' when "
                          f"constraints.rotationless is set (got {r.integrator!r})")
    if rotationless is None and r.integrator == "nonholonomic-rattle":
        raise ConfigError("run.integrator 'nonholonomic-rattle' needs constraints.rotationless "
                          "= 'spatial' or 'material'")
    if r.checkpoint is not None and r.checkpoint % r.every:
        raise ConfigError(f"run.checkpoint must be a multiple of run.every (got checkpoint="
                          f"{r.checkpoint}, every={r.every})")
    if not (math.isfinite(r.neighbor_skin) and r.neighbor_skin > 0):
        raise ConfigError(f"run.neighbor_skin must be a finite number > 0 (got "
                          f"{r.neighbor_skin})")


def _neighbor_list_obstacle(config: Config, terms) -> str | None:
    """What keeps this config from summing its pair forces over a neighbour list, as
    "needs <what> (got <what>)", or None: a periodic box, pair terms that all have a cut-off
    on r with r_cut + run.neighbor_skin <= half the shortest box edge, a splitting integrator.
    ``terms``: the built [[potential]] entries."""
    from affinebody.potentials import NoNeighborRange, neighbor_range
    from affinebody.space import as_space

    r = config.run
    if r.integrator not in SPLITTING_INTEGRATORS:
        return (f"a splitting integrator, run.integrator = one of "
                f"{', '.join(SPLITTING_INTEGRATORS)} (got {r.integrator!r})")
    if config.system.box is None:
        return "a periodic box: set system.box (got no box)"
    try:
        _, r_cut, variable = neighbor_range(list(terms))
    except NoNeighborRange as err:
        if err.index is None:
            return "pair potentials with a cut-off (got no pair term in [[potential]])"
        got = "none" if terms[err.index].cutoff is None else "cut-offs that differ"
        return f"a cut-off on r in every pair term: set potential.{err.index}.r_cut (got {got})"
    if variable != "r":
        return "a cut-off on r in every pair term (got a cut-off on D)"
    half = as_space(tuple(config.system.box)).max_cutoff
    if r_cut + r.neighbor_skin > half * (1 + 1e-12):
        return (f"r_cut + run.neighbor_skin <= half the shortest box edge: reduce "
                f"run.neighbor_skin or enlarge system.box (got {r_cut} + {r.neighbor_skin} > "
                f"{half})")
    return None


def uses_neighbor_list(config: Config, terms=None) -> bool:
    """Whether a run of ``config`` sums its pair forces over a neighbour list.

    run.neighbor_list = "off": never (all pairs); "on": always, ConfigError when the system
    does not allow a list (:func:`_neighbor_list_obstacle` names the missing piece); "auto":
    when the system allows one and has at least AUTO_NEIGHBOR_LIST_BODIES bodies.
    ``terms``: the built [[potential]] entries (built here when None).
    """
    mode = config.run.neighbor_list
    if mode == "off" or (mode == "auto" and config.bodies_count < AUTO_NEIGHBOR_LIST_BODIES):
        return False
    if terms is None:
        terms = [build_potential_entry(e, k, config) for k, e in enumerate(config.potential)]
    obstacle = _neighbor_list_obstacle(config, terms)
    if obstacle is not None and mode == "on":
        raise ConfigError(f'run.neighbor_list = "on" needs {obstacle}; or set '
                          f'run.neighbor_list = "off"')
    return obstacle is None


def check_system(config: Config) -> None:
    s = config.system
    if s.group not in CONFIG_GROUPS:
        raise ConfigError(f"system.group must be one of {', '.join(CONFIG_GROUPS)} "
                          f"(got {s.group!r})")
    if s.box is not None:
        box = _array(s.box, "system.box", (s.n,))
        if np.any(box <= 0):
            raise ConfigError(f"system.box edges must all be > 0 (got {s.box})")
        if not math.prod(s.box) < 1e300:
            raise ConfigError(f"system.box = {s.box}: its volume is beyond float64 (choose "
                              f"units in which the edges are moderate numbers)")
    if isinstance(s.bodies, list) and len(set(s.bodies)) != len(s.bodies):
        raise ConfigError("system.bodies labels must be distinct")


def check_initial(config: Config) -> None:
    i, n, count = config.initial, config.n, config.bodies_count
    if i.file is not None and _initial_generator(i) != "file":
        raise ConfigError(f"initial.file is read with initial.generator = 'file' (got "
                          f"{i.generator!r}): remove one of them")
    if _initial_generator(i) == "file":
        _check_initial_file(config)
    elif i.rescale or not i.file_momenta or i.frame != -1:  # values: a dumped config has all
        raise ConfigError("initial.frame, initial.file_momenta and initial.rescale apply to "
                          "initial.file: set it or remove them")
    for name in ("x", "velocity", "momentum"):
        if getattr(i, name) is not None:
            _array(getattr(i, name), f"initial.{name}", (count, n))
    for name in ("phi", "phi_velocity", "phi_momentum"):
        if getattr(i, name) is not None:
            _array(getattr(i, name), f"initial.{name}", (count, n, n))
    if i.velocity is not None and i.momentum is not None:
        raise ConfigError("initial: give either velocity or momentum, not both")
    if i.phi_velocity is not None and i.phi_momentum is not None:
        raise ConfigError("initial: give either phi_velocity or phi_momentum, not both")
    if i.phi is not None:
        with np.errstate(over="ignore", invalid="ignore"):
            det = np.linalg.det(np.asarray(i.phi))
            scale = np.prod(np.linalg.norm(np.asarray(i.phi), axis=-2), axis=-1)
        huge = np.flatnonzero(~(np.isfinite(det) & np.isfinite(scale)))
        if huge.size:
            raise ConfigError(f"initial.phi.{huge[0]} is beyond float64 (its determinant "
                              f"overflows): give phi in units in which its entries are moderate")
        bad = np.flatnonzero(~(np.abs(det) > 1e-12 * scale))
        if bad.size:
            raise ConfigError(f"initial.phi.{bad[0]} is singular (det = {det[bad[0]]:.3g}): an "
                              f"internal configuration must be invertible")
    generator = _initial_generator(i)
    if generator is None:
        raise ConfigError("initial.x is required (or set initial.generator = 'lattice' or "
                          "'random')")
    if generator == "explicit" and i.x is None:
        raise ConfigError("initial.x is required when initial.generator = 'explicit'")
    if i.x is None:  # a key of the other generator would be silently ignored
        other = {"lattice": [("extent", i.extent is not None)],
                 "random": [("shape", i.shape is not None), ("jitter", i.jitter != 0)]}
        for name, given in other.get(generator, []):
            if given:
                raise ConfigError(f"initial.{name} is not read by generator = '{generator}' "
                                  f"(it belongs to the other generator): remove it")
    for name in ("spacing", "jitter", "phi_noise", "momentum_scale", "phi_momentum_scale"):
        value = getattr(i, name)
        if not (math.isfinite(value) and value >= 0) or (name == "spacing" and value == 0):
            raise ConfigError(f"initial.{name} must be {'> 0' if name == 'spacing' else '>= 0'} "
                              f"(got {value})")
    if i.jitter > 1:  # x moves by jitter x spacing x U(-1, 1): beyond 1 the lattice is gone
        raise ConfigError(f"initial.jitter is a fraction of initial.spacing and must be <= 1 "
                          f"(got {i.jitter}); for bodies placed at random use "
                          f"initial.generator = 'random'")
    if i.extent is not None:
        _positive(i.extent, "initial.extent")
    if i.shape is not None:
        if len(i.shape) != n or any(s < 1 for s in i.shape):
            raise ConfigError(f"initial.shape must be {n} positive integers (got {i.shape})")
        if math.prod(i.shape) < count:
            raise ConfigError(f"initial.shape {i.shape} has {math.prod(i.shape)} sites for "
                              f"{count} bodies")
    if i.origin is not None:
        _array(i.origin, "initial.origin", (n,))


def build_potential_entry(entry: PotentialSection, index: int, config: Config):
    """The potential of ``[[potential]]`` entry ``index`` (:mod:`affinebody.potentials`).

    ``kind = "dilatation"`` with an ``expr`` (as in the README's example) is the one-body
    expression potential sum_K f(det phi_K) of (80), (81), restricted to the variable ``det``.
    """
    from affinebody import potentials

    field = f"potential.{index}"
    params = dict(entry.model_extra or {})
    if entry.expr is not None:
        params["expr"] = entry.expr
    if entry.kind == "dilatation" and "expr" in params:
        extra = sorted(set(params) - {"expr"})
        if extra:
            raise ConfigError(f"{field}: a dilatation expression takes no other parameters "
                              f"(got {', '.join(extra)})")
        try:
            pot = potentials.OneBodyPotential.from_expression(params["expr"], config.n,
                                                              field=f"{field}.expr")
        except ValueError as err:
            raise ConfigError(str(err)) from None
        other = sorted(set(pot.variables) - {"det"})
        if other:
            raise ConfigError(f"{field}.expr: a dilatation potential depends on det only "
                              f"(got {', '.join(other)}; use kind = 'one-body')")
        return pot
    try:
        term = potentials.build_potential(entry.kind, params, n=config.n,
                                          box=config.system.box, field=field)
        term.check_dimension(config.n)  # else said at the first energy, without the entry
        return term
    except ValueError as err:  # said with the entry's place when the message lacks it
        message = str(err).removeprefix("config error: ")
        raise ConfigError(message if message.startswith(field) else
                          f"{field}: {message}") from None


def check_potentials(config: Config) -> None:
    """Every [[potential]] entry builds (kind known, parameters valid, expression allowed),
    and run.neighbor_list = "on" finds what a neighbour list needs."""
    terms = [build_potential_entry(entry, k, config) for k, entry in enumerate(config.potential)]
    uses_neighbor_list(config, terms)


#: Memory of ``affinebody run`` per body with a neighbour list, measured in 3D (README: 0.69 GiB
#: at 10^3 bodies, 6.05 GiB at 10^6, ``benchmarks/run_scale.py --memory``), scaled to n by the
#: n + n^2 numbers of a body's configuration; and the memory of a process that does nothing.
MEMORY_PER_BODY_3D = 5.6 * 1024
MEMORY_BASE = 0.7 * 2**30
#: Largest buffer of frames that one compiled call of the run driver returns (``chunk_steps``
#: shortens its chunks for large systems to stay within it).
FRAME_BUFFER_BYTES = 256 * 2**20


def frame_bytes(config: Config) -> int:
    """Bytes of one recorded frame of the state (x, p: N n; phi, pi: N n^2; float64)."""
    n = config.n
    return config.bodies_count * 2 * (n + n * n) * 8


def estimated_memory(config: Config) -> float:
    """Bytes a run of ``config`` needs, estimated before anything is allocated: the measured
    per-body cost (:data:`MEMORY_PER_BODY_3D`, scaled to n), the frame buffer of a compiled
    call, and without a neighbour list the pair arrays of the all-pairs sum (N(N - 1)/2 pairs,
    each with its geometry: about 8 (2 n^2 + n + 8) bytes)."""
    n, bodies = config.n, config.bodies_count
    per_body = MEMORY_PER_BODY_3D * (n + n * n) / 12
    one = frame_bytes(config)
    frames = one + min(FRAME_BUFFER_BYTES, 1000 * one)  # chunk_steps keeps a chunk's frames in
    pairs = bodies * (bodies - 1) / 2
    if config.run.neighbor_list == "on" or (
            config.run.neighbor_list == "auto" and bodies >= AUTO_NEIGHBOR_LIST_BODIES):
        pairs = 0.0  # with a list (if the config cannot have one, check_run says so)
    return MEMORY_BASE + bodies * per_body + frames + pairs * 8 * (2 * n * n + n + 8)


def available_memory() -> float | None:
    """Bytes this machine can still give a process (Linux: MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _gib(value: float) -> str:
    """A size in bytes as GiB (TiB from 1 TiB on), for messages."""
    return f"{value / 2**30:.3g} GiB" if value < 2**40 else f"{value / 2**40:.3g} TiB"


def refuse_beyond_memory(need: float, what: str, fix: str) -> None:
    """The one policy for work that cannot fit in memory, checked before anything is
    allocated: a ConfigError ``{what} needs about {need} of memory, more than the {have}
    available: {fix}`` when ``need`` bytes exceed :func:`available_memory` (nothing where that
    is unknown)."""
    have = available_memory()
    if have is not None and need > have:
        raise ConfigError(f"{what} needs about {_gib(need)} of memory, more than the "
                          f"{_gib(have)} available: {fix}")


def check_memory(config: Config) -> None:
    """Refuse, before allocating anything, a config whose run cannot fit in memory
    (:func:`estimated_memory` against :func:`available_memory`), with both figures."""
    bodies = config.bodies_count
    hint = ("reduce system.bodies" if config.run.neighbor_list != "off" or bodies < 500
            else 'reduce system.bodies or use run.neighbor_list = "on"')
    refuse_beyond_memory(estimated_memory(config), f"system.bodies = {bodies}", hint)


def _check_list_memory(config: Config, space, reach: float) -> None:
    """Refuse, before allocating it, a neighbour list that cannot fit in memory: bodies far
    too dense for their box (:func:`affinebody.neighbors.uniform_list_bytes`)."""
    from affinebody import neighbors as nb

    if not space.periodic:
        return
    bodies, radius = config.bodies_count, reach + config.run.neighbor_skin
    per_body = 2 * nb.uniform_pair_count(space, bodies, radius) / bodies
    refuse_beyond_memory(nb.uniform_list_bytes(space, bodies, radius),
                         f"system.bodies = {bodies} in system.box = {list(config.system.box)} "
                         f"(about {per_body:.3g} bodies within the pair cut-off of each, a "
                         f"neighbour list of their pairs)",
                         "enlarge system.box or lower system.bodies")


def check_barostat(config: Config) -> None:
    if config.run.pressure and config.system.box is None:
        raise ConfigError("run.pressure = true needs a periodic box: set system.box")
    b, n = config.barostat, config.n
    if b is None:
        return
    if config.system.box is None:
        raise ConfigError("barostat needs a periodic box: set system.box")
    for name in ("tau", "compressibility"):
        _positive(getattr(b, name), f"barostat.{name}")
    if b.interval * config.run.dt > b.tau:
        raise ConfigError(f"barostat.interval * run.dt must not exceed barostat.tau (one move "
                          f"of the box spans interval * dt; got {b.interval} * {config.run.dt} "
                          f"> {b.tau}): lower barostat.interval or raise barostat.tau")
    thermostat = config.thermostat
    if b.temperature is None and thermostat is None:
        raise ConfigError("barostat.temperature is required without a [thermostat] (give kT, "
                          "or add a [thermostat] whose temperature it then takes)")
    if b.temperature is not None:
        _positive(b.temperature, "barostat.temperature")
        if thermostat is not None and b.temperature != thermostat.temperature:
            raise ConfigError(f"barostat.temperature must equal thermostat.temperature (one "
                              f"ensemble; got {b.temperature} and {thermostat.temperature}): "
                              f"leave barostat.temperature out")
    if isinstance(b.pressure, list):
        largest = float(np.abs(_array(b.pressure, "barostat.pressure", (n, n))).max())
    elif not math.isfinite(b.pressure):
        raise ConfigError(f"barostat.pressure must be finite (got {b.pressure})")
    else:
        largest = abs(b.pressure)
    volume = math.prod(config.system.box)
    if not largest * volume < 1e300:  # P0 V enters the conserved energy of every step
        raise ConfigError(f"barostat.pressure = {_show(b.pressure)} times the box volume "
                          f"{volume:.3g} is beyond float64: give the pressure in units in "
                          f"which P0 V is a moderate energy")


def records_pressure(config: Config) -> bool:
    """Whether a run of ``config`` records the pressure and the volume (h5md
    PERIODIC_OBSERVABLES): with ``run.pressure = true`` or a ``[barostat]``."""
    return config.system.box is not None and (config.run.pressure
                                              or config.barostat is not None)


def check_config(config: Config) -> Config:
    """Second pass: the meaning of every field (see the module docstring)."""
    check_system(config)
    config.bodies_count  # noqa: B018 - raises if the counts disagree
    check_memory(config)
    body_inertia(config)
    check_kinetic(config)
    check_initial(config)
    check_run(config)
    check_thermostat(config)
    check_potentials(config)
    check_barostat(config)
    return config


# --------------------------------------------------------------------------- building
@dataclass(frozen=True)
class Built:
    """A checked config turned into the objects of the dynamics."""

    system: Any  # affinebody.system.HamiltonianSystem
    state: Any  # affinebody.state.State, the initial state
    inertia: Inertia
    neighbor_list: bool = False  # sum the pair forces over a neighbour list (uses_neighbor_list)
    #: (spec, list) of ``neighbors.allocate`` for the initial state when ``neighbor_list``
    neighbors: Any = None
    #: seconds spent in each stage of :func:`build` (what ``affinebody run --verbose`` prints)
    timings: dict = dataclass_field(default_factory=dict)
    #: the ``thermostats.Langevin`` / ``Bussi`` of ``[thermostat]``, None for NVE
    thermostat: Any = None


def _kinetic_parameter(name: str, config: Config, inertia: Inertia):
    """The value of ``kinetic.<name>`` for the model (each model declares the names it takes):
    J defaults to the body's inertia (8), B to 0; matrices and tensors are checked."""
    k, n = config.kinetic, config.n
    if name == "J":
        return inertia.J if k.J is None else _spd(k.J, "kinetic.J", n)
    if name == "H":
        return _spd(k.H, "kinetic.H", n)
    if name in ("L", "R"):
        return _array(getattr(k, name), f"kinetic.{name}", (n, n, n, n))
    value = getattr(k, name)
    return 0.0 if value is None and name == "B" else float(value)


def build_kinetic(config: Config, inertia: Inertia):
    """The :class:`~affinebody.kinetic.KineticEnergy` of ``[kinetic]`` (positive definiteness
    checked here and again by the model's own ``check``)."""
    from affinebody import kinetic as models

    k, n = config.kinetic, config.n
    translational = models.TRANSLATIONAL_MODELS[k.translational](mass=inertia.mass)
    model = models.MODELS[k.internal]
    internal = model(**{name: _kinetic_parameter(name, config, inertia)
                        for name in model.parameters})
    energy = models.KineticEnergy(translational, internal)
    try:
        energy.check(n)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    return energy


def _rng(seed: int, stream: int) -> np.random.Generator:
    """An independent random stream per generated quantity (order of use does not matter)."""
    return np.random.default_rng([seed, stream])


def _lattice_shape(count: int, n: int) -> list[int]:
    side = 1
    while side**n < count:
        side += 1
    return [side] * n


def initial_configuration(config: Config) -> tuple[np.ndarray, np.ndarray]:
    """(x [N, n], phi [N, n, n]) from ``[initial]``: explicit arrays, else the generator;
    ConfigError naming the generator's keys when they put x or phi beyond float64."""
    with np.errstate(over="ignore", invalid="ignore"):
        x, phi = _generated_configuration(config)
    i = config.initial
    if i.x is None and not np.all(np.isfinite(x)):
        raise ConfigError(f"initial: the generated positions are not finite in float64 (spacing "
                          f"{i.spacing}, jitter {i.jitter}, extent {i.extent}): lower them")
    if i.phi is None and not np.all(np.isfinite(phi)):
        raise ConfigError(f"initial.phi_noise = {i.phi_noise} is too large: phi is the "
                          f"exponential of the noise, beyond float64 (values of 0.01 to 0.3 are "
                          f"usual)")
    return x, phi


def _generated_configuration(config: Config) -> tuple[np.ndarray, np.ndarray]:
    i, n, count = config.initial, config.n, config.bodies_count
    if _initial_generator(i) == "file":
        return file_frame(config)[:2]
    seed = config.run.seed if i.seed is None else i.seed
    origin = np.zeros(n) if i.origin is None else np.asarray(i.origin, dtype=np.float64)
    if i.x is not None:
        x = np.asarray(i.x, dtype=np.float64)
    elif i.generator == "random":
        box = config.system.box
        if i.extent is not None:
            extent = i.extent
        elif box is not None:  # the whole periodic box
            extent = np.asarray(box, dtype=np.float64)
        else:
            extent = i.spacing * count ** (1 / n)
        u = _rng(seed, 0).uniform(0.0, 1.0, (count, n))
        x = origin + u[_cell_order(u)] * extent
    else:  # lattice
        shape = i.shape or _lattice_shape(count, n)
        sites = np.stack(np.unravel_index(np.arange(count), shape), axis=-1).astype(np.float64)
        x = origin + i.spacing * sites
        if i.jitter:
            x = x + i.jitter * i.spacing * _rng(seed, 1).uniform(-1.0, 1.0, x.shape)
    if i.phi is not None:
        phi = np.asarray(i.phi, dtype=np.float64)
    else:
        phi = np.broadcast_to(np.eye(n), (count, n, n)).copy()
        if i.phi_noise:
            group = config.system.group
            algebra = "GL" if group in ("L", "GL", "GL+") else group
            noise = i.phi_noise * _rng(seed, 2).standard_normal((count, n, n))
            phi = np.asarray(_exponential_of_algebra(noise, algebra))
    return x, phi


def _cell_order(u: np.ndarray) -> np.ndarray:
    """The order of points ``u`` [N, n] in the unit cube that visits cells of about one point
    each row by row (the last axis fastest), as the lattice generator numbers its sites. In
    the order drawn, the bodies a body interacts with lie anywhere in memory, and every step
    gathers them from there: at 97 336 bodies in 3D such a numbering runs at 0.65 of the
    ordered one in the loop (README, "Benchmarks": ``run_scale.py --renumbered``; 0.45 before
    the neighbour list visited the bodies in space)."""
    count, n = u.shape
    side = max(1, math.ceil(count ** (1 / n)))
    cells = np.minimum((u * side).astype(np.int64), side - 1)
    return np.lexsort(cells.T[::-1])


@jax.jit
def _hamiltonian(system, state, neighbors):
    """H at ``state`` as one compiled program (the initial energy of :func:`build`): op by op
    its array operations are compiled and dispatched one at a time."""
    return system.hamiltonian(state, neighbors)


@functools.partial(jax.jit, static_argnums=1)
def _exponential_of_algebra(a, algebra: str):
    """expm of a projected on ``algebra``, compiled as one program (op by op, its array
    operations are compiled and dispatched one at a time: 2.4 s against 1.0 s in a new process
    at 4096 bodies)."""
    from affinebody.groups import expm, project_algebra

    return expm(project_algebra(a, algebra))


def initial_state(config: Config, kinetic):
    """The initial :class:`~affinebody.state.State`; velocities go through the Legendre maps."""
    from affinebody.state import State

    i, n, count = config.initial, config.n, config.bodies_count
    seed = config.run.seed if i.seed is None else i.seed
    if _initial_generator(i) == "file" and i.file_momenta:
        return State(*file_frame(config))
    x, phi = initial_configuration(config)
    if i.momentum is not None:
        p = np.asarray(i.momentum, dtype=np.float64)
    elif i.velocity is not None:
        p = np.asarray(kinetic.translational.legendre(phi, np.asarray(i.velocity, np.float64)))
    else:
        with np.errstate(over="ignore", invalid="ignore"):  # too large: build says which key
            p = i.momentum_scale * _rng(seed, 3).standard_normal((count, n))
            if i.zero_momentum and count > 1:
                p = p - p.mean(axis=0)
    if i.phi_momentum is not None:
        pi = np.asarray(i.phi_momentum, dtype=np.float64)
    elif i.phi_velocity is not None:
        xi = np.asarray(i.phi_velocity, dtype=np.float64)
        pi = np.asarray(kinetic.internal.legendre(phi, xi))
    else:
        with np.errstate(over="ignore"):
            pi = i.phi_momentum_scale * _rng(seed, 4).standard_normal((count, n, n))
    return State(x, phi, p, pi)


def build(config: Config) -> Built:
    """System, initial state and inertia of a checked config (needs JAX's float64 mode).

    Every stage is O(N) when the pair forces use a neighbour list: the list is allocated here
    (kept in ``Built.neighbors``) and the initial energy, whose finiteness is checked, is
    summed over it instead of over all N(N-1)/2 pairs."""
    import time

    from affinebody._checks import require_x64
    from affinebody.potentials import total_potential
    from affinebody.system import HamiltonianSystem

    require_x64()
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = now - clock
        clock = now

    inertia = body_inertia(config)
    kinetic = build_kinetic(config, inertia)
    terms = [build_potential_entry(e, k, config) for k, e in enumerate(config.potential)]
    potential = total_potential(terms) if terms else None
    group = config.system.group
    if group not in CONFIG_GROUPS:
        raise ConfigError(f"system.group {group!r} is not supported by the integrators "
                          f"(choose one of {', '.join(CONFIG_GROUPS)})")
    try:
        system = HamiltonianSystem(kinetic, potential, group,
                                   rotationless=config.constraints.rotationless)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    lap("models")
    state = initial_state(config, kinetic)
    lap("initial state")
    try:
        state = system.check(state)
    except ValueError as err:
        raise ConfigError(f"initial: {err}") from None
    lap("state checks")
    if _kinetic.compile_host_drift(kinetic, state.phi):
        lap("drift kernel")
    neighbor_list = uses_neighbor_list(config, terms)
    lists = None
    if neighbor_list:
        from affinebody import neighbors as nb

        space, cutoff, variable = system.neighbor_range()
        _check_list_memory(config, space, float(nb.spatial_reach(cutoff, variable, state.phi)))
        try:
            lists = nb.allocate(space, state.x, state.phi, cutoff, variable,
                                config.run.neighbor_skin,  # a [barostat]: cells that follow
                                cell=None if config.barostat is None else space.matrix)
        except ValueError as err:
            raise ConfigError(f"initial: {err}") from None
        lap("neighbour list")
    energy = float(_hamiltonian(system, state, None if lists is None else lists[1]))
    lap("initial energy")
    if not math.isfinite(energy):
        kinetic = float(np.sum(system.kinetic_energy(state)))
        if not math.isfinite(kinetic):
            raise ConfigError(f"initial: the kinetic energy of the initial state is {kinetic}: "
                              f"lower initial.momentum_scale or initial.phi_momentum_scale (or "
                              f"the momenta or velocities given)")
        raise ConfigError(f"initial: the energy of the initial state is {energy} (bodies on top "
                          f"of each other in a singular potential, or det phi = 0?)")
    return Built(system, state, inertia, neighbor_list, lists, timings,
                 build_thermostat(config))


__all__ = [
    "INTERNAL_MODELS", "TRANSLATIONAL_MODELS", "INTEGRATOR_NAMES", "SPLITTING_INTEGRATORS",
    "AUTO_NEIGHBOR_LIST_BODIES", "CONFIG_GROUPS", "MAX_DIMENSION", "INT64_MAX",
    "MOST_PATH_POINTS", "UnitSystem", "ConfigError",
    "Vector", "Matrix", "Matrices", "Tensor4", "SystemSection", "Constituents", "BodySection",
    "KineticSection", "PotentialSection", "InitialSection", "RunSection", "ThermostatSection",
    "ScanRange", "SweepSection", "ConstraintsSection", "PhononsSection", "BarostatSection",
    "Config", "one_line_error", "load_toml", "parse_config", "load_config", "Inertia",
    "body_inertia", "check_kinetic", "check_thermostat", "build_thermostat", "check_run",
    "uses_neighbor_list", "check_system", "check_initial", "build_potential_entry",
    "check_potentials", "FileHeader", "file_frame", "MEMORY_PER_BODY_3D", "MEMORY_BASE",
    "FRAME_BUFFER_BYTES", "frame_bytes",
    "estimated_memory", "available_memory", "refuse_beyond_memory", "check_memory",
    "check_barostat", "records_pressure", "check_config", "Built", "build_kinetic",
    "initial_configuration", "initial_state", "build"
]
