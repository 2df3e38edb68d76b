"""Trajectory files in the H5MD 1.1 layout (https://www.nongnu.org/h5md/h5md.html).

The layout is a public contract::

    /h5md                        attrs version=[1, 1]; groups author, creator, modules/affine_bodies
    /particles/bodies/position/{step, time, value}      value [T, N, n]      (x)
    /particles/bodies/momentum/{step, time, value}      value [T, N, n]      (p)
    /particles/bodies/phi/{step, time, value}           value [T, N, n, n]   (phi[i, a] = phi^i_a)
    /particles/bodies/phi_momentum/{step, time, value}  value [T, N, n, n]   (pi[a, i] = pi^a_i)
    /particles/bodies/mass  [N];  /particles/bodies/radius [N]
    /particles/bodies/box                 attrs dimension=n, boundary=["periodic" | "none"] * n
    /particles/bodies/box/edges/{step, time, value}     value [T, n]  (periodic runs only; step
                                          and time are hard links to position's step and time)
    /observables/{total_energy, kinetic_energy, potential_energy}/{step, time, value}   [T]
    /observables/linear_momentum/...      value [T, n]      sum_K p_K              (103)
    /observables/affine_momentum/...      value [T, n, n]   sum_K (x_K p_K^T + phi_K pi_K)  (109)
    /observables/angular_momentum/...     value [T, n, n]   J - J^T of the affine momentum J
    /observables/pressure/...             value [T, n, n]   pressure tensor (run.pressure or a
                                          barostat, periodic box; docs/pressure.md)
    /observables/volume/...               value [T]         det of the cell (the same runs)
    /observables/{translational_temperature, internal_temperature}/...  value [T]
                                          2 T_tr / (N n) and 2 T_int / (N d), d the internal
                                          momentum degrees of freedom per body (thermostats.py)
    /observables/effective_energy/...     value [T]   thermostatted runs: H minus the heat
    /observables/rejected_moves/...       value [T]   barostat.metropolis runs: the barostat
                                          moves rejected since the previous frame
    /parameters/{config, seed, version, dt, steps, config_hash}
    /parameters/frames_committed  [1] int64: frames whose every element is on disk
    /h5md/modules/units                   attrs version=[1, 0], system="reduced" | "gromacs"

The box is stored once per frame (an H5MD time-dependent element), the form MDAnalysis reads
(a barostat changes it from frame to frame);
files of earlier versions stored ``box/edges`` once, as a dataset, and are still read here.
The string attributes of H5MD 1.1 proper (author and creator names, creator version, box
boundary) are fixed-length ASCII strings; the ``unit`` attributes of the units module are
variable-length (:func:`_set_unit` says why). The file is written with
HDF5's latest format (superblock version 3, needed for SWMR), so readers need HDF5 >= 1.10.

Units (:data:`UNIT_SYSTEMS`): in the default ``reduced`` system every number is a ratio to the
run's reference length, mass, time and energy (sigma, m, tau = sigma sqrt(m / epsilon),
epsilon), that is dimensionless, so no ``unit`` attribute is written and the units module
names the system. With ``system.units = "gromacs"`` the same numbers are read as nm, u (g/mol),
ps and kJ/mol, a consistent set (1 kJ/mol = 1 u nm^2 ps^-2), and every dimensionful dataset
carries its H5MD ``unit`` string ("nm", "ps", "u nm ps-1", ...), as MDAnalysis expects.

``phi_momentum`` keeps the paper's placement pi[a, i] = pi^a_i, so that Sigma = phi @ pi and
Sigma_hat = pi @ phi (45).

Crash safety: the writer creates every dataset first and then switches the file to HDF5's
single-writer/multiple-reader (SWMR) mode, in which the library orders its metadata writes so
that the file on disk stays readable when the writing process is killed. After such a kill HDF5
refuses an ordinary open ("file is already open for write"); :func:`open_h5` falls back to a SWMR
read, which is why every reader here goes through it. Frames are flushed as they are written.
Each append writes and flushes its frames, then raises ``/parameters/frames_committed`` and
flushes again; readers cut every element to that count, so frames a kill caught half-written
(an element extended but its data not yet on disk) are never read. The file is laid out under
a temporary name and renamed into place only once it is a complete SWMR file (before SWMR mode
is on, HDF5 gives no such guarantee), so a kill at any instant leaves either no output, the
previous one, or a readable trajectory.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from affinebody import __version__
from affinebody.state import State
from affinebody.units import UNIT_SYSTEMS

H5MD_VERSION = (1, 1)
MODULE_NAME = "affine_bodies"
MODULE_VERSION = (1, 0)
PARTICLE_GROUP = "bodies"
#: /parameters dataset holding the number of frames completely written (see the docstring).
COMMITTED = "frames_committed"
UNITS_MODULE_VERSION = (1, 0)

#: H5MD element -> quantity kind of its values (None: dimensionless).
ELEMENT_UNITS = {"position": "length", "momentum": "momentum", "phi": None,
                 "phi_momentum": "action", "total_energy": "energy",
                 "kinetic_energy": "energy", "potential_energy": "energy",
                 "linear_momentum": "momentum", "affine_momentum": "action",
                 "angular_momentum": "action", "pressure": "pressure", "volume": "volume",
                 "translational_temperature": "energy", "internal_temperature": "energy",
                 "effective_energy": "energy"}

#: State fields -> H5MD element names under /particles/bodies.
STATE_ELEMENTS = {"x": "position", "p": "momentum", "phi": "phi", "pi": "phi_momentum"}
#: Observable names -> number of trailing axes of size n (0: scalar, 1: vector, 2: matrix).
OBSERVABLES = {
    "total_energy": 0,
    "kinetic_energy": 0,
    "potential_energy": 0,
    "linear_momentum": 1,
    "affine_momentum": 2,
    "angular_momentum": 2,
    "translational_temperature": 0,
    "internal_temperature": 0,
}
#: Observables of periodic runs only (same convention as :data:`OBSERVABLES`).
PERIODIC_OBSERVABLES = {"pressure": 2, "volume": 0}
#: Observables written by thermostatted runs only: H minus the heat the thermostat put in.
THERMOSTAT_OBSERVABLES = {"effective_energy": 0}
#: Observables of runs whose barostat tests its moves (``barostat.metropolis``): the moves
#: rejected since the previous frame.
BAROSTAT_TEST_OBSERVABLES = {"rejected_moves": 0}
#: File observables recorded under another name by the run driver
#: (``simulate.NAMED_OBSERVABLES``); the others have the same name in both.
DRIVER_NAMES = {"total_energy": "energy"}


class TrajectoryFileError(ValueError):
    """An output file that cannot be read as an affinebody H5MD trajectory."""


class NoRoomError(OSError):
    """The disk (or the process's file-size limit) has no room for the next block of frames;
    nothing of the block was written, so the file stays complete up to the frames before it."""


#: Room kept free beyond a block's own bytes, for HDF5's metadata (chunk indices, heaps).
METADATA_MARGIN = 1 << 16


def room_for(path: Path) -> float:
    """Bytes that can still be written to ``path``: the free space of its file system and, when
    the process has a file-size limit (``ulimit -f``), what that limit leaves."""
    import resource
    import shutil

    room = float(shutil.disk_usage(path.parent).free)
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY:
        room = min(room, limit - (path.stat().st_size if path.exists() else 0))
    return room


def open_h5(path: str | Path) -> h5py.File:
    """Open ``path`` read-only; falls back to a SWMR read for files whose writer was killed."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"{path}: no such file")
    try:
        return h5py.File(path, "r")
    except OSError as first:
        # only a file left open by a (killed) SWMR writer is retried: a SWMR read of a
        # truncated file can retry its metadata reads for a very long time
        if "already open for write" not in str(first):
            raise TrajectoryFileError(
                f"{path}: not a readable HDF5 file (truncated or corrupt: {_short(first)})"
            ) from None
        try:
            return h5py.File(path, "r", swmr=True)
        except OSError as second:
            raise TrajectoryFileError(
                f"{path}: not a readable HDF5 file (truncated or corrupt: {_short(second)})"
            ) from None


def _short(err: Exception) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return text if len(text) < 160 else text[:157] + "..."


@dataclass(frozen=True)
class Trajectory:
    """A trajectory read back from an H5MD file, as NumPy arrays (frames along axis 0)."""

    step: np.ndarray
    time: np.ndarray
    x: np.ndarray
    phi: np.ndarray
    p: np.ndarray
    pi: np.ndarray
    mass: np.ndarray
    radius: np.ndarray
    box: np.ndarray | None
    observables: Mapping[str, np.ndarray] = field(default_factory=dict)
    config_text: str = ""
    seed: int = 0
    version: str = ""
    dt: float = float("nan")
    #: box edges of every frame [T, n] (None without a periodic box); ``box`` is frame 0's
    boxes: np.ndarray | None = None
    #: the unit system (a key of :data:`UNIT_SYSTEMS`; files without one are "reduced")
    units: str = "reduced"
    #: the file it was read from (for messages)
    source: str = ""

    @property
    def state(self) -> State:
        """All frames as one batched :class:`State` ([T, N, ...] arrays)."""
        return State(self.x, self.phi, self.p, self.pi)

    @property
    def frames(self) -> int:
        return int(self.step.shape[0])

    @property
    def n(self) -> int:
        return int(self.phi.shape[-1])

    @property
    def bodies(self) -> int:
        return int(self.phi.shape[-3])

    def frame(self, k: int) -> State:
        """Frame ``k`` (negative counts from the end) as a :class:`State`."""
        return State(self.x[k], self.phi[k], self.p[k], self.pi[k])

    def configuration(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """(x [N, n], phi [N, n, n]) of frame ``k``, what plots and exports draw; a
        :class:`TrajectoryFileError` naming the frame and the body where either is not
        finite (a run writes finite frames only: such a file was changed or written by other
        software)."""
        x, phi = np.asarray(self.x[k]), np.asarray(self.phi[k])
        finite = np.all(np.isfinite(x), axis=-1) & np.all(np.isfinite(phi), axis=(-2, -1))
        if not np.all(finite):
            k = k % self.frames
            raise TrajectoryFileError(
                f"{self.source}: frame {k} (step {int(self.step[k])}) holds a non-finite x or "
                f"phi of body {int(np.argmin(finite))}: affinebody runs write finite frames "
                f"only, so the file was changed or written by other software")
        return x, phi


def read_trajectory(path: str | Path) -> Trajectory:
    """Read an affinebody H5MD file into a :class:`Trajectory` (every frame in memory).

    Raises :class:`TrajectoryFileError` (a ``ValueError``) with a one-line message for missing,
    truncated or foreign files. Frames are cut to the length every element agrees on, so a file
    whose writer was killed between two element writes still reads consistently. For large
    systems use :func:`open_trajectory`, which reads frames on demand.
    """
    with open_trajectory(path) as lazy:
        try:
            return dataclasses.replace(lazy, **{name: np.asarray(getattr(lazy, name)[:])
                                                for name in STATE_ELEMENTS})
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise TrajectoryFileError(
                f"{path}: cannot read the trajectory (truncated or corrupt: {_short(err)})"
            ) from None


class _Frames:
    """The first ``count`` frames of an H5MD ``value`` dataset, read on indexing."""

    def __init__(self, dataset: h5py.Dataset, count: int):
        self.dataset, self.count = dataset, count
        self.shape = (count, *dataset.shape[1:])
        self.ndim = len(self.shape)

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, key):
        if isinstance(key, tuple):
            first, rest = key[0], key[1:]
        else:
            first, rest = key, ()
        if isinstance(first, slice):
            first = slice(*first.indices(self.count))
        elif int(first) < 0:
            first = int(first) + self.count
        return np.asarray(self.dataset[(first, *rest)])

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.dataset[: self.count], dtype=dtype)


