"""Ensembles and parameter sweeps on Dask: ``affinebody sweep CONFIG.toml``.

A sweep runs one config many times: over the points of a parameter scan, and at each point over
``samples`` random initial data. The ``[sweep]`` table of the config says what varies::

    [sweep]
    samples = 2000
    seed = 0
    initial_velocity = "normal"   # internal affine velocity Omega_hat; "none" keeps [initial]
    velocity_scale = 1.0
    x_velocity = "none"           # "normal": dx/dt ~ N(0, 1) per body and component
    x_velocity_scale = 1.0
    bound = 1000.0
    batch = 64                    # samples per task (vmapped)
    equilibration = 0             # thermostatted sweeps: steps before the averages
    scan = { "kinetic.A" = [0.5, 1.0, 2.0], "run.dt" = { start = 0.01, stop = 0.1, num = 4 } }

Initial data. ``initial_velocity = "normal"`` draws the co-moving affine velocity
Omega_hat = phi^-1 dphi/dt (34) of every body with i.i.d. standard normal entries, projects it
orthogonally onto the Lie algebra of ``system.group`` (sl(n): minus Tr/n times Id; so(n): the
skew part; gl(n): unchanged; :func:`affinebody.groups.project_algebra`) and multiplies it by
``velocity_scale``; the momentum is then pi = legendre(phi, xi) with xi = phi Omega_hat, through
the internal kinetic model's Legendre map (50), and the constrained-momentum representative on a
subgroup. ``x_velocity = "normal"`` does the same for dx/dt (p = legendre(phi, v), (6), (64)).
Sample k of a sweep with seed s draws from the key ``fold_in(key(s), k)`` only (sub-keys 0 for
Omega_hat, 1 for dx/dt), so a sample's initial data, and its whole result, do not depend on the
number of workers, on the batching into tasks, or on the order in which tasks finish; every
parameter point sees the same initial velocities (common random numbers).

Scan. ``scan`` maps a dotted config field (``"kinetic.A"``, ``"potential.0.expr"``,
``"initial.phi.0.1.1"``, ``"run.dt"``) to a list of values or a range
``{start, stop, num, log}`` (both ends included; geometric with ``log = true``); the points are
the Cartesian product, in the order the fields are given. Every point's config is checked
as a config file is (pydantic and :func:`~affinebody.config.check_config`) before anything
runs. From Python (:func:`run_sweep`'s default) a point whose config is refused (e.g. af-is
with I <= |A|) is recorded with the reason, and the others still run; ``affinebody sweep``
(``refuse_bad_points=True``) refuses the sweep instead, in one line naming the scanned key,
its value, the point and the problem (exit 1), and for small sweeps (points x bodies up to
:data:`BUILD_CHECK_LIMIT`) also builds every point's system first, as ``affinebody validate``
does.

Classification (over the horizon run.steps * run.dt, checked after every step): a sample is
``bounded`` when max_t max_K max(sigma_max(phi_K), sigma_max(phi_K^-1)) < ``bound``, and
``unbounded`` otherwise (its ``exit_time`` is the first time the bound was reached). A sample is
followed until the horizon, or until that spread reaches bound^2 (certainly unbounded: stopping
keeps the numbers finite), or until it fails: ``failed`` with the reason "non-finite state",
"left the group" (det phi crossed 0 on GL+/GL) or "non-finite initial energy"; a point whose
build fails and a task that raises are recorded as failed samples too. Never fatal: the
sweep goes on, and ``affinebody sweep`` exits 0 with failed samples among its results, but 3
(``EXIT_STOPPED``) when every sample failed (nothing was measured; the results are written). Also
reported per sample: the final relative energy error |E - E0| / |E0|, the largest relative
volume det Gamma[phi_K, phi_L] (79) and the smallest and largest det phi_K (over bodies and the
followed time), and the drawn Omega_hat and dx/dt.

Thermostatted sweeps (NVT, NPT). With a ``[thermostat]`` every sample is a thermostatted run
(NVT), with a ``[thermostat]`` and a ``[barostat]`` an NPT run, made of the steps
``affinebody run`` makes: the integrator composed with the thermostat
(``integrators.Thermostatted``) through :func:`~affinebody.simulate.watched_step`, or the NPT
driver's loop (:func:`affinebody.barostat.advance`, with the thermostat's O step of
:func:`affinebody.runner.constant_pressure`). A scan may vary ``thermostat.temperature`` and
``barostat.pressure`` (e.g. ``scan = { "thermostat.temperature" = {start = 0.1, stop = 0.5,
num = 5} }`` for a thermal-expansion curve, ``scan = { "barostat.pressure" = [0, 1, 2] }`` for an
equation of state); kT and P0 are traced, so a whole scan runs one compiled function. The
noise of sample k (the thermostat's seed in NVT, the NPT driver's seed in NPT) is the 32 random
bits of ``fold_in(fold_in(key(seed), k), 2)``: like its initial data, a sample's result does
not depend on workers or batching, and every point sees the same noise (common random numbers).
``[sweep] equilibration`` (steps, default 0) is run before the averages start; then every
``run.every`` steps (``run.steps`` must be a multiple of it) the run driver's observables are
measured and summed in the loop (O(N) memory, no frames): total energy E = H, potential energy,
translational and internal temperature (``simulate.NAMED_OBSERVABLES``), the scalar pressure
Tr P / n (:mod:`affinebody.pressure`, kinetic part included) and the volume (periodic boxes;
else NaN). Per sample (``samples.csv``, :data:`THERMAL_SCALARS`): the number of measurements,
the time averages, the variances (1/m) of E and V, the heat capacity C = var(E)/kT^2 (NVT,
C_V) or var(E + P0 V)/kT^2 (NPT, C_P, P0 = Tr P0 / n; k_B = 1), and in NPT the isothermal
compressibility kappa_T = var(V)/(kT <V>); with ``barostat.metropolis`` the fraction of the
barostat's moves after the equilibration that its Metropolis test rejected
(``rejected_fraction``, NaN otherwise); in NPT ``move_length``, how long the barostat's moves
were for the box at the sample's last state (``barostat.move_length`` of
``barostat.move_modulus``: beta_T K interval dt / tau), and a sweep whose plain moves were
longer than ``barostat.LONG_MOVE`` at some point warns (its var(V), compressibility and C_P are
then too large). The classification columns (bounded, spreads,
energy errors) do not apply: a sample is ``sampled``, or ``failed`` with its reason (the
driver's stops, a non-finite state or box under the barostat, a box narrower than twice the
pair cut-off). ``summary.json`` holds, per point, the mean over its sampled samples of each
column (``NAME``) and its standard error across the samples (``NAME_error``: valid however
correlated the measurements inside a sample are), with the point's ``temperature`` and
``pressure_target``; and ``ensemble`` ("NVT" or "NPT"), ``equilibration`` and ``every``.
Without a ``[thermostat]`` everything above the previous paragraph holds unchanged.

Execution. Samples are split into tasks of ``batch`` samples (the last one padded to the same
size, so every task of a point has one shape and compiles once per worker); a task integrates
its samples with ``jax.vmap`` over one ``lax.while_loop`` per sample (the driver of
:mod:`affinebody.simulate`, less the frames). Without a scheduler address a local Dask cluster
is started (``LocalCluster``: processes started with ``spawn``, one thread each, single-threaded
XLA/BLAS through :data:`WORKER_ENV`), and closed at the end; with ``--scheduler tcp://host:port``
the running cluster is used as it is (its workers need ``affinebody`` installed). Every task
switches JAX to float64 in its worker before it computes (and checks it did). ``workers = 0``
runs the tasks in this process without Dask (a debugging aid).

Output (``-o OUT_DIR``): ``tasks/point-PPPP-batch-BBBBB.json``, one file per task, written as
the task completes (its samples, their results, and the worker's float64 and thread settings);
then ``samples.csv`` (one row per sample) and ``summary.json``: ``fraction_bounded`` (bounded /
classified samples, failed ones excluded) with its binomial standard error and 95% Wilson
interval, counts, energy errors, volumes, failure reasons, per parameter point and pooled;
and its provenance: ``scheduler`` (the Dask scheduler's address, or "in-process"),
``workers`` (the cluster's workers at the end of the sweep, 1 in-process) and
``worker_processes`` (the distinct processes that ran tasks: more than ``workers`` when a
worker was restarted).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import itertools
import json
import logging
import math
import os
import time
import uuid
import warnings
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from affinebody import _host, _xla
from affinebody._json import json_safe, json_text
from affinebody.config import Config, ConfigError, ScanRange, check_config
from affinebody.simulate import Stop, kept_list_or_refit, relative_error

#: Environment of local Dask workers: one thread for XLA and BLAS, XLA's faster compilation
#: (``_xla.FAST_COMPILATION``, where jaxlib knows it), float64 JAX.
WORKER_ENV = {
    "XLA_FLAGS": _xla.with_flags("--xla_cpu_multi_thread_eigen=false",
                                 _xla.FAST_COMPILATION if _xla.flags_known() else ()),
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "JAX_ENABLE_X64": "True",
}

#: Outcomes of a sample beyond the driver's stops (``simulate.Stop``: a failed step keeps its
#: code, 1..3), in one table with them: code -> (status, failure reason).
_BOUNDED, _UNBOUNDED, _BAD_INITIAL, _ERROR = 10, 11, 12, 13
_SAMPLED, _BOX, _NARROW = 14, 15, 16  # thermostatted sweeps
STATUS_CODES = {
    _BOUNDED: ("bounded", ""),
    _UNBOUNDED: ("unbounded", ""),
    **{int(stop): ("failed", stop.reason) for stop in Stop if stop != Stop.NONE},
    _BAD_INITIAL: ("failed", "non-finite initial energy"),
    _ERROR: ("failed", "error"),
    _SAMPLED: ("sampled", ""),
    _BOX: ("failed", "non-finite state or box under the barostat"),
    _NARROW: ("failed", "the box shrank below twice the pair cut-off"),
}
#: Per-sample scalar results (besides status and failure), in samples.csv column order.
SCALARS = ("exit_time", "followed_time", "max_spread", "energy_error", "initial_energy",
           "final_energy", "max_relative_volume", "min_det", "max_det")
#: Per-sample results of a thermostatted sweep (NVT, NPT), in samples.csv column order.
THERMAL_SCALARS = ("followed_time", "measurements", "mean_total_energy", "var_total_energy",
                   "mean_potential_energy", "mean_translational_temperature",
                   "mean_internal_temperature", "mean_pressure", "mean_volume", "var_volume",
                   "heat_capacity", "compressibility", "rejected_fraction", "move_length")


# --------------------------------------------------------------------------- specification
@dataclass(frozen=True)
class SweepSpec:
    """The ``[sweep]`` table with the command-line overrides applied."""

    samples: int = 1
    seed: int = 0
    initial_velocity: str = "none"
    velocity_scale: float = 1.0
    x_velocity: str = "none"
    x_velocity_scale: float = 1.0
    bound: float = 1000.0
    batch: int = 64
    equilibration: int = 0

    @classmethod
    def from_config(cls, config: Config, samples: int | None = None,
                    seed: int | None = None) -> SweepSpec:
        s = config.sweep
        spec = cls() if s is None else cls(
            s.samples, s.seed, s.initial_velocity, s.velocity_scale, s.x_velocity,
            s.x_velocity_scale, s.bound, s.batch, s.equilibration)
        check_thermal(config, spec)
        if samples is not None:
            if samples < 1:
                raise ConfigError(f"--samples must be >= 1 (got {samples})")
            spec = dataclasses.replace(spec, samples=int(samples))
        if seed is not None:
            if not 0 <= seed < 2**32:
                raise ConfigError(f"--seed must be in 0 .. 2**32 - 1 (got {seed})")
            spec = dataclasses.replace(spec, seed=int(seed))
        return spec

    @property
    def batch_size(self) -> int:
        """Samples per task: ``batch``, or all samples when there are fewer."""
        return min(self.batch, self.samples)


def check_thermal(config: Config, spec: SweepSpec) -> None:
    """One-line refusals of a sweep's ensemble: a ``[barostat]`` only with a ``[thermostat]``
    (NPT), ``equilibration`` only with a thermostat and shorter than the run, whose length is
    a multiple of run.every (the measurement interval)."""
    r = config.run
    if config.thermostat is None:
        if config.barostat is not None:
            raise ConfigError("sweep: a [barostat] needs a [thermostat] (its samples are NPT "
                              "runs): add a [thermostat] at the barostat's temperature")
        if spec.equilibration:
            raise ConfigError(f"sweep.equilibration applies to thermostatted sweeps (got "
                              f"{spec.equilibration} without a [thermostat]): remove it")
        return
    if r.steps % r.every:
        raise ConfigError(f"run.steps must be a multiple of run.every in a thermostatted sweep "
                          f"(observables are measured every run.every steps; got steps="
                          f"{r.steps}, every={r.every})")
    if spec.equilibration + r.every > r.steps:
        raise ConfigError(f"sweep.equilibration must leave a measurement: at most run.steps - "
                          f"run.every = {r.steps - r.every} (got {spec.equilibration})")


@dataclass(frozen=True)
class ScanPoint:
    """One parameter point: its index, the scanned values, and its config (or why not)."""

    index: int
    parameters: tuple[tuple[str, Any], ...]
    config_json: str | None
    error: str | None = None

    @property
    def parameter_dict(self) -> dict[str, Any]:
        return dict(self.parameters)

    @property
    def horizon(self) -> float:
        """The time this point's samples are followed, ``run.steps * run.dt`` of its own
        config (a scan may change either); NaN for a refused point, which runs nothing."""
        if self.config_json is None:
            return math.nan
        run = json.loads(self.config_json)["run"]
        return float(run["dt"]) * int(run["steps"])


def scan_key(path: str) -> str:
    """The config key of the scan entry ``path``, as TOML writes it: ``sweep.scan."kinetic.A"``
    (the dotted field is one quoted key of the table)."""
    return f"sweep.scan.{json.dumps(path, ensure_ascii=False)}"


def _written(value) -> str:
    """A scanned value as the config writes it: ``5.0``, ``0.15`` (not the
    0.15000000000000002 of a range's arithmetic), ``"af-is"``."""
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and math.isfinite(value):
        return repr(float(f"{value:.12g}"))
    return str(value)


def scan_values(path: str, values) -> list:
    """The values of one scan entry: a list as given, or a range expanded (both ends in);
    numbers must be finite."""
    given = [values.start, values.stop] if isinstance(values, ScanRange) else values
    for value in given:
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{scan_key(path)}: values must be finite (got {value})")
    if isinstance(values, ScanRange):
        if values.log:
            if not (values.start > 0 and values.stop > 0):
                raise ConfigError(f"{scan_key(path)}: a log range needs start > 0 and stop > 0 "
                                  f"(got start={values.start}, stop={values.stop})")
            grid = np.geomspace(values.start, values.stop, values.num)
        else:
            grid = np.linspace(values.start, values.stop, values.num)
        return [float(v) for v in grid]
    if not values:
        raise ConfigError(f"{scan_key(path)}: give at least one value")
    return list(values)


def _config_data(config: Config) -> dict:
    return config.model_dump(exclude={"source_text": True, "sweep": True})


def _set_field(data: dict, path: str, value):
    """Set the dotted ``path`` of the config data to ``value`` and return what was set (an
    integral float as an int in an integer field); ConfigError if no such field."""
    parts = path.split(".")
    if parts[0] == "sweep":
        raise ConfigError(f"sweep.scan: cannot scan the [sweep] table itself ({path!r})")
    node: Any = data
    where = "config"
    for depth, part in enumerate(parts):
        last = depth == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise ConfigError(f"{scan_key(path)}: {where} has {len(node)} entries "
                                  f"(index {part!r} is not one of them)")
            key: Any = int(part)
        elif isinstance(node, dict):
            # potential entries take any parameter of their kind; other tables have fixed keys
            if part not in node and not (where.startswith("potential.") and last):
                raise ConfigError(f"{scan_key(path)}: {part!r} is not a field of {where} (scan "
                                  f"a config field, e.g. 'kinetic.A' or 'potential.0.expr')")
            key = part
        else:
            raise ConfigError(f"{scan_key(path)}: {where} is a value, not a table or array")
        if last:
            old = node[key] if (isinstance(node, list) or key in node) else None
            if isinstance(old, int) and not isinstance(old, bool) and isinstance(value, float) \
                    and abs(value - round(value)) <= 1e-9 * max(1.0, abs(value)):
                value = int(round(value))
            node[key] = value
            return value
        if node[key] is None:
            raise ConfigError(f"{scan_key(path)}: {where}.{part} is not set in the config "
                              f"(give it a value to scan inside it)")
        node = node[key]
        where = part if where == "config" else f"{where}.{part}"


#: ``affinebody sweep`` builds every scan point's system before running (what ``affinebody
#: validate`` does after the checks: the models, the initial state on its group, its finite
#: energy) while points x bodies is at most this; above it only the config of each point is
#: checked (pydantic and :func:`~affinebody.config.check_config`, no JAX, O(points)), and a
#: point whose build fails fails its samples at run time.
BUILD_CHECK_LIMIT = 1000


def _checked(data: dict) -> tuple[Config | None, str | None]:
    """``data`` validated as a config the way a config file is (pydantic, then
    :func:`~affinebody.config.check_config`): (config, None), or (None, why) in one line."""
    from pydantic import ValidationError

    from affinebody.config import one_line_error

    try:
        return check_config(Config.model_validate(data)), None
    except ValidationError as err:
        return None, one_line_error(err)
    except ConfigError as err:
        return None, str(err).removeprefix("config error: ")


def _refusal(base: dict, parameters: tuple, index: int, why: str, refused) -> ConfigError:
    """The one-line refusal of scan point ``index`` (``parameters``: its (path, value)s):
    the scanned key(s) whose value is refused, the value(s), the point and ``why``. With
    several scanned keys, those refused on their own (each set alone in ``base``, by
    ``refused(data)``); all of them where none is (the values are refused together)."""
    written, alone = [], []
    for path, value in parameters:
        data = copy.deepcopy(base)
        written.append((path, _set_field(data, path, value)))  # 3, not 3.0, in an int field
        if len(parameters) > 1 and refused(data):
            alone.append(written[-1])
    culprits = alone or written
    where = ", ".join(f"{scan_key(path) if k == 0 else json.dumps(path, ensure_ascii=False)} "
                      f"= {_written(value)}"
                      for k, (path, value) in enumerate(culprits))
    return ConfigError(f"{where} (point {index}): {why}")


def _build_error(config: Config) -> str | None:
    """Why :func:`affinebody.config.build` refuses ``config`` (one line), or None."""
    from affinebody.config import build

    try:
        build(config)
    except ValueError as err:
        return str(err).removeprefix("config error: ")
    return None


def scan_points(config: Config, *, refuse: bool = False) -> list[ScanPoint]:
    """The parameter points of ``config``'s scan (a single point without one), each checked
    as a config file is (pydantic, then :func:`~affinebody.config.check_config`).

    A malformed scan (unknown field, empty list) raises ConfigError. A point whose config is
    refused is returned with ``error`` set, to be recorded as failed samples; with ``refuse``
    (``affinebody sweep``) the first such point raises ConfigError instead, one line naming
    the scanned key, its value, the point and the problem, and while points x bodies is at
    most :data:`BUILD_CHECK_LIMIT` every point's system is built too (as ``affinebody
    validate`` does; needs JAX's float64 mode).
    """
    scan = {} if config.sweep is None else dict(config.sweep.scan)
    base = _config_data(config)
    paths = list(scan)
    grids = [scan_values(p, scan[p]) for p in paths]
    for path in paths:  # structural check once, on a copy
        _set_field(copy.deepcopy(base), path, grids[paths.index(path)][0])
    build_each = refuse and math.prod(map(len, grids)) * config.bodies_count <= BUILD_CHECK_LIMIT
    if build_each:
        from affinebody._checks import require_x64

        require_x64()

    def refused(data: dict) -> bool:
        checked, why = _checked(data)
        return why is not None or (build_each and _build_error(checked) is not None)

    points = []
    for index, combination in enumerate(itertools.product(*grids)):
        data = copy.deepcopy(base)
        for path, value in zip(paths, combination, strict=True):
            _set_field(data, path, value)
        parameters = tuple(zip(paths, combination, strict=True))
        checked, why = _checked(data)
        if why is None and build_each:
            why = _build_error(checked)
        if why is not None:
            if refuse:
                raise _refusal(base, parameters, index, why, refused)
            points.append(ScanPoint(index, parameters, None, f"config error: {why}"))
            continue
        text = json.dumps(_config_data(checked), sort_keys=True)
        points.append(ScanPoint(index, parameters, text))
    if all(point.error is not None for point in points):  # nothing would run
        first = points[0]
        where = ", ".join(f"{path} = {value!r}" for path, value in first.parameters)
        raise ConfigError(f"sweep.scan: every point of the scan is refused, e.g. {where}: "
                          f"{first.error.removeprefix('config error: ')}")
    return points


@dataclass(frozen=True)
class Task:
    """One unit of work: samples ``start`` to ``start + count - 1`` of one point, padded to
    ``size`` with copies of the last sample (discarded) so that all tasks of a point share one
    shape."""

    point: int
    batch: int
    config_json: str
    start: int
    count: int
    size: int
    spec: SweepSpec

    @property
    def indices(self) -> np.ndarray:
        idx = np.arange(self.start, self.start + self.size, dtype=np.int64)
        return np.minimum(idx, self.start + self.count - 1)

    @property
    def name(self) -> str:
        return f"point-{self.point:04d}-batch-{self.batch:05d}"


def results_bytes(config: Config, points: int, spec: SweepSpec, columns: int,
                  keep_draws: bool = True) -> float:
    """Bytes :func:`run_sweep` holds for its results, estimated before any is allocated: per
    sample its scalars, its status and (``keep_draws``) its drawn velocities (Omega_hat,
    dx/dt of every body), per task its description (a few hundred bytes)."""
    n, bodies = config.n, config.bodies_count
    per_sample = 8 * (columns + (bodies * (n * n + n) if keep_draws else 0) + 2)
    return float(points) * spec.samples * (per_sample + 500 / spec.batch_size)


def _check_results_memory(config: Config, points: int, spec: SweepSpec, columns: int,
                          keep_draws: bool) -> None:
    from affinebody.config import refuse_beyond_memory

    refuse_beyond_memory(results_bytes(config, points, spec, columns, keep_draws),
                         f"sweep.samples = {spec.samples} (or --samples) at {points} scan "
                         f"point(s)", "ask for fewer samples or points")


def make_tasks(points: Sequence[ScanPoint], spec: SweepSpec) -> list[Task]:
    """Tasks for every runnable point (points with a config error get none)."""
    size = spec.batch_size
    tasks = []
    for point in points:
        if point.config_json is None:
            continue
        for batch, start in enumerate(range(0, spec.samples, size)):
            count = min(size, spec.samples - start)
            tasks.append(Task(point.index, batch, point.config_json, start, count, size, spec))
    return tasks


# --------------------------------------------------------------------------- worker side
def prepare_worker() -> dict[str, Any]:
    """Make this process compute in float64 with single-threaded XLA/BLAS (where not yet set),
    its C heap keeping the memory it frees (:func:`affinebody._host.keep_freed_memory`).

    Run at the start of every task: a remote cluster's workers are used unchanged otherwise.
    The thread settings only take effect in a process whose XLA backend has not started yet
    (always true for the workers of the local cluster, which get :data:`WORKER_ENV`).
    """
    for key, value in WORKER_ENV.items():
        os.environ.setdefault(key, value)
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    _host.keep_freed_memory()
    dtype = str(jnp.zeros(()).dtype)
    if dtype != "float64":
        raise RuntimeError(f"worker {os.getpid()} could not switch JAX to float64 (got {dtype})")
    return {"pid": os.getpid(), "x64": bool(jax.config.jax_enable_x64), "dtype": dtype,
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "omp_threads": os.environ.get("OMP_NUM_THREADS", "")}


@dataclass(frozen=True)
class _Prepared:
    system: Any
    state: Any
    method: Any
    dt: float
    steps: int
    neighbors: Any = None  # (spec, list) allocated for the initial configuration, or None
    # thermostatted sweeps: the thermostat (Langevin / Bussi) and the barostat
    # (StochasticCellRescaling, NPT) as templates whose temperature and pressure are traced
    # (every point of a temperature or pressure scan runs the same compiled function)
    thermostat: Any = None
    temperature: float = math.nan
    barostat: Any = None
    pressure: Any = None  # P0 [n, n] of an NPT sweep
    space: Any = None  # the periodic box, else None
    every: int = 1  # run.every: the measurement interval


@functools.lru_cache(maxsize=32)
def _prepare(config_json: str) -> _Prepared:
    from pydantic import ValidationError

    from affinebody.config import build, one_line_error
    from affinebody.integrators import get_integrator

    try:
        config = Config.model_validate(json.loads(config_json))
    except ValidationError as err:
        raise ConfigError(one_line_error(err)) from None
    built = build(check_config(config))
    extra = {}
    if built.thermostat is not None:
        from affinebody.space import as_space

        box = config.system.box
        thermostat = built.thermostat
        extra = {"thermostat": dataclasses.replace(thermostat, temperature=1.0, seed=0),
                 "temperature": float(thermostat.temperature), "every": int(config.run.every),
                 "space": None if box is None else as_space(tuple(box))}
        if config.barostat is not None:
            from affinebody.runner import constant_pressure

            baro = constant_pressure(config, thermostat)[0]
            zero = tuple((0.0,) * config.n for _ in range(config.n))
            extra["pressure"] = baro.target
            extra["barostat"] = dataclasses.replace(baro, pressure=zero, temperature=1.0)
    return _Prepared(built.system, built.state, get_integrator(config.run.integrator),
                     float(config.run.dt), int(config.run.steps),
                     built.neighbors if built.neighbor_list else None, **extra)


def draw_initial_state(system, state, key, *, internal: str, internal_scale, translational: str,
                       translational_scale):
    """Initial state of one sample: ``state`` with velocities drawn from ``key`` (see module).

    Returns (State, Omega_hat [N, n, n], dx/dt [N, n]). Without draws the velocities are those
    of ``state`` (through the inverse Legendre maps).
    """
    import jax

    from affinebody import _linalg as linalg
    from affinebody.groups import project_algebra
    from affinebody.state import State

    kinetic = system.kinetic
    phi = state.phi
    if internal == "normal":
        z = jax.random.normal(jax.random.fold_in(key, 0), phi.shape, dtype=phi.dtype)
        omega_hat = internal_scale * project_algebra(z, system.group)
        pi = kinetic.internal.legendre(phi, phi @ omega_hat)
    else:
        pi = state.pi
        omega_hat = linalg.solve(phi, kinetic.internal.inverse_legendre(phi, pi))
    if translational == "normal":
        v = translational_scale * jax.random.normal(jax.random.fold_in(key, 1), state.x.shape,
                                                    dtype=state.x.dtype)
        p = kinetic.translational.legendre(phi, v)
    else:
        p = state.p
        v = kinetic.translational.inverse_legendre(phi, p)
    return system.constrain(State(state.x, phi, p, pi)), omega_hat, v


def _measures(phi):
    """(max_K max(sigma_max(phi_K), 1/sigma_min(phi_K)), min det, max det, max |det ratio|)."""
    import jax.numpy as jnp

    from affinebody import _linalg as linalg

    sigma = jnp.linalg.svd(phi, compute_uv=False)
    spread = jnp.max(jnp.maximum(sigma[..., 0], 1.0 / sigma[..., -1]))
    det = linalg.det(phi)
    volume = jnp.abs(det)
    return spread, jnp.min(det), jnp.max(det), jnp.max(volume) / jnp.min(volume)


def follow(system, state, dt, bound, *, steps: int, method, watch_det: bool, spec=None,
           neighbors=None):
    """Integrate one sample and classify it (module docstring); a ``lax.while_loop`` of the
    run driver's :func:`~affinebody.simulate.watched_step`, so a sample fails exactly where
    ``affinebody run`` would stop. With a neighbour list (``spec``, ``neighbors`` valid for
    ``state``) the pair terms are summed over it, as in ``run``: O(N) per step.

    Returns a dict of scalars: code (a key of :data:`STATUS_CODES`; ``Stop.OVERFLOW`` when the
    list overflowed: the caller reallocates and repeats the sample), steps_done, exit_step
    (-1: never reached the bound), max_spread, min_det, max_det, max_relative_volume,
    initial_energy, final_energy.
    """
    import jax
    import jax.numpy as jnp
    from jax import lax

    from affinebody import _linalg as linalg
    from affinebody.simulate import initial_forces, watched_step

    energy0 = system.hamiltonian(state, neighbors)
    step = watched_step(system, method, dt, spec, sign0=jnp.sign(linalg.det(state.phi)),
                        watch_det=watch_det)
    runaway = bound * bound
    spread, dmin, dmax, rel = _measures(state.phi)
    finite0 = jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(state)]))
    code0 = jnp.where(jnp.isfinite(energy0) & finite0, _BOUNDED, _BAD_INITIAL)
    exit0 = jnp.where(spread >= bound, 0, -1)
    forces = initial_forces(system, method, state, neighbors)
    lost = (jnp.asarray(0, jnp.int32), jnp.asarray(0, jnp.int32), jnp.zeros((), state.x.dtype))
    init = (state, neighbors, forces, code0, jnp.asarray(0), exit0, spread, dmin, dmax, rel,
            lost)

    def running(carry):
        code, k, _, spread = carry[3:7]
        return (k < steps) & (code == _BOUNDED) & (spread < runaway)

    def advance(carry):
        state, nbrs, forces, code, k, exit_step, spread, dmin, dmax, rel, lost = carry
        w = step(state, nbrs, forces)
        good = w.stop == Stop.NONE
        if w.tracked is not None:  # what a reallocation must hold (as in simulate.run)
            lost = (w.tracked.overflow, w.tracked.most_pairs, w.tracked.largest_reach)
        s, lo, hi, r = _measures(jnp.where(good, w.state.phi, state.phi))
        code = jnp.where(good, code, w.stop)
        keep = lambda new, old: jnp.where(good, new, old)  # noqa: E731
        # the list is not kept back with the state (as in simulate.run: that cost two copies
        # of it per step); after the loop a failed sample's kept state gets one of its own
        state, nbrs, forces = (jax.tree.map(keep, w.state, state), w.neighbors,
                               jax.tree.map(keep, w.forces, forces))
        exit_step = jnp.where(good & (exit_step < 0) & (s >= bound), k + 1, exit_step)
        spread = jnp.where(good, jnp.maximum(spread, s), spread)
        dmin = jnp.where(good, jnp.minimum(dmin, lo), dmin)
        dmax = jnp.where(good, jnp.maximum(dmax, hi), dmax)
        rel = jnp.where(good, jnp.maximum(rel, r), rel)
        return (state, nbrs, forces, code, jnp.where(good, k + 1, k), exit_step, spread, dmin,
                dmax, rel, lost)

    state, nbrs, _, code, k, exit_step, spread, dmin, dmax, rel, lost = lax.while_loop(
        running, advance, init)
    if spec is not None:
        # the loop ended on a step it discarded, with that step's list: the kept state gets
        # its own (one that does not fit: the sample is repeated with room for both lists)
        nbrs, refit, lost = kept_list_or_refit(spec, code != code0, state, nbrs, lost)
        code = jnp.where(refit, int(Stop.OVERFLOW), code)
    code = jnp.where((code == _BOUNDED) & (exit_step >= 0), _UNBOUNDED, code)
    return {"code": code, "steps_done": k, "exit_step": exit_step, "max_spread": spread,
            "min_det": dmin, "max_det": dmax, "max_relative_volume": rel,
            "initial_energy": energy0, "final_energy": system.hamiltonian(state, nbrs),
            "overflow": lost[0], "most_pairs": lost[1], "largest_reach": lost[2]}


