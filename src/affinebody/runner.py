"""The simulator as a tool: run a config into an H5MD file, resume, plot, export, validate.

:func:`run_simulation` drives :func:`affinebody.simulate.run` chunk by chunk. Chunk boundaries
are fixed multiples of a step count derived from the config alone (dividing the checkpoint
interval), so an interrupted run resumed from its last checkpoint calls the same compiled
function on the same states as the uninterrupted run and reproduces it bit for bit. After each
chunk the new frames are appended to the H5MD file and flushed; at checkpoint steps the state is
saved atomically. A non-finite or singular state stops the run: the frames up to the last good
one stay in the file, and :class:`SimulationStopped` names the step, time, body and likely cause.

Neighbour lists (run.neighbor_list, :func:`affinebody.config.uses_neighbor_list`). The list is
carried from chunk to chunk (``Trajectory.neighbors``) and rebuilt from the state alone at the
start of the run and at every checkpoint step, with capacities grown from those allocated for
the config's initial state by the one capacity rule (:func:`affinebody.neighbors.list_at`). A
resumed run rebuilds it the same way at its checkpoint, so it too reproduces the uninterrupted
run bit for bit. The mode used is stored in the file's /parameters (neighbor_list "on" or
"off", neighbor_skin).

The commands ``run``, ``demo``, ``plot``, ``export`` and ``validate`` of the command line are
in :mod:`affinebody.cli.run`; errors reach the terminal as one line on stderr with a non-zero
exit status (:mod:`affinebody.cli.common`), never as a traceback.
"""

from __future__ import annotations

import functools
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import jax
import numpy as np

from affinebody import _host, _xla, barostat, pair_kernels, pressure
from affinebody import neighbors as nb
from affinebody._checks import enable_x64, reciprocal_condition
from affinebody._timing import CompileClock, Phases
from affinebody.checkpoint import Checkpoint, checkpoint_path, load_checkpoint, save_checkpoint
from affinebody.config import (
    FRAME_BUFFER_BYTES,
    INT64_MAX,
    Config,
    ConfigError,
    build,
    build_potential_entry,
    frame_bytes,
    parse_config,
    records_pressure,
    uses_neighbor_list,
)
from affinebody.h5md import (
    DRIVER_NAMES,
    OBSERVABLES,
    PERIODIC_OBSERVABLES,
    H5MDWriter,
    copy_frames_from_file,
    open_trajectory,
)
from affinebody.potentials import PairTerm, terms_of
from affinebody.simulate import NAMED_OBSERVABLES, StopReport, relative_error
from affinebody.space import as_space
from affinebody.state import State

#: Largest number of steps integrated by one compiled call (the progress bar's resolution).
CHUNK_TARGET_STEPS = 1000
#: The driver's observers (``simulate.NAMED_OBSERVABLES``) behind the file's observables
#: (``h5md.OBSERVABLES``): the same names, except the file's total_energy (H5MD's name).
_OBSERVERS = {name: DRIVER_NAMES.get(name, name) for name in OBSERVABLES}


class SimulationStopped(RuntimeError):
    """The motion became non-finite or singular; the file keeps every frame before it."""