@contextmanager
def open_trajectory(path: str | Path) -> Iterator[Trajectory]:
    """A :class:`Trajectory` whose x, phi, p and pi are read frame by frame from the open file
    (``trajectory.phi[k]`` reads frame k only), so memory stays O(N) for any number of frames;
    steps, times, observables and parameters (O(T)) are read at once. Same errors as
    :func:`read_trajectory`."""
    f = open_h5(path)
    try:
        try:
            if "h5md" not in f or "particles" not in f or PARTICLE_GROUP not in f["particles"]:
                raise TrajectoryFileError(
                    f"{path}: not an affinebody H5MD file (no /h5md or /particles/{PARTICLE_GROUP})"
                )
            bodies = f["particles"][PARTICLE_GROUP]
            elements = {}
            for name, element in STATE_ELEMENTS.items():
                if element not in bodies:
                    raise TrajectoryFileError(f"{path}: missing /particles/bodies/{element}")
                elements[name] = bodies[element]
            obs_group = f["observables"] if "observables" in f else {}
            lengths = [len(g["step"]) for g in elements.values()]
            lengths += [len(g["value"]) for g in elements.values()]
            lengths += [len(obs_group[k]["value"]) for k in obs_group]
            edges = bodies["box"].get("edges") if "box" in bodies else None
            per_frame = isinstance(edges, h5py.Group)
            if per_frame:
                lengths.append(len(edges["value"]))
            params = f["parameters"] if "parameters" in f else {}
            if COMMITTED in params:  # files of earlier versions have no commit count
                lengths.append(int(params[COMMITTED][0]))
            count = min(lengths) if lengths else 0
            arrays = {k: _Frames(g["value"], count) for k, g in elements.items()}
            step = np.asarray(elements["x"]["step"][:count])
            time = np.asarray(elements["x"]["time"][:count])
            observables = {k: np.asarray(obs_group[k]["value"][:count]) for k in obs_group}
            box = boxes = None
            if per_frame:  # this version: a time-dependent element
                boxes = np.asarray(edges["value"][:count])
                box = boxes[0] if count else None
            elif edges is not None:  # files of earlier versions: the edges stored once
                box = np.asarray(edges[()])
                boxes = np.broadcast_to(box, (count, *box.shape))
            units = f["h5md"]["modules"].get("units") if "modules" in f["h5md"] else None
            system = _attribute_string(units, "system") if units is not None else "reduced"
            trajectory = Trajectory(
                step=step,
                time=time,
                mass=np.asarray(bodies["mass"][()]),
                radius=np.asarray(bodies["radius"][()]) if "radius" in bodies
                else np.full(elements["phi"]["value"].shape[-3], 0.5),
                box=box,
                boxes=boxes,
                units=system or "reduced",
                source=str(path),
                observables=observables,
                config_text=_read_string(params, "config"),
                seed=int(params["seed"][()]) if "seed" in params else 0,
                version=_read_string(params, "version"),
                dt=float(params["dt"][()]) if "dt" in params else float("nan"),
                **arrays,
            )
        except TrajectoryFileError:
            raise
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise TrajectoryFileError(
                f"{path}: cannot read the trajectory (truncated or corrupt: {_short(err)})"
            ) from None
        yield trajectory
    finally:
        f.close()