def _batch(system, state, seed, indices, dt, bound, internal_scale, translational_scale,
           neighbors, *, steps, method, watch_det, internal, translational, spec):
    """Every sample of a task. Without a list the samples are vmapped (one batched loop);
    with one they run one after the other (``lax.map``): a list's rebuild is a ``lax.cond``,
    which vmap would turn into a rebuild at every step, and a system large enough to need a
    list has work enough per step."""
    import jax

    def one(index):
        key = jax.random.fold_in(jax.random.key(seed), index)
        start, omega_hat, v = draw_initial_state(
            system, state, key, internal=internal, internal_scale=internal_scale,
            translational=translational, translational_scale=translational_scale)
        out = follow(system, start, dt, bound, steps=steps, method=method, watch_det=watch_det,
                     spec=spec, neighbors=neighbors)
        return {**out, "omega_hat": omega_hat, "velocity": v}

    if spec is None:
        return jax.vmap(one)(indices)
    return jax.lax.map(one, indices)


@functools.cache
def _compiled_batch():
    import jax

    return jax.jit(_batch, static_argnames=("steps", "method", "watch_det", "internal",
                                             "translational", "spec"))


def run_task(task: Task, in_worker: bool = True) -> dict[str, Any]:
    """Compute one task: per-sample arrays of its ``count`` samples + worker info.

    In a worker (default) it first calls :func:`prepare_worker`; in the calling process
    (``in_worker=False``, the ``workers = 0`` mode) it changes no global setting and requires
    float64 to be on already. A config that does not build (e.g. a non-finite initial energy)
    gives failed samples with the reason; other exceptions propagate (and are recorded by the
    caller as failed samples).
    """
    if in_worker:
        info = prepare_worker()
    else:
        from affinebody._checks import require_x64

        require_x64()
        info = {"pid": os.getpid(), "x64": True, "dtype": "float64", "in_process": True}
    clock = time.perf_counter()
    try:
        prepared = _prepare(task.config_json)
    except ValueError as err:
        return _failure_result(task, str(err).splitlines()[0], info)
    if prepared.thermostat is not None:
        return _run_thermal_task(task, prepared, info, clock)
    import jax.numpy as jnp

    from affinebody.system import OPEN_GROUPS

    spec = task.spec
    system = prepared.system
    lists = prepared.neighbors or (None, None)

    def samples(indices, lists):
        out = _compiled_batch()(
            system, prepared.state, jnp.asarray(spec.seed, dtype=jnp.uint32),
            jnp.asarray(indices), jnp.asarray(prepared.dt), jnp.asarray(spec.bound),
            jnp.asarray(spec.velocity_scale), jnp.asarray(spec.x_velocity_scale), lists[1],
            steps=prepared.steps, method=prepared.method,
            watch_det=system.group in OPEN_GROUPS, internal=spec.initial_velocity,
            translational=spec.x_velocity, spec=lists[0])
        return {k: np.array(v) for k, v in out.items()}  # writable: repeats fill them in

    out = {k: v[: task.count] for k, v in samples(task.indices, lists).items()}
    for j in np.flatnonzero(out["code"] == Stop.OVERFLOW):
        out = _repeat_with_larger_list(samples, out, j, task.indices[j], lists, prepared.state)
    dt = prepared.dt
    code = out["code"].astype(np.int64)
    exit_step = out["exit_step"]
    e0, e1 = out["initial_energy"], out["final_energy"]
    with np.errstate(invalid="ignore", divide="ignore"):
        energy_error = relative_error(e1, e0)
    result = {
        "code": code,
        "message": [STATUS_CODES[int(c)][1] for c in code],
        "exit_time": np.where(exit_step >= 0, exit_step * dt, np.nan),
        "followed_time": out["steps_done"] * dt,
        "max_spread": out["max_spread"],
        "energy_error": energy_error,
        "initial_energy": e0,
        "final_energy": e1,
        "max_relative_volume": out["max_relative_volume"],
        "min_det": out["min_det"],
        "max_det": out["max_det"],
        "omega_hat": out["omega_hat"],
        "velocity": out["velocity"],
        "horizon": dt * prepared.steps,
        "worker": {**info, "seconds": time.perf_counter() - clock},
    }
    return result