@dataclass(frozen=True)
class RunSummary:
    """What a run did: where it wrote, how far it got, how fast, how well energy was kept.

    ``phases`` holds the wall seconds of each stage (set-up stages, "neighbour lists",
    "integrate", "output"); ``compile_seconds`` the part of "integrate" that JAX spent
    compiling, so the integration rate excludes it."""

    output: Path
    start_step: int
    steps: int
    frames: int
    wall_seconds: float
    initial_energy: float
    final_energy: float
    max_relative_energy_error: float
    bodies: int = 0
    phases: dict = field(default_factory=dict)
    compile_seconds: float = 0.0
    #: (moves rejected, moves made) by a barostat that tests its moves (barostat.metropolis)
    barostat_moves: tuple[int, int] | None = None
    #: how the pair forces were summed, in words (:func:`pair_forces`; "" without pair terms)
    pair_forces: str = ""
    #: the observable whose drift the summary gives: "total_energy" or, with a thermostat or
    #: barostat, "effective_energy" (H less the heat and work put in)
    energy_observable: str = "total_energy"

    @property
    def integrate_seconds(self) -> float:
        """Seconds in the compiled loop, compilation excluded (0 where nothing was integrated:
        a resumed run that was already complete; its seconds went to copying its frames)."""
        return max(self.phases.get("integrate", 0.0) - self.compile_seconds, 0.0)

    @property
    def steps_per_second(self) -> float:
        """Steps integrated per second of :attr:`integrate_seconds` (0 where none were)."""
        done = self.steps - self.start_step
        if done == 0:
            return 0.0
        seconds = self.integrate_seconds
        return done / seconds if seconds > 0 else math.inf

    def lines(self) -> list[str]:
        resumed = f" (resumed at step {self.start_step})" if self.start_step else ""
        done = self.steps - self.start_step
        rate = self.steps_per_second
        work = (f"{done} steps in {self.wall_seconds:.2f} s: compiling "
                f"{self.compile_seconds:.2f} s, integrating {self.integrate_seconds:.2f} s "
                f"({rate:.3g} steps/s, {rate * self.bodies:.3g} body-steps/s)") if done else (
            f"nothing integrated: the run was already complete at step {self.steps} "
            f"({self.wall_seconds:.2f} s to check it and copy its frames)")
        return [
            f"wrote {self.frames} frames, steps 0..{self.steps}{resumed}, to {self.output}",
            work,
            f"{self.energy_observable.replace('_', ' ')} {self.initial_energy:.12g} -> "
            f"{self.final_energy:.12g}, "
            f"max relative error {self.max_relative_energy_error:.3e}",
        ] + ([] if not (self.barostat_moves and self.barostat_moves[1]) else [
            f"barostat: {self.barostat_moves[0]} of {self.barostat_moves[1]} moves rejected "
            f"({self.barostat_moves[0] / max(self.barostat_moves[1], 1):.1%})"])

    def phase_lines(self) -> list[str]:
        """One line per phase (``affinebody run --verbose``)."""
        out = []
        for name, seconds in self.phases.items():
            extra = (f" (compiling {self.compile_seconds:.3f} s)" if name == "integrate" else "")
            out.append(f"  {name:<22} {seconds:9.3f} s{extra}")
        return out