def _read_string(group, name: str) -> str:
    if name not in group:
        return ""
    value = group[name][()]
    return value.decode() if isinstance(value, bytes) else str(value)


def _attribute_string(obj, name: str) -> str:
    value = obj.attrs.get(name, "")
    return value.decode() if isinstance(value, bytes) else str(value)


def fixed_string(text: str | list[str]) -> np.ndarray:
    """``text`` (or a list of strings) as a fixed-length ASCII HDF5 string, the type H5MD 1.1
    requires for its string attributes (h5py writes ``str`` as variable-length)."""
    data = np.asarray(text, dtype=np.bytes_)
    return data if data.ndim else data[()]


def _set_unit(dataset: h5py.Dataset, kind: str | None, units: Mapping[str, str]) -> None:
    """The H5MD ``unit`` attribute of ``dataset``, a variable-length ASCII string: the units
    module asks for a fixed-length one, but MDAnalysis (2.8) recognises a unit only when h5py
    reads it as ``str``, which it does for variable-length strings only (fixed-length ones come
    back as bytes); a working reader is worth more than that letter of the module."""
    if kind is not None and kind in units:
        dataset.attrs.create("unit", units[kind], dtype=h5py.string_dtype("ascii"))


def _time_series(parent: h5py.Group, name: str, shape: tuple[int, ...], chunk: int,
                 units: Mapping[str, str]) -> h5py.Group:
    """Create an H5MD time-dependent element ``name`` with empty, growable step/time/value."""
    group = parent.create_group(name)
    group.create_dataset("step", shape=(0,), maxshape=(None,), dtype="i8", chunks=(chunk,))
    time = group.create_dataset("time", shape=(0,), maxshape=(None,), dtype="f8",
                                chunks=(chunk,))
    value = group.create_dataset(
        "value", shape=(0, *shape), maxshape=(None, *shape), dtype="f8", chunks=(chunk, *shape)
    )
    _set_unit(time, "time", units)
    _set_unit(value, ELEMENT_UNITS.get(name), units)
    return group