def _run_thermal_task(task: Task, prepared: _Prepared, info: dict, clock: float) -> dict:
    """:func:`run_task` of a thermostatted sweep (columns :data:`THERMAL_SCALARS`)."""
    import jax.numpy as jnp

    from affinebody import barostat as baro_module
    from affinebody.system import OPEN_GROUPS

    spec = task.spec
    system = prepared.system
    lists = prepared.neighbors or (None, None)

    def samples(indices, lists):
        out = _compiled_thermal_batch()(
            system, prepared.state, jnp.asarray(spec.seed, dtype=jnp.uint32),
            jnp.asarray(indices), jnp.asarray(prepared.dt), jnp.asarray(spec.velocity_scale),
            jnp.asarray(spec.x_velocity_scale), lists[1], jnp.asarray(prepared.temperature),
            None if prepared.pressure is None else jnp.asarray(prepared.pressure),
            steps=prepared.steps, every=prepared.every, equilibration=spec.equilibration,
            method=prepared.method, thermostat=prepared.thermostat,
            barostat=prepared.barostat, space=prepared.space, watch_det=system.group in OPEN_GROUPS,
            internal=spec.initial_velocity, translational=spec.x_velocity, spec=lists[0])
        return {k: np.array(v) for k, v in out.items()}

    cell = None if prepared.barostat is None else prepared.space.matrix
    out = {k: v[: task.count] for k, v in samples(task.indices, lists).items()}
    for j in np.flatnonzero(out["code"] == Stop.OVERFLOW):
        out = _repeat_with_larger_list(samples, out, j, task.indices[j], lists, prepared.state,
                                       cell)
    if prepared.barostat is not None:  # all pairs: the minimum image needs half a cut-off
        for j in np.flatnonzero(out["code"] == _SAMPLED):
            if baro_module.first_narrow_frame(system, out["narrowest_cell"][j][None]) is not None:
                out["code"][j] = _NARROW
    code = out["code"].astype(np.int64)
    result = thermal_results(out, prepared.dt)
    result.update({
        "code": code,
        "message": [STATUS_CODES[int(c)][1] for c in code],
        "omega_hat": out["omega_hat"],
        "velocity": out["velocity"],
        "horizon": prepared.dt * prepared.steps,
        "worker": {**info, "seconds": time.perf_counter() - clock},
    })
    return result