def chunk_steps(config: Config) -> int:
    """Steps per compiled call: the largest multiple of run.every dividing the checkpoint
    interval, not above CHUNK_TARGET_STEPS and with its frames within FRAME_BUFFER_BYTES (at
    least run.every: memory O(N) for any N). Depends on the config only (bit-exact resume)."""
    every, interval = config.run.every, config.checkpoint_every
    frames = interval // every
    most_frames = max(1, FRAME_BUFFER_BYTES // frame_bytes(config))
    # from the largest candidate down: a checkpoint interval of 10^12 steps takes no time
    for d in range(min(frames, most_frames, max(1, CHUNK_TARGET_STEPS // every)), 0, -1):
        if frames % d == 0:
            return d * every
    return every


def host_kernels_do_the_threading(config: Config) -> bool:
    """Whether a run of ``config`` on a CPU does all its parallel work in the host kernels
    (:mod:`affinebody._host`, which split it over the cores on threads of their own): pair
    forces over a neighbour list, every pair term through the fused kernel (a config
    expression, or a family that gives its f as one:
    :func:`affinebody.pair_kernels.fused_on_host`; a barostat's virial pass runs the fused
    kernel too, and NPT runs measured faster with XLA's one thread: README, "Constant
    pressure vs constant volume"). Any other run leaves XLA work it spreads over the cores
    itself: the all-pairs sums, an f that XLA evaluates between two host calls (a Python f,
    harmonic-invariants)."""
    terms = [build_potential_entry(e, k, config) for k, e in enumerate(config.potential)]
    return uses_neighbor_list(config, terms) and all(
        pair_kernels.fused_on_host(term, config.n) for term in terms
        if isinstance(term, PairTerm))


def prepare_process(config: Config) -> bool:
    """What ``affinebody run`` does for its own process before JAX starts, once the config is
    known: where :func:`host_kernels_do_the_threading` and the host kernels' threads take
    every core the process may use (at most :data:`affinebody._host.PARTS` cores), XLA's CPU
    client gets one thread (:func:`affinebody._xla.single_xla_thread`). With more cores
    XLA's idle pool threads have cores of their own, and its per-body work of large systems
    may use them. True when it set it."""
    return (_host.cores() <= _host.PARTS and host_kernels_do_the_threading(config)
            and _xla.single_xla_thread())


def run_simulation(
    config: Config,
    output: str | Path,
    *,
    steps: int | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: Callable[[int, int, float], None] | None = None,
) -> RunSummary:
    """Integrate ``config`` and write the trajectory to ``output`` (H5MD), with checkpoints.

    steps: override run.steps. resume: continue from ``checkpoint_path(output)``.
    overwrite: replace an existing ``output`` (and its checkpoint); without it (and without
    ``resume``) an existing output is refused before anything is computed, so a repeated
    command never destroys a trajectory.
    progress(step, total, relative_energy_error) is called after every chunk.
    Raises ConfigError / CheckpointError / TrajectoryFileError (ValueErrors) for bad input and
    :class:`SimulationStopped` when the motion breaks down.
    """
    from affinebody.simulate import IntegrationStopped
    from affinebody.simulate import run as integrate

    enable_x64()  # the simulator as a tool computes in float64 (the CLI turns it on too)
    _host.keep_freed_memory()  # a step's freed arrays are reused, not faulted in afresh
    started = time.perf_counter()
    output = Path(output)
    total = config.run.steps if steps is None else int(steps)
    if not 1 <= total <= INT64_MAX:
        raise ConfigError(f"--steps must be >= 1 and <= {INT64_MAX} (got {total})")
    if not output.parent.is_dir():
        raise ConfigError(f"-o {output}: the folder {output.parent} does not exist (create it, "
                          f"or write elsewhere)")
    if not (resume or overwrite) and (output.exists() or checkpoint_path(output).exists()):
        raise ConfigError(f"{output} exists: continue it with --resume, replace it with "
                          f"--overwrite, or write elsewhere with -o")
    built = build(config)
    phases = Phases()
    for name, seconds in built.timings.items():
        phases.add(f"set-up: {name}", seconds)
    compiling = CompileClock()
    dt, every = config.run.dt, config.run.every
    ckpt_file = checkpoint_path(output)
    config_hash = config.hash()
    parameters = {
        "config": config.source_text,
        "seed": config.run.seed,
        "dt": dt,
        "steps": total,
        "every": every,
        "integrator": config.run.integrator,
        "config_hash": config_hash,
        "neighbor_list": "on" if built.neighbor_list else "off",
    }
    base_spec = None
    if built.neighbor_list:
        parameters["neighbor_skin"] = config.run.neighbor_skin
        base_spec = built.neighbors[0]
    resumed_spec = base_spec  # the list sizes a resumed run starts from
    writer_args = dict(mass=built.inertia.mass, radius=built.inertia.radius, n=config.n,
                       box=config.system.box, parameters=parameters,
                       units=config.system.units, pressure=records_pressure(config),
                       thermostat=_tracks_heat(config, built),
                       barostat_test=config.barostat is not None and config.barostat.metropolis)
    if resume:
        checkpoint = load_checkpoint(ckpt_file, config_hash,
                                     changes=lambda: _changes_since(output, config))
        if checkpoint.step > total:
            given = f"--steps {total}" if steps is not None else f"run.steps = {total}"
            raise ConfigError(f"{given} is before the checkpoint at step {checkpoint.step} "
                              f"(the run was extended with --steps): give --steps "
                              f"{checkpoint.step} or more to continue it")
        temporary = output.with_name(output.name + ".resume.tmp")
        writer = H5MDWriter(temporary, **writer_args)
        try:
            copied, energies = copy_frames_from_file(output, writer, checkpoint.step)
            if copied != checkpoint.frames:
                raise ConfigError(f"{output} holds {copied} frames up to step {checkpoint.step}, "
                                  f"the checkpoint expects {checkpoint.frames}; cannot resume")
        except BaseException:
            writer.close()
            temporary.unlink(missing_ok=True)
            raise
        temporary.replace(output)
        writer.path = output
        start, state, heat = checkpoint.step, checkpoint.state, checkpoint.heat
        if base_spec is not None and checkpoint.neighbor_sizes is not None:
            resumed_spec = nb.resized(base_spec, checkpoint.neighbor_sizes)
        initial_energy = float(energies[0])
        max_error = float(np.max(relative_error(energies, initial_energy)))
        last_energy = float(energies[-1])
    else:
        ckpt_file.unlink(missing_ok=True)
        writer = H5MDWriter(output, **writer_args)
        start, state, heat = 0, built.state, 0.0
        initial_energy = math.nan
        max_error = 0.0
        last_energy = math.nan

    chunk = chunk_steps(config)
    # the conserved quantity whose error is reported: H, or H minus the heat under a thermostat
    energy_key = "effective_energy" if _tracks_heat(config, built) else "total_energy"
    interval = config.checkpoint_every
    step = start
    lists = None  # (spec, list) valid for `state`, or None: all pairs
    observers = dict(_OBSERVERS)
    if records_pressure(config):  # pressure and volume (docs/pressure.md)
        space = as_space(tuple(config.system.box))
        observers.update((name, pressure.Observer(name, space))
                         for name in PERIODIC_OBSERVABLES)
    npt = None if config.barostat is None else _NPT(config, built)
    rejected = 0  # barostat moves rejected by their Metropolis test in this run
    if npt is not None and resume:
        npt.cell = checkpoint.cell
    if progress is not None:
        progress(step, total, math.nan)  # before the first (compiling) chunk
    with writer, compiling.installed():
        while step < total:
            if base_spec is not None and step == 0:
                lists = built.neighbors  # allocated for the initial state (= list_at's)
            elif base_spec is not None and (step == start or step % interval == 0):
                # rebuilt from the state alone (a resumed run rebuilds the same), at the sizes
                # in use: those grown by a reallocation are kept (no new shapes to compile)
                with phases("neighbour lists"):
                    lists = nb.list_at(resumed_spec if lists is None else lists[0], state.x,
                                       state.phi, None if npt is None else npt.cell)
            end = min((step // chunk + 1) * chunk, total)
            pieces = [(end - step - (end - step) % every, every)] if end - step >= every else []
            if (end - step) % every:
                pieces.append(((end - step) % every, (end - step) % every))
            for length, stride in pieces:
                boxes = None
                try:
                    with phases("integrate"):
                        if npt is not None:
                            trajectory, boxes, stop = npt.run(state, step, length, stride,
                                                              lists, heat)
                        else:
                            trajectory = integrate(built.system, state, dt, length,
                                                   config.run.integrator, every=stride,
                                                   observers=observers, neighbors=lists,
                                                   thermostat=built.thermostat,
                                                   first_step=step, heat=heat)
                            stop = None
                except IntegrationStopped as stopped:
                    trajectory, stop = stopped.trajectory, stopped.report
                frame_steps = step + np.rint(np.asarray(trajectory.times) / dt).astype(np.int64)
                first = 1 if step > 0 or writer.frames > 0 else 0
                energy = np.asarray(trajectory.observables[energy_key])
                if math.isnan(initial_energy):
                    initial_energy = float(energy[0])
                with phases("output"):
                    writer.append(
                        frame_steps[first:],
                        frame_steps[first:] * dt,
                        State(*(np.asarray(a)[first:] for a in trajectory.states)),
                        {k: np.asarray(v)[first:] for k, v in trajectory.observables.items()},
                        None if boxes is None else boxes[first:],
                    )
                if "rejected_moves" in trajectory.observables:
                    rejected += int(np.sum(trajectory.observables["rejected_moves"][first:]))
                max_error = max(max_error, float(np.max(relative_error(energy, initial_energy))))
                last_energy = float(energy[-1])
                state = State(*(np.asarray(a)[-1] for a in trajectory.states))
                singular = None if stop is not None else _singular_stop(
                    built.system, state, length, dt, step)  # finite, det of its sign: a body?
                if stop is not None or singular is not None:
                    raise SimulationStopped(_stop_message(
                        stop or singular, step, dt, built.inertia.labels, writer.frames, output,
                        through=singular is not None))
                if "heat" in trajectory.observables:
                    heat = float(trajectory.observables["heat"][-1])
                lists = trajectory.neighbors
                step += length
            if step % interval == 0 or step == total:
                with phases("output"):
                    save_checkpoint(ckpt_file, Checkpoint(
                        step, state, writer.frames, config_hash,
                        None if npt is None else npt.cell, heat,
                        None if lists is None else nb.sizes(lists[0])))
            if progress is not None:
                progress(step, total, float(relative_error(np.asarray([last_energy]),
                                                             initial_energy)[0]))
        frames = writer.frames
    if npt is not None and not npt.barostat.metropolis and step > start:
        try:  # are the plain moves short against the volume's relaxation?
            with phases("checks"):
                modulus = barostat.move_modulus(npt.system, state, npt.cell, npt.space, lists)
            warning = barostat.long_move_warning(npt.barostat, modulus, dt)
        except Exception as err:  # noqa: BLE001 - a diagnostic never fails a finished run
            warning = (f"the length of the barostat's moves was not checked "
                       f"({type(err).__name__}: {err})")
        if warning:
            warnings.warn(warning, RuntimeWarning, stacklevel=2)
    return RunSummary(output, start, total, frames, time.perf_counter() - started,
                      initial_energy, last_energy, max_error, bodies=config.bodies_count,
                      phases=phases.seconds, compile_seconds=compiling.seconds,
                      barostat_moves=None if npt is None or not npt.barostat.metropolis else (
                          rejected, npt.barostat.moves(start, step)),
                      pair_forces=pair_forces(built.system, config.n, built.neighbor_list),
                      energy_observable=energy_key)


def _changes_since(output: Path, config: Config) -> list[str]:
    """The settings in which ``config`` differs from the config stored in ``output`` (the run
    being resumed), for the refusal of a checkpoint of another configuration; empty when the
    file or its config cannot be read."""
    try:
        with open_trajectory(output) as trajectory:
            text = trajectory.config_text
        return config.changes_from(parse_config(text)) if text else []
    except (OSError, ValueError):  # a damaged file: the refusal without the list
        return []


def pair_forces(system, n: int, listed: bool) -> str:
    """How a run sums the pair forces of ``system``, in words: over all pairs (autodiff of
    the pair terms), or over the neighbour list with the kernel of
    :func:`affinebody.pair_kernels.kernel_in_use`; "" without pair terms."""
    pairs = [t for t in terms_of(system.potential) if isinstance(t, PairTerm)]
    if not pairs:
        return ""
    if not listed:
        return "all pairs (autodiff of the pair terms)"
    kernels = dict.fromkeys(pair_kernels.kernel_in_use(t, n) for t in pairs)
    return "neighbour list, " + "; ".join(kernels)


def _tracks_heat(config: Config, built) -> bool:
    """Whether the run records the heat and the effective energy: a thermostat, or a barostat
    (whose work the NPT driver books with the heat)."""
    return built.thermostat is not None or config.barostat is not None


class _NPT:
    """The constant-pressure driver of a run with a ``[barostat]``: ``affinebody.barostat.run``
    over the run's pieces, carrying the cell from piece to piece (and through checkpoints)."""

    def __init__(self, config: Config, built):
        self.config, self.system = config, built.system
        self.space = as_space(tuple(config.system.box))
        self.barostat, self.thermostat = constant_pressure(config, built.thermostat)
        self.cell = self.space.matrix
        self.observers = tuple((name, NAMED_OBSERVABLES[driver])
                               for name, driver in _OBSERVERS.items())

    def run(self, state, step: int, length: int, every: int, lists=None, exchanged=0.0):
        """(trajectory, box edges of its frames, stop report or None) of ``length`` steps
        from ``state`` at ``step``; the frames stop before the first non-finite one.
        ``lists``: the (spec, list) of a neighbour-list run, valid for ``state`` in the
        current cell, or None. ``exchanged``: the heat and the barostat's work before
        ``step`` (one sum, what the checkpoint keeps as its heat); the trajectory's ``heat``
        is that sum too."""
        from affinebody.simulate import Trajectory

        c = self.config
        npt = barostat.run(self.system, state, self.space, self.barostat, c.run.dt, length,
                           seed=c.run.seed, cell=self.cell, first_step=step,
                           integrator=c.run.integrator, every=every, observers=self.observers,
                           neighbors=lists, thermostat=self.thermostat, heat=exchanged)
        npt.observables["heat"] = npt.observables["heat"] + npt.observables.pop("work")
        frame_steps = np.rint(npt.times / c.run.dt).astype(np.int64)
        finite = (np.ones(len(frame_steps), dtype=bool) if npt.failed_step is None
                  else frame_steps < npt.failed_step)
        keep = len(finite) if finite.all() else int(np.argmin(finite))
        narrow = barostat.first_narrow_frame(self.system, npt.cells[:keep])
        stop = None
        if keep < len(finite) or narrow is not None:
            reason = self._stop_reason(npt, keep, narrow)
            keep = keep if narrow is None else narrow
            bad = (npt.failed_step if narrow is None else int(frame_steps[keep])) - step
            stop = StopReport(bad, (step + bad) * c.run.dt, -1, reason, reason)
        cut = lambda a: np.asarray(a)[:keep]  # noqa: E731
        trajectory = Trajectory(times=cut(npt.times) - step * c.run.dt,
                                states=jax.tree.map(cut, npt.states),
                                observables={k: cut(v) for k, v in npt.observables.items()},
                                neighbors=npt.neighbors)
        self.cell = np.asarray(npt.cells[keep - 1])
        return trajectory, np.diagonal(npt.cells[:keep], axis1=1, axis2=2), stop

    def _stop_reason(self, npt, keep: int, narrow: int | None) -> str:
        """Why the piece ``npt`` stopped after ``keep`` good frames (``narrow``: the first
        frame whose box is too narrow for the pair cut-off, or None), and what to change: the
        barostat's parameters named with their values when its next move from the last good
        frame is large (``barostat.stop_advice``)."""
        if narrow is not None:
            return ("the box shrank below twice the pair cut-off (the minimum image is no "
                    "longer exact): lower barostat.pressure or start from a larger system.box")
        if npt.stop_reason is not None:
            return npt.stop_reason
        advice = None if keep == 0 else barostat.stop_advice(
            self.barostat, npt.cells[keep - 1], npt.observables["pressure"][keep - 1],
            self.space, self.config.run.dt)
        return "non-finite state or box under the barostat: " + (advice or (
            "reduce run.dt or raise barostat.tau (a stop in the first moves: check the initial "
            "state, e.g. bodies on top of each other, and barostat.pressure, compressibility "
            "and the temperature against the system's scale)"))


def constant_pressure(config: Config, thermostat):
    """(barostat, thermostat hook) of a config with a ``[barostat]``: the
    ``barostat.StochasticCellRescaling`` of the table (kT: barostat.temperature, else the
    thermostat's) and the ``thermostat``'s O step after each step, with its own keys (which
    ``barostat.run`` folds from its step key), or None. The parts of every NPT run:
    ``affinebody run`` and the samples of ``affinebody sweep``."""
    b = config.barostat
    temperature = b.temperature if b.temperature is not None else thermostat.temperature
    try:
        baro = barostat.c_rescale(b.pressure, config.n, tau=b.tau,
                                  compressibility=b.compressibility, temperature=temperature,
                                  coupling=b.coupling, interval=b.interval,
                                  metropolis=b.metropolis)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    return baro, None if thermostat is None else ThermostatHook(thermostat)


def thermostat_hook(thermostat, system, state, key, dt, noise=None):
    """The ``[thermostat]``'s O(dt) step in the form ``barostat.run`` takes; ``noise``: the
    ``thermostats.factors`` of the system, computed here when not given."""
    from affinebody import thermostats

    noise = thermostats.factors(system, state) if noise is None else noise
    return thermostats.thermostat_step(system, thermostat, state, dt, key, noise)[0]


@dataclass(frozen=True)
class ThermostatHook:
    """:func:`thermostat_hook` of one thermostat, as a value: hooks of equal thermostats are
    equal, so runs of one config in one process share their compiled NPT loop (a static
    argument), where a new ``functools.partial`` per run would compile it again."""

    thermostat: object

    def __call__(self, system, state, key, dt):
        return thermostat_hook(self.thermostat, system, state, key, dt)

    def prepare(self, system, state):
        """The hook with the noise factors computed once, what ``barostat.run`` calls before
        its loop: they depend on the kinetic model and the number of bodies only (computed in
        every step they cost 3-5 % of an NPT step at 97 336 bodies, af-is with Langevin)."""
        from affinebody import thermostats

        return functools.partial(thermostat_hook, self.thermostat,
                                 noise=thermostats.factors(system, state))


def _singular_stop(system, state: State, length: int, dt: float, offset: int):
    """A StopReport where a body of the state a chunk ended with is out of its configuration
    group though the loop's checks passed: on GL+ and GL, phi singular to float64 with det phi
    still of its sign (the body flattened or sheared without bound). The next chunk would
    have refused that state as if it were the run's initial state."""
    body = system.outside_group(state.phi)
    if body is None:
        return None
    phi = np.asarray(state.phi[body])
    if system.group in ("GL", "GL+"):
        reason = (f"phi is singular as far as float64 resolves (reciprocal condition number "
                  f"{float(reciprocal_condition(phi)):.1e}, det phi "
                  f"{float(np.linalg.det(phi)):.3g}): the body flattened or sheared without "
                  f"bound by this step (reduce run.dt, check the potential and the initial "
                  f"data)")
    else:
        reason = (f"phi drifted off {system.group}(n) beyond the tolerance 1e-9 by this step "
                  f"(reduce run.dt)")
    return StopReport(length, (offset + length) * dt, body, reason, reason)


def _stop_message(report, offset: int, dt: float, labels, frames: int, output: Path,
                  through: bool = False) -> str:
    """The one line of a stopped run; ``through``: the last frame kept is at the stop (a
    state found singular at the end of a chunk), not before it."""
    step = offset + report.step
    who = ""  # a stop of the box or of the list is no one body's
    if report.body >= 0:
        label = labels[report.body] if report.body < len(labels) else str(report.body)
        who = f", body {report.body} ({label})"
    if report.reason == "left the group":
        cause = ("det phi crossed 0, the body left its configuration group (time step too "
                 "large or potential too weak to keep det phi > 0; group = \"L\" allows it)")
    else:
        cause = report.reason
    when = "up to" if through else "before"
    kept = f"the {frames} frames {when} it are" if frames != 1 else f"the frame {when} it is"
    return (f"simulation stopped at step {step} (t = {step * dt:.6g}){who}: {cause}; {kept} "
            f"kept in {output}")


def demo_config_text() -> str:
    """The built-in demo config (a 2D crystal of affine bodies), as TOML text."""
    return resources.files("affinebody.examples").joinpath("demo.toml").read_text("utf-8")


__all__ = [
    "CHUNK_TARGET_STEPS", "SimulationStopped", "RunSummary", "chunk_steps", "run_simulation",
    "constant_pressure", "thermostat_hook", "ThermostatHook", "demo_config_text",
    "host_kernels_do_the_threading", "pair_forces", "prepare_process",
]