class H5MDWriter:
    """Append-only writer of an affinebody trajectory in the H5MD layout of this module.

    Use as a context manager. ``append`` writes a block of frames and flushes them to disk.
    ``pressure``: the file also holds :data:`PERIODIC_OBSERVABLES` (a periodic ``box``);
    ``thermostat``: :data:`THERMOSTAT_OBSERVABLES`; ``barostat_test``:
    :data:`BAROSTAT_TEST_OBSERVABLES`.
    ``parameters`` are stored under /parameters (strings and numbers only). ``units`` names
    the unit system (a key of :data:`UNIT_SYSTEMS`).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        mass: np.ndarray,
        radius: np.ndarray,
        n: int,
        box: np.ndarray | None = None,
        parameters: Mapping[str, object] | None = None,
        author: str = "affinebody user",
        units: str = "reduced",
        pressure: bool = False,
        thermostat: bool = False,
        barostat_test: bool = False,
    ):
        self.path = Path(path)
        if units not in UNIT_SYSTEMS:
            raise ValueError(f"units must be one of {sorted(UNIT_SYSTEMS)} (got {units!r})")
        unit = dict(UNIT_SYSTEMS[units])
        if unit:  # pressure and volume in n dimensions
            unit.update(pressure=f"{unit['energy']} {unit['length']}-{n}",
                        volume=f"{unit['length']}+{n}")
        self.box = None if box is None else np.asarray(box, dtype=np.float64)
        if pressure and box is None:
            raise ValueError("pressure and volume are observables of a periodic box: give box")
        #: the observables this file holds (with ``pressure``: PERIODIC_OBSERVABLES too, with
        #: ``thermostat``: THERMOSTAT_OBSERVABLES, with ``barostat_test``:
        #: BAROSTAT_TEST_OBSERVABLES)
        self.observables = dict(OBSERVABLES, **(PERIODIC_OBSERVABLES if pressure else {}),
                                **(THERMOSTAT_OBSERVABLES if thermostat else {}),
                                **(BAROSTAT_TEST_OBSERVABLES if barostat_test else {}))
        mass = np.asarray(mass, dtype=np.float64)
        bodies = mass.shape[0]
        self.n, self.bodies = int(n), int(bodies)
        chunk = max(1, min(256, 2**16 // max(1, bodies * n * n)))
        # Built under a temporary name and renamed into place once it is a complete, empty
        # SWMR trajectory: a crash while it is being laid out leaves no half-made file (and an
        # existing file at ``path``, which --overwrite replaces, intact until then).
        building = self.path.with_name(f".{self.path.name}.{os.getpid()}.creating")
        try:
            self.file = h5py.File(building, "w", libver="latest")
            f = self.file
            h5md = f.create_group("h5md")
            h5md.attrs["version"] = np.asarray(H5MD_VERSION, dtype=np.int32)
            h5md.create_group("author").attrs["name"] = fixed_string(author.encode(
                "ascii", "replace").decode())
            creator = h5md.create_group("creator")
            creator.attrs["name"] = fixed_string("affinebody")
            creator.attrs["version"] = fixed_string(__version__)
            modules = h5md.create_group("modules")
            module = modules.create_group(MODULE_NAME)
            module.attrs["version"] = np.asarray(MODULE_VERSION, dtype=np.int32)
            units_module = modules.create_group("units")
            units_module.attrs["version"] = np.asarray(UNITS_MODULE_VERSION, dtype=np.int32)
            units_module.attrs["system"] = fixed_string(units)

            particles = f.create_group("particles").create_group(PARTICLE_GROUP)
            for name, element in STATE_ELEMENTS.items():
                shape = (bodies, n) if name in ("x", "p") else (bodies, n, n)
                _time_series(particles, element, shape, chunk, unit)
            _set_unit(particles.create_dataset("mass", data=mass), "mass", unit)
            _set_unit(particles.create_dataset("radius",
                                               data=np.asarray(radius, dtype=np.float64)),
                      "length", unit)
            box_group = particles.create_group("box")
            box_group.attrs["dimension"] = np.int32(n)
            periodic = box is not None
            boundary = "periodic" if periodic else "none"
            box_group.attrs["boundary"] = fixed_string([boundary] * n)
            if periodic:  # per frame, as MDAnalysis reads it; step and time are position's
                edges = box_group.create_group("edges")
                edges["step"] = particles["position"]["step"]
                edges["time"] = particles["position"]["time"]
                _set_unit(edges.create_dataset("value", shape=(0, n), maxshape=(None, n),
                                               dtype="f8", chunks=(max(chunk, 64), n)),
                          "length", unit)

            observables = f.create_group("observables")
            for name, rank in self.observables.items():
                _time_series(observables, name, (n,) * rank, max(chunk, 64), unit)

            params = f.create_group("parameters")
            params.create_dataset("version", data=__version__, dtype=h5py.string_dtype())
            for key, value in (parameters or {}).items():
                if isinstance(value, str):
                    params.create_dataset(key, data=value, dtype=h5py.string_dtype())
                else:
                    params.create_dataset(key, data=np.asarray(value))
            if "dt" in params:
                _set_unit(params["dt"], "time", unit)
            params.create_dataset(COMMITTED, data=np.zeros(1, dtype=np.int64), maxshape=(1,),
                                  chunks=(1,))
            f.flush()
            self.file.swmr_mode = True
            os.replace(building, self.path)  # the open file keeps writing to the renamed inode
        except BaseException:
            if getattr(self, "file", None) is not None:
                self.file.close()
            building.unlink(missing_ok=True)
            raise
        self.frames = 0

    def append(
        self,
        step: np.ndarray,
        time: np.ndarray,
        state: State,
        observables: Mapping[str, np.ndarray],
        boxes: np.ndarray | None = None,
    ) -> None:
        """Append frames: ``step`` [F], ``time`` [F], ``state`` with [F, N, ...] arrays;
        ``boxes`` [F, n]: the box edges of each frame (default: the writer's fixed box)."""
        step = np.atleast_1d(np.asarray(step, dtype=np.int64))
        time = np.atleast_1d(np.asarray(time, dtype=np.float64))
        count = step.shape[0]
        if count == 0:
            return
        start, stop = self.frames, self.frames + count
        self._require_room(count)
        groups = [
            (self.file["particles"][PARTICLE_GROUP][element], getattr(state, name))
            for name, element in STATE_ELEMENTS.items()
        ]
        groups += [(self.file["observables"][name], observables[name])
                   for name in self.observables]
        for group, value in groups:
            value = np.asarray(value, dtype=np.float64)
            if value.shape[0] != count:
                raise ValueError(f"{group.name}: got {value.shape[0]} frames, expected {count}")
            for key, data in (("value", value), ("step", step), ("time", time)):
                dataset = group[key]
                dataset.resize(stop, axis=0)
                dataset[start:stop] = data
        if self.box is not None:  # step and time are position's (hard links): written above
            edges = self.file["particles"][PARTICLE_GROUP]["box"]["edges"]["value"]
            edges.resize(stop, axis=0)
            edges[start:stop] = np.broadcast_to(self.box if boxes is None else boxes,
                                                (count, self.n))
        self.flush()  # the frames are on disk ...
        self.file["parameters"][COMMITTED][0] = stop
        self.flush()  # ... before the count that makes readers see them
        self.frames = stop

    def _require_room(self, count: int) -> None:
        """:class:`NoRoomError` unless ``count`` frames fit: their bytes, one new chunk of
        every dataset (HDF5 allocates whole chunks), and :data:`METADATA_MARGIN`. Checked
        before anything of the block is written: a write that fails half-way leaves an HDF5
        file whose superblock points past its end, which no reader opens."""
        if not hasattr(self, "_bytes"):
            datasets = []
            self.file.visititems(lambda _, obj: datasets.append(obj)
                                 if isinstance(obj, h5py.Dataset) and obj.chunks else None)
            self._bytes = (
                sum(int(np.prod(d.shape[1:])) * d.dtype.itemsize for d in datasets),
                sum(int(np.prod(d.chunks)) * d.dtype.itemsize for d in datasets))
        per_frame, chunks = self._bytes
        need = count * per_frame + chunks + METADATA_MARGIN
        room = room_for(self.path)
        if room < need:
            raise NoRoomError(
                f"no room to write to {self.path}: {room / 2**20:.3g} MiB left on its disk or "
                f"under the file-size limit, the next {count} frames need about "
                f"{need / 2**20:.3g} MiB; the {self.frames} frames written and the last "
                f"checkpoint (if any) are kept: free space, then continue with --resume")

    def flush(self) -> None:
        self.file.flush()

    def close(self) -> None:
        if self.file.id.valid:
            self.file.close()

    def __enter__(self) -> H5MDWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def copy_frames_from_file(path: str | Path, writer: H5MDWriter, through_step: int,
                          block_bytes: int = 1 << 26) -> tuple[int, np.ndarray]:
    """Append the frames of the file ``path`` with step <= ``through_step`` to ``writer``,
    a block of frames at a time (memory: about ``block_bytes``, not the whole trajectory).

    Used by ``--resume``. Returns the number of frames copied and their total energies (their
    effective energies in a thermostatted run's file).
    """
    with open_trajectory(path) as source:
        missing = [k for k in writer.observables if k not in source.observables]
        if missing:
            raise TrajectoryFileError(f"missing observables {missing} in the file to resume")
        keep = source.step <= through_step
        count = int(np.count_nonzero(keep))
        if count and not np.all(keep[:count]):
            raise TrajectoryFileError(f"{path}: steps are not increasing")
        per_frame = 8 * sum(int(np.prod(getattr(source, name).shape[1:]))
                            for name in STATE_ELEMENTS)
        block = max(1, block_bytes // max(per_frame, 1))
        try:
            for lo in range(0, count, block):
                hi = min(lo + block, count)
                writer.append(source.step[lo:hi], source.time[lo:hi],
                              State(*(getattr(source, name)[lo:hi]
                                      for name in ("x", "phi", "p", "pi"))),
                              {k: source.observables[k][lo:hi] for k in writer.observables},
                              None if source.boxes is None else source.boxes[lo:hi])
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise TrajectoryFileError(
                f"{path}: cannot read the trajectory (truncated or corrupt: {_short(err)})"
            ) from None
        conserved = ("effective_energy" if "effective_energy" in writer.observables
                     else "total_energy")
        return count, np.asarray(source.observables[conserved][:count])


__all__ = [
    "H5MD_VERSION", "MODULE_NAME", "MODULE_VERSION", "PARTICLE_GROUP", "COMMITTED",
    "UNITS_MODULE_VERSION", "ELEMENT_UNITS", "STATE_ELEMENTS", "OBSERVABLES",
    "PERIODIC_OBSERVABLES", "THERMOSTAT_OBSERVABLES", "BAROSTAT_TEST_OBSERVABLES",
    "DRIVER_NAMES", "TrajectoryFileError",
    "NoRoomError", "METADATA_MARGIN", "room_for", "open_h5", "Trajectory", "read_trajectory",
    "open_trajectory", "fixed_string", "H5MDWriter", "copy_frames_from_file"
]