def _repeat_with_larger_list(samples, out, j, index, lists, state, cell=None):
    """Sample ``j`` (sample number ``index``) overflowed its neighbour list: run it again, alone,
    with the list reallocated at the initial configuration by the one capacity policy
    (:func:`affinebody.neighbors.reallocate`, from what the failed step saw), until it
    completes (at most ``MAX_REALLOCATIONS_IN_A_ROW`` times; then it stays failed with the
    reason "neighbour list overflow"). Its result depends on the sample alone, not on the
    batch it ran in."""
    from affinebody import neighbors as nb

    spec = lists[0]
    for _ in range(nb.MAX_REALLOCATIONS_IN_A_ROW):
        try:
            spec, lst = nb.reallocate(spec, state.x, state.phi, flags=int(out["overflow"][j]),
                                      pairs=int(out["most_pairs"][j]),
                                      reach=float(out["largest_reach"][j]), cell=cell)
        except ValueError:  # NeighborListOverflow, or a reach beyond half the box
            break
        again = samples(np.asarray([index]), (spec, lst))
        for key, value in again.items():
            out[key][j] = value[0]
        if int(out["code"][j]) != Stop.OVERFLOW:
            break
    return out


# --------------------------------------------------------------------------- thermal mode
#: The run driver's observables averaged by a thermostatted sample (``simulate.NAMED_OBSERVABLES``).
_AVERAGED = ("energy", "potential_energy", "translational_temperature", "internal_temperature")


def thermal_sample(system, state, dt, seed, temperature, pressure=None, *, steps: int,
                   every: int, equilibration: int, method, thermostat, barostat=None,
                   space=None, watch_det: bool, spec=None, neighbors=None) -> dict[str, Any]:
    """Integrate one thermostatted sample (NVT, or NPT with ``barostat``) and reduce its
    observables to sums of scalars (module docstring, "Thermostatted sweeps"); traceable.

    ``thermostat`` and ``barostat`` are templates: their kT is ``temperature``, the barostat's
    target P0 is ``pressure`` [n, n] (both may be traced). NVT: a ``lax.scan`` of the run
    driver's :func:`~affinebody.simulate.watched_step` with ``method`` composed with the
    thermostat (``integrators.Thermostatted``, its seed replaced by ``seed``). NPT: blocks of
    ``every`` steps of the NPT driver (:func:`affinebody.barostat.advance` with the
    thermostat's O step of ``affinebody run``, :class:`affinebody.runner.ThermostatHook`,
    keys from ``seed``). Observables are measured after every ``every`` steps; those after more than
    ``equilibration`` steps are summed (shifted by their initial values). A failing step
    freezes the sample: ``code`` is then its :class:`~affinebody.simulate.Stop` (or
    ``_BOX``/``_NARROW`` under the barostat), else ``_SAMPLED``. Memory O(N): no frames kept.
    """
    import dataclasses as dc

    import jax
    import jax.numpy as jnp
    from jax import lax

    from affinebody import _linalg as linalg
    from affinebody import barostat as baro_module
    from affinebody import pressure as pm
    from affinebody.integrators import Thermostatted
    from affinebody.runner import ThermostatHook
    from affinebody.simulate import NAMED_OBSERVABLES, initial_forces, watched_step

    dtype = state.x.dtype
    nan = jnp.asarray(jnp.nan, dtype)
    observers = tuple((name, NAMED_OBSERVABLES[name]) for name in _AVERAGED)
    thermostat = dc.replace(thermostat, temperature=temperature, seed=seed)
    if barostat is not None:
        barostat = dc.replace(barostat, pressure=pressure, temperature=temperature)
        p0 = jnp.trace(pressure) / state.n
        hook = ThermostatHook(thermostat)

    def scalars(values, pressure, volume):
        """(E, U, T_tr, T_int, P, V, E + P0 V) from the driver's observables."""
        e = values["energy"]
        enthalpy = e if barostat is None else e + p0 * volume
        return jnp.stack([e, values["potential_energy"], values["translational_temperature"],
                          values["internal_temperature"], pressure, volume,
                          enthalpy]).astype(dtype)

    if barostat is None:
        method = Thermostatted(method, thermostat)
        step = watched_step(system, method, dt, spec, sign0=jnp.sign(linalg.det(state.phi)),
                            watch_det=watch_det)

        def measure(state, nbrs):
            values = {name: f(system, state, nbrs) for name, f in observers}
            if space is None:
                return scalars(values, nan, nan)
            tensor = pm.pressure_tensor(system, state, space, nbrs)
            return scalars(values, pm.scalar_pressure(tensor), jnp.asarray(space.volume, dtype))

        carry0 = (state, neighbors, initial_forces(system, method, state, neighbors))
    else:
        cell0 = jnp.asarray(space.matrix, dtype)

        def measure(state, nbrs, cell=cell0):
            boxed = system.replace(cell=cell)
            values = {name: f(boxed, state, nbrs) for name, f in observers}
            tensor = pm.pressure_tensor(boxed, state, space, nbrs)
            return scalars(values, pm.scalar_pressure(tensor), linalg.det(cell))

        carry0 = (state, neighbors, cell0)

    reference = measure(state, neighbors)
    int0 = jnp.asarray(0, jnp.int32)
    lost0 = (int0, int0, jnp.zeros((), dtype))
    narrowest0 = jnp.asarray(space.matrix if barostat is not None else 0.0, dtype)

    def nvt_block(carry, start):
        def one(inner, _):
            (state, nbrs, forces), code, done, lost = inner
            w = step(state, nbrs, forces)
            first = (code == _SAMPLED) & (w.stop != Stop.NONE)
            good = (code == _SAMPLED) & (w.stop == Stop.NONE)
            if w.tracked is not None:
                seen = (w.tracked.overflow, w.tracked.most_pairs, w.tracked.largest_reach)
                lost = jax.tree.map(lambda old, new: jnp.where(first, new, old), lost, seen)
            keep = lambda new, old: jnp.where(good, new, old)  # noqa: E731
            # the list is not kept back with the state (as in simulate.run: that cost two
            # copies of it per step): once a step failed, the sample's measurements are no
            # longer counted and nothing reads its list again
            state, forces = jax.tree.map(keep, (w.state, w.forces), (state, forces))
            return ((state, w.neighbors, forces), jnp.where(first, w.stop, code), done + good,
                    lost), None

        (moved, code, done, lost), _ = lax.scan(one, carry[:4], None, length=every)
        return moved, code, done, lost, carry[4], measure(moved[0], moved[1]), int0

    def npt_block(carry, start):
        (state, nbrs, cell), code, done, lost, narrowest = carry
        new, new_cell, values, failed, overflowed, narrow, seen, new_list = baro_module.advance(
            system, state, cell, start, seed, dt, nbrs, steps=every, method=method,
            barostat=barostat, space=space, thermostat=hook, observers=observers, spec=spec)
        stop = jnp.where(overflowed, int(Stop.OVERFLOW), jnp.where(
            narrow, _NARROW, jnp.where(failed >= 0, _BOX, int(Stop.NONE))))
        first = (code == _SAMPLED) & (stop != Stop.NONE)
        good = (code == _SAMPLED) & (stop == Stop.NONE)
        lost = jax.tree.map(lambda old, nw: jnp.where(first, nw, old), lost, seen)
        done = jnp.where(good, done + every, jnp.where(first, failed - 1 - start, 0) + done)
        keep = lambda nw, old: jnp.where(good, nw, old)  # noqa: E731
        moved = jax.tree.map(keep, (new, new_list, new_cell), (state, nbrs, cell))
        reciprocal = lambda c: jnp.max(jnp.linalg.norm(linalg.inv(c), axis=-1))  # noqa: E731
        narrowest = jnp.where(good & (reciprocal(new_cell) > reciprocal(narrowest)), new_cell,
                              narrowest)
        rejected = values.get("rejected_moves", int0)  # by the Metropolis test, in this block
        values = scalars(values, pm.scalar_pressure(values["pressure"]), values["volume"])
        return moved, jnp.where(first, stop, code), done, lost, narrowest, values, rejected

    block = nvt_block if barostat is None else npt_block
    zero = jnp.zeros(7, dtype)

    def accumulate(carry, index):
        start = index * every
        moved, code, done, lost, narrowest, values, rejected = block(carry[:5], start)
        counted = (code == _SAMPLED) & (start + every > equilibration)
        shifted = jnp.where(counted, values - reference, 0.0)
        count, total, squares = carry[5]
        sums = (count + counted, total + shifted, squares + shifted * shifted)
        made = 0 if barostat is None else barostat.moves(start, start + every)
        moves = jax.tree.map(lambda a, b: a + jnp.where(counted, b, 0).astype(a.dtype),
                             carry[6], (rejected, made))
        return (moved, code, done, lost, narrowest, sums, moves), None

    init = (carry0, jnp.asarray(_SAMPLED), jnp.asarray(0), lost0, narrowest0,
            (jnp.asarray(0), zero, zero), (int0, int0))
    (moved, code, done, lost, narrowest, sums, moves), _ = lax.scan(
        accumulate, init, jnp.arange(steps // every))
    move_length = nan
    if barostat is not None:  # how long the moves were for the box, at the last state
        final, final_list, final_cell = moved
        move_length = baro_module.move_length(barostat, baro_module.move_modulus_jit(
            system, final, final_cell, final_list, space=space, spec=spec), dt)
    return {"code": code, "steps_done": done, "measurements": sums[0], "reference": reference,
            "move_length": move_length,
            "sums": sums[1], "squares": sums[2], "narrowest_cell": narrowest,
            "temperature": jnp.asarray(temperature, dtype),
            "npt": jnp.asarray(barostat is not None),
            "tested_moves": jnp.asarray(barostat is not None and barostat.metropolis),
            "rejected_moves": moves[0], "barostat_moves": moves[1],
            "overflow": lost[0], "most_pairs": lost[1], "largest_reach": lost[2]}


def _thermal_batch(system, state, seed, indices, dt, internal_scale, translational_scale,
                   neighbors, temperature, pressure, *, steps, every, equilibration, method,
                   thermostat, barostat, space, watch_det, internal, translational, spec):
    """Every sample of a thermostatted task (as :func:`_batch`): sample k draws its initial
    velocities from fold_in(key(seed), k) (sub-keys 0, 1) and the seed of its thermostat (NVT)
    or of the NPT driver's noise (NPT) from its sub-key 2."""
    import jax
    import jax.numpy as jnp

    def one(index):
        key = jax.random.fold_in(jax.random.key(seed), index)
        start, omega_hat, v = draw_initial_state(
            system, state, key, internal=internal, internal_scale=internal_scale,
            translational=translational, translational_scale=translational_scale)
        sample_seed = jax.random.bits(jax.random.fold_in(key, 2), (), jnp.uint32)
        out = thermal_sample(system, start, dt, sample_seed, temperature, pressure,
                             steps=steps, every=every, equilibration=equilibration,
                             method=method, thermostat=thermostat, barostat=barostat,
                             space=space, watch_det=watch_det, spec=spec, neighbors=neighbors)
        return {**out, "omega_hat": omega_hat, "velocity": v}

    if spec is None:
        return jax.vmap(one)(indices)
    return jax.lax.map(one, indices)


@functools.cache
def _compiled_thermal_batch():
    import jax

    return jax.jit(_thermal_batch, static_argnames=(
        "steps", "every", "equilibration", "method", "thermostat", "barostat", "space",
        "watch_det", "internal", "translational", "spec"))


def thermal_results(out: dict[str, np.ndarray], dt: float) -> dict[str, np.ndarray]:
    """The per-sample columns :data:`THERMAL_SCALARS` from the sums of
    :func:`thermal_sample` (host side): means, variances (1/m, of the m measurements),
    C = var(E)/kT^2 (NVT) or var(E + P0 V)/kT^2 (NPT), kappa_T = var(V)/(kT <V>) (NPT), the
    fraction of the barostat's moves rejected (NPT with its Metropolis test)."""
    m = out["measurements"].astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = out["reference"] + out["sums"] / m[:, None]
        shift = out["sums"] / m[:, None]
        var = np.maximum(out["squares"] / m[:, None] - shift * shift, 0.0)
        kt = out["temperature"]
        npt = out["npt"]
        sampled = out["code"] == _SAMPLED
        column = lambda a: np.where(sampled, a, np.nan)  # noqa: E731
        return {
            "followed_time": out["steps_done"] * dt,
            "measurements": m,
            "mean_total_energy": column(mean[:, 0]),
            "var_total_energy": column(var[:, 0]),
            "mean_potential_energy": column(mean[:, 1]),
            "mean_translational_temperature": column(mean[:, 2]),
            "mean_internal_temperature": column(mean[:, 3]),
            "mean_pressure": column(mean[:, 4]),
            "mean_volume": column(mean[:, 5]),
            "var_volume": column(var[:, 5]),
            "heat_capacity": column(var[:, 6] / kt**2),
            "compressibility": column(np.where(npt, var[:, 5] / (kt * mean[:, 5]), np.nan)),
            "rejected_fraction": column(np.where(
                out["tested_moves"] & (out["barostat_moves"] > 0),
                out["rejected_moves"] / np.maximum(out["barostat_moves"], 1), np.nan)),
            "move_length": column(out["move_length"]),
        }


def _failure_result(task: Task, message: str, info: dict | None = None) -> dict[str, Any]:
    nan = np.full(task.count, np.nan)
    result = {"code": np.full(task.count, _ERROR, dtype=np.int64),
              "message": [message] * task.count, "horizon": math.nan,
              "omega_hat": None, "velocity": None, "worker": info or {}}
    result.update({name: nan.copy() for name in SCALARS + THERMAL_SCALARS})
    return result


# --------------------------------------------------------------------------- client side
@dataclass
class SweepResult:
    """Everything a sweep produced. ``samples[name]`` has shape [points, samples] (omega_hat
    [points, samples, N, n, n], velocity [points, samples, N, n], absent when run without
    ``keep_draws``; NaN where not computed),
    ``status`` and ``failure`` are string arrays of the same leading shape."""

    spec: SweepSpec
    points: list[ScanPoint]
    samples: dict[str, np.ndarray]
    status: np.ndarray
    failure: np.ndarray
    summary: dict[str, Any]
    output: Path | None
    workers: list[dict[str, Any]] = field(default_factory=list)


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A Dask client: on the cluster at ``scheduler`` (used unchanged), or on a new local
    cluster of ``workers`` processes (default: all cores; spawn, one thread each), closed after.
    """
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        if workers is not None:
            raise ConfigError("--workers applies to the local cluster only; the cluster at "
                              "--scheduler keeps its own workers")
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as err:
            raise ValueError(f"error: cannot connect to the Dask scheduler at {scheduler}: "
                             f"{err}") from None
        try:
            yield client
        finally:
            client.close()
        return
    cores = os.cpu_count() or 1
    count = cores if workers is None else int(workers)
    if not 1 <= count <= 4 * cores:  # each worker is a process with its own JAX
        raise ConfigError(f"--workers must be 0 (in this process, no Dask) or from 1 to "
                          f"{4 * cores} local processes (4 per core; got {count}): a larger "
                          f"cluster is one to connect to with --scheduler")
    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn"}):
        cluster = LocalCluster(n_workers=count, threads_per_worker=1, processes=True,
                               dashboard_address=":0", silence_logs=logging.ERROR,
                               env=dict(WORKER_ENV))
    try:
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _cluster_info(client) -> dict[str, Any]:
    """Provenance of a Dask cluster: its scheduler's address and its number of workers (a
    worker restarted during the sweep is still one worker, though its process id changed)."""
    info = client.scheduler_info()
    return {"scheduler": info.get("address") or client.scheduler.address,
            "workers": len(info.get("workers", {}))}


def _execute(tasks: list[Task], client, on_done: Callable[[Task, dict], None]) -> None:
    """Run the tasks (on the client's cluster, or here when client is None), calling
    ``on_done(task, result)`` as each completes; a raising task gives failed samples."""
    if client is None:
        for task in tasks:
            try:
                result = run_task(task, in_worker=False)
            except Exception as err:  # noqa: BLE001 - recorded, not fatal
                result = _failure_result(task, f"task error: {type(err).__name__}: {err}")
            on_done(task, result)
        return
    from distributed import as_completed

    token = uuid.uuid4().hex[:8]
    futures = {client.submit(run_task, task, key=f"affinebody-sweep-{token}-{task.name}",
                             pure=False): task for task in tasks}
    for future in as_completed(futures):
        task = futures[future]
        if future.status == "finished":
            result = future.result()
        else:
            err = future.exception()
            result = _failure_result(task, f"task error: {type(err).__name__}: {err}")
        future.release()
        on_done(task, result)


#: The most numbers of drawn velocities a task file holds in its JSON rows; a task that drew
#: more (many bodies) writes them to ``TASK.npz`` beside it: as JSON text, every float
#: converted in Python, 2 samples of 10 648 bodies took 5.9 MB (now 2.0 MB of binary) and a
#: batch of 64 at 10^5 bodies would take gigabytes.
TASK_JSON_DRAWS = 100_000


def _write_task_file(folder: Path, task: Task, point: ScanPoint, result: dict,
                     columns: tuple[str, ...] = SCALARS) -> None:
    """``folder/TASK.json``: the task's samples, row by row, and their drawn velocities
    (``omega_hat``, ``velocity``), in the rows, or in ``TASK.npz`` (arrays [count, N, ...],
    named in the JSON's ``draws``) where they exceed :data:`TASK_JSON_DRAWS` numbers. Each
    file is written under a temporary name and renamed into place."""
    draws = {name: np.asarray(result[name][: task.count]) for name in ("omega_hat", "velocity")
             if result.get(name) is not None}
    inline = sum(a.size for a in draws.values()) <= TASK_JSON_DRAWS
    rows = []
    for j in range(task.count):
        code = int(result["code"][j])
        row = {"sample": task.start + j, "status": STATUS_CODES[code][0],
               "failure": result["message"][j]}
        row.update({name: float(result[name][j]) for name in columns})
        if inline:
            row.update({name: values[j] for name, values in draws.items()})
        rows.append(row)
    data = {"point": task.point, "batch": task.batch, "parameters": point.parameter_dict,
            "samples": [task.start, task.start + task.count], "horizon": result["horizon"],
            "worker": result["worker"], "rows": rows}
    if draws and not inline:
        side = folder / f"{task.name}.npz"
        _write_replacing(side, lambda handle: np.savez(handle, **draws))
        data["draws"] = side.name
    _write_replacing(folder / f"{task.name}.json",
                     lambda handle: handle.write(json_text(data).encode("utf-8")))


def _write_replacing(path: Path, write: Callable) -> None:
    """``write(handle)`` into ``path`` under a temporary name, then renamed into place: a
    reader never sees a half-written task file."""
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, "wb") as handle:
        write(handle)
    temporary.replace(path)


def binomial_summary(successes: int, trials: int) -> dict[str, Any]:
    """Fraction, its standard error sqrt(p(1-p)/m) and the 95% Wilson score interval."""
    if trials == 0:
        return {"fraction": math.nan, "error": math.nan, "interval": [math.nan, math.nan]}
    p = successes / trials
    z = 1.959963984540054
    centre = (p + z * z / (2 * trials)) / (1 + z * z / trials)
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / (
        1 + z * z / trials)
    return {"fraction": p, "error": math.sqrt(p * (1 - p) / trials),
            "interval": [max(0.0, centre - half), min(1.0, centre + half)]}


def _stat(values: np.ndarray, how) -> float:
    finite = values[np.isfinite(values)]
    return float(how(finite)) if finite.size else math.nan


def summarize_point(point: ScanPoint, status: np.ndarray, failure: np.ndarray,
                    samples: dict[str, np.ndarray], bound: float, horizon: float) -> dict:
    """The summary of one parameter point (see the module docstring)."""
    counts = Counter(status.tolist())
    bounded, unbounded = counts.get("bounded", 0), counts.get("unbounded", 0)
    failed = counts.get("failed", 0)
    stats = binomial_summary(bounded, bounded + unbounded)
    classified = status != "failed"
    volume_ok = (samples["max_det"] < bound) & (samples["min_det"] > 1.0 / bound)
    relative_ok = samples["max_relative_volume"] < bound
    followed = samples["followed_time"] >= horizon * (1 - 1e-12)
    volume = binomial_summary(int(np.sum(volume_ok & classified & followed)),
                              int(np.sum(classified & (followed | ~volume_ok))))
    relative = binomial_summary(int(np.sum(relative_ok & classified & followed)),
                                int(np.sum(classified & (followed | ~relative_ok))))
    return {
        "index": point.index,
        "parameters": point.parameter_dict,
        "samples": int(status.size),
        "bounded": bounded,
        "unbounded": unbounded,
        "failed": failed,
        "fraction_bounded": stats["fraction"],
        "fraction_bounded_error": stats["error"],
        "fraction_bounded_interval": stats["interval"],
        "fraction_volume_bounded": volume["fraction"],
        "fraction_relative_volume_bounded": relative["fraction"],
        "energy_error_median": _stat(samples["energy_error"][classified], np.median),
        "energy_error_max": _stat(samples["energy_error"][classified], np.max),
        "max_relative_volume": _stat(samples["max_relative_volume"], np.max),
        "min_det": _stat(samples["min_det"], np.min),
        "max_det": _stat(samples["max_det"], np.max),
        "horizon": horizon,
        "failures": dict(Counter(f for f in failure.tolist() if f)),
        "config_error": point.error,
    }


def summarize_thermal_point(point: ScanPoint, status: np.ndarray, failure: np.ndarray,
                            samples: dict[str, np.ndarray], horizon: float) -> dict:
    """The summary of one point of a thermostatted sweep: for every column of
    :data:`THERMAL_SCALARS` the mean over its sampled samples and the standard error of that
    mean, std / sqrt(m) (``NAME`` and ``NAME_error``); the samples are independent, so the
    error holds however correlated the measurements inside one sample are."""
    counts = Counter(status.tolist())
    ok = status == "sampled"
    out = {"index": point.index, "parameters": point.parameter_dict,
           "samples": int(status.size), "sampled": counts.get("sampled", 0),
           "failed": counts.get("failed", 0)}
    if point.config_json is not None:
        data = json.loads(point.config_json)
        out["temperature"] = data["thermostat"]["temperature"]
        if data.get("barostat") is not None:
            pressure = np.asarray(data["barostat"]["pressure"], dtype=float)
            out["pressure_target"] = float(pressure if pressure.ndim == 0
                                           else np.trace(pressure) / pressure.shape[0])
    for name in THERMAL_SCALARS:
        values = samples[name][ok]
        values = values[np.isfinite(values)]
        m = values.size
        out[name] = float(np.mean(values)) if m else math.nan
        out[f"{name}_error"] = float(np.std(values, ddof=1) / math.sqrt(m)) if m > 1 else math.nan
    out.update({"horizon": horizon,
                "failures": dict(Counter(f for f in failure.tolist() if f)),
                "config_error": point.error})
    return out


def long_moves_warning(lengths: Sequence[float]) -> str | None:
    """The one-line warning of an NPT sweep with plain moves whose mean ``move_length`` at
    some points (``lengths``, NaN where nothing was sampled) exceeds
    :data:`affinebody.barostat.LONG_MOVE`, or None."""
    from affinebody.barostat import LONG_MOVE, LONG_MOVE_FIX, long_move_effect

    lengths = [x for x in lengths if np.isfinite(x)]
    long = [x for x in lengths if x > LONG_MOVE]
    if not long:
        return None
    effect = long_move_effect(max(long), "with them compressibility and heat_capacity")
    return (f"barostat moves are up to {max(long):.2g} of the volume's relaxation time "
            f"(move_length in samples.csv; over {LONG_MOVE} at {len(long)} of {len(lengths)} "
            f"points): {effect}; {LONG_MOVE_FIX}")


def run_sweep(
    config: Config,
    *,
    samples: int | None = None,
    seed: int | None = None,
    client=None,
    scheduler: str | None = None,
    workers: int | None = None,
    output: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
    keep_draws: bool = True,
    refuse_bad_points: bool = False,
) -> SweepResult:
    """Run the sweep of ``config`` (its ``[sweep]`` table, with ``samples``/``seed`` overrides).

    Executes on ``client`` if given, else on the cluster at ``scheduler``, else on a new local
    cluster of ``workers`` processes (default all cores; 0: in this process, no Dask).
    ``output``: folder for the task files, ``samples.csv`` and ``summary.json``.
    ``progress(done_samples, total_samples)`` is called as tasks complete.
    ``keep_draws``: whether the result holds every sample's drawn velocities of every body
    (``samples["omega_hat"]``, ``samples["velocity"]``); without them it holds O(samples)
    numbers, not O(samples x bodies) (the task files of ``output`` hold the draws either
    way: ``affinebody sweep`` keeps none).
    ``refuse_bad_points``: a scan point whose config is refused raises ConfigError before any
    task runs (``affinebody sweep``; :func:`scan_points` with ``refuse``), instead of being
    recorded as failed samples while the other points run.
    """
    clock = time.perf_counter()
    spec = SweepSpec.from_config(config, samples, seed)
    thermal = config.thermostat is not None
    columns = THERMAL_SCALARS if thermal else SCALARS
    points = scan_points(config, refuse=refuse_bad_points)
    _check_results_memory(config, len(points), spec, len(columns), keep_draws)
    tasks = make_tasks(points, spec)
    P, S = len(points), spec.samples
    n, N = config.n, config.bodies_count
    data = {name: np.full((P, S), np.nan) for name in columns}
    if keep_draws:
        data["omega_hat"] = np.full((P, S, N, n, n), np.nan)
        data["velocity"] = np.full((P, S, N, n), np.nan)
    status = np.full((P, S), "failed", dtype=object)
    failure = np.full((P, S), "", dtype=object)
    horizons = np.array([point.horizon for point in points])
    for point in points:
        if point.error is not None:
            failure[point.index] = point.error
    folder = None
    if output is not None:
        folder = Path(output)
        (folder / "tasks").mkdir(parents=True, exist_ok=True)
        for pattern in ("point-*.json", "point-*.npz"):
            for stale in (folder / "tasks").glob(pattern):
                stale.unlink()
    done = 0
    total = sum(t.count for t in tasks)
    worker_info: dict[int, dict] = {}

    def on_done(task: Task, result: dict) -> None:
        nonlocal done
        rows = slice(task.start, task.start + task.count)
        p = task.point
        for name in columns:
            data[name][p, rows] = result[name]
        for name in ("omega_hat", "velocity"):
            if keep_draws and result.get(name) is not None:
                data[name][p, rows] = result[name]
        codes = result["code"]
        status[p, rows] = [STATUS_CODES[int(c)][0] for c in codes]
        failure[p, rows] = result["message"]
        if result["worker"].get("pid") is not None:
            worker_info[result["worker"]["pid"]] = {
                k: v for k, v in result["worker"].items() if k != "seconds"}
        if folder is not None:
            _write_task_file(folder / "tasks", task, points[p], result, columns)
        done += task.count
        if progress is not None:
            progress(done, total)

    cluster = {"scheduler": "in-process", "workers": 1}
    if workers == 0 and client is None and scheduler is None:
        from affinebody._checks import require_x64

        require_x64()  # this process computes: it must already be in float64
        _execute(tasks, None, on_done)
    elif client is not None:
        _execute(tasks, client, on_done)
        cluster = _cluster_info(client)
    else:
        with dask_client(scheduler, workers) as own:
            _execute(tasks, own, on_done)
            cluster = _cluster_info(own)  # while the client is open (closed, it has none)

    summaries = []
    for point in points:
        p = point.index
        if thermal:
            summaries.append(summarize_thermal_point(point, status[p], failure[p],
                                                     {k: v[p] for k, v in data.items()},
                                                     float(horizons[p])))
            continue
        summaries.append(summarize_point(point, status[p], failure[p],
                                         {k: v[p] for k, v in data.items()}, spec.bound,
                                         float(horizons[p])))
    if thermal and config.barostat is not None and not config.barostat.metropolis:
        warning = long_moves_warning([p["move_length"] for p in summaries])
        if warning:
            warnings.warn(warning, RuntimeWarning, stacklevel=2)
    if thermal:
        summary = {
            "ensemble": "NVT" if config.barostat is None else "NPT",
            "equilibration": spec.equilibration,
            "every": config.run.every,
        }
    else:
        pooled = binomial_summary(int(np.sum(status == "bounded")),
                                  int(np.sum(status != "failed")))
        summary = {
            "fraction_bounded": pooled["fraction"],
            "fraction_bounded_error": pooled["error"],
            "fraction_bounded_interval": pooled["interval"],
        }
    summary.update({
        "samples": S,
        "points": summaries,
        "total_samples": P * S,
        "failed": int(np.sum(status == "failed")),
    })
    if not thermal:
        summary["bound"] = spec.bound
    summary.update({
        "horizon": _common(horizons),
        "seed": spec.seed,
        "initial_velocity": spec.initial_velocity,
        "velocity_scale": spec.velocity_scale,
        "scheduler": cluster["scheduler"],
        "workers": cluster["workers"],
        "worker_processes": len(worker_info),
        "wall_seconds": time.perf_counter() - clock,
    })
    if folder is not None:
        (folder / "summary.json").write_text(json_text(summary, indent=1),
                                             encoding="utf-8")
        _write_samples_csv(folder / "samples.csv", points, status, failure, data, columns)
    return SweepResult(spec, points, data, status, failure, summary, folder,
                       list(worker_info.values()))


def _common(values: np.ndarray) -> float:
    """The one finite value of ``values`` (the points' horizons), NaN (null in JSON) where
    they differ, as where a scan changes run.dt or run.steps: each point gives its own."""
    finite = set(values[np.isfinite(values)].tolist())
    return finite.pop() if len(finite) == 1 else math.nan


def _write_samples_csv(path: Path, points, status, failure, data,
                       columns: tuple[str, ...] = SCALARS) -> None:
    import csv

    names = [p for p, _ in points[0].parameters] if points else []
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["point", "sample", *names, "status", "failure", *columns])
        for point in points:
            values = [v for _, v in point.parameters]
            for k in range(status.shape[1]):
                writer.writerow([point.index, k, *values, status[point.index, k],
                                 failure[point.index, k],
                                 *(repr(float(data[s][point.index, k])) for s in columns)])


__all__ = ("BUILD_CHECK_LIMIT", "THERMAL_SCALARS", "TASK_JSON_DRAWS", "SweepResult", "SweepSpec",
           "ScanPoint", "Task", "WORKER_ENV", "binomial_summary", "check_thermal", "dask_client",
           "draw_initial_state", "follow", "long_moves_warning", "make_tasks", "prepare_worker",
           "run_sweep", "run_task", "scan_key", "scan_points", "summarize_thermal_point",
           "thermal_results", "thermal_sample", "json_safe", "scan_values", "summarize_point",
           "results_bytes")
