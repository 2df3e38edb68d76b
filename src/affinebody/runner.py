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
the config's initial state by a fixed rule (:func:`neighbors_at`). A resumed run rebuilds it
the same way at its checkpoint, so it too reproduces the uninterrupted run bit for bit. The
mode used is stored in the file's /parameters (neighbor_list "on" or "off", neighbor_skin).

The click commands ``run``, ``demo``, ``plot``, ``export`` and ``validate`` are registered on
the ``affinebody`` group in :mod:`affinebody.cli`. Errors reach the terminal as one line on
stderr with a non-zero exit status, never as a traceback.
"""

from __future__ import annotations

import functools
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import click
import numpy as np

from affinebody._timing import CompileClock, Phases
from affinebody.checkpoint import Checkpoint, checkpoint_path, load_checkpoint, save_checkpoint
from affinebody.config import (
    Config,
    ConfigError,
    build,
    check_config,
    load_config,
    parse_config,
    uses_neighbor_list,
)
from affinebody.h5md import (
    OBSERVABLES,
    H5MDWriter,
    copy_frames_from_file,
    open_trajectory,
    read_trajectory,
)
from affinebody.state import State

#: Largest number of steps integrated by one compiled call (the progress bar's resolution).
CHUNK_TARGET_STEPS = 1000
#: Observers recorded by the driver -> H5MD observable names.
_OBSERVERS = {
    "total_energy": "energy",
    "kinetic_energy": "kinetic_energy",
    "potential_energy": "potential_energy",
    "linear_momentum": "linear_momentum",
    "affine_momentum": "affine_momentum",
    "angular_momentum": "angular_momentum",
}
assert set(_OBSERVERS) == set(OBSERVABLES)


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

    @property
    def integrate_seconds(self) -> float:
        """Seconds in the compiled loop, compilation excluded."""
        return max(self.phases.get("integrate", self.wall_seconds) - self.compile_seconds, 0.0)

    @property
    def steps_per_second(self) -> float:
        done = self.steps - self.start_step
        seconds = self.integrate_seconds
        return done / seconds if seconds > 0 else math.inf

    def lines(self) -> list[str]:
        resumed = f" (resumed at step {self.start_step})" if self.start_step else ""
        done = self.steps - self.start_step
        rate = self.steps_per_second
        return [
            f"wrote {self.frames} frames, steps 0..{self.steps}{resumed}, to {self.output}",
            f"{done} steps in {self.wall_seconds:.2f} s: compiling {self.compile_seconds:.2f} s, "
            f"integrating {self.integrate_seconds:.2f} s ({rate:.3g} steps/s, "
            f"{rate * self.bodies:.3g} body-steps/s)",
            f"energy {self.initial_energy:.12g} -> {self.final_energy:.12g}, "
            f"max relative error {self.max_relative_energy_error:.3e}",
        ]

    def phase_lines(self) -> list[str]:
        """One line per phase (``affinebody run --verbose``)."""
        out = []
        for name, seconds in self.phases.items():
            extra = (f" (compiling {self.compile_seconds:.3f} s)" if name == "integrate" else "")
            out.append(f"  {name:<22} {seconds:9.3f} s{extra}")
        return out


def enable_x64() -> None:
    """The CLI computes in float64 (the library itself never flips this flag)."""
    import jax

    jax.config.update("jax_enable_x64", True)


def chunk_steps(config: Config) -> int:
    """Steps per compiled call: the largest multiple of run.every dividing the checkpoint
    interval and not above CHUNK_TARGET_STEPS (at least run.every). Depends on the config only."""
    every, interval = config.run.every, config.checkpoint_every
    frames = interval // every
    best = 1
    for d in range(1, frames + 1):
        if frames % d == 0 and d * every <= max(every, CHUNK_TARGET_STEPS):
            best = d
    return best * every


def neighbors_at(system, base, state):
    """The (spec, list) of a run's neighbour list at ``state``, a function of ``base`` (the
    spec allocated for the initial state) and ``state`` only, so that a resumed run rebuilds
    exactly the list of the uninterrupted one.

    The list is built with ``base``'s capacities; while it overflows them, the pair capacity
    grows by factors 3/2 until it holds 5/4 of the pairs in range and the cell capacity
    doubles. (A list that cannot be built so is allocated afresh, also from ``state`` alone.)
    """
    import dataclasses

    import jax.numpy as jnp

    from affinebody import neighbors as nb

    x, phi = jnp.asarray(state.x), jnp.asarray(state.phi)
    spec = base
    for _ in range(64):
        built = nb.build_jit(spec, x, phi)
        flags = int(built.overflow)
        if not flags:
            return spec, built
        if flags & nb.REACH_OVERFLOW:
            break
        capacity, cells = spec.capacity, spec.cell_capacity
        if flags & nb.PAIR_OVERFLOW:
            while capacity < 1.25 * int(built.count):
                capacity = math.ceil(1.5 * capacity)
        if flags & nb.CELL_OVERFLOW:
            cells *= 2
        spec = dataclasses.replace(spec, capacity=capacity, cell_capacity=cells)
    space, cutoff, variable = system.neighbor_range()
    return nb.allocate(space, x, phi, cutoff, variable, base.skin)


def _relative_error(energy: np.ndarray, reference: float) -> np.ndarray:
    return np.abs(energy - reference) / max(abs(reference), np.finfo(float).tiny)


def run_simulation(
    config: Config,
    output: str | Path,
    *,
    steps: int | None = None,
    resume: bool = False,
    progress: Callable[[int, int, float], None] | None = None,
) -> RunSummary:
    """Integrate ``config`` and write the trajectory to ``output`` (H5MD), with checkpoints.

    steps: override run.steps. resume: continue from ``checkpoint_path(output)``.
    progress(step, total, relative_energy_error) is called after every chunk.
    Raises ConfigError / CheckpointError / TrajectoryFileError (ValueErrors) for bad input and
    :class:`SimulationStopped` when the motion breaks down.
    """
    from affinebody.simulate import IntegrationStopped
    from affinebody.simulate import run as integrate

    enable_x64()
    started = time.perf_counter()
    output = Path(output)
    total = config.run.steps if steps is None else int(steps)
    if total < 1:
        raise ConfigError(f"--steps must be >= 1 (got {total})")
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
    writer_args = dict(mass=built.inertia.mass, radius=built.inertia.radius, n=config.n,
                       box=config.system.box, parameters=parameters)
    if resume:
        checkpoint = load_checkpoint(ckpt_file, config_hash)
        if checkpoint.step > total:
            raise ConfigError(f"--steps {total} is before the checkpoint at step "
                              f"{checkpoint.step}; nothing to resume")
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
        start, state = checkpoint.step, checkpoint.state
        initial_energy = float(energies[0])
        max_error = float(np.max(_relative_error(energies, initial_energy)))
        last_energy = float(energies[-1])
    else:
        ckpt_file.unlink(missing_ok=True)
        writer = H5MDWriter(output, **writer_args)
        start, state = 0, built.state
        initial_energy = math.nan
        max_error = 0.0
        last_energy = math.nan

    chunk = chunk_steps(config)
    interval = config.checkpoint_every
    step = start
    lists = None  # (spec, list) valid for `state`, or None: all pairs
    if progress is not None:
        progress(step, total, math.nan)  # before the first (compiling) chunk
    with writer, compiling.installed():
        while step < total:
            if base_spec is not None and step == 0:
                lists = built.neighbors  # allocated for the initial state (= neighbors_at's)
            elif base_spec is not None and (step == start or step % interval == 0):
                with phases("neighbour lists"):
                    lists = neighbors_at(built.system, base_spec, state)
            end = min((step // chunk + 1) * chunk, total)
            pieces = [(end - step - (end - step) % every, every)] if end - step >= every else []
            if (end - step) % every:
                pieces.append(((end - step) % every, (end - step) % every))
            for length, stride in pieces:
                try:
                    with phases("integrate"):
                        trajectory = integrate(built.system, state, dt, length,
                                               config.run.integrator, every=stride,
                                               observers=_OBSERVERS, neighbors=lists)
                    stop = None
                except IntegrationStopped as stopped:
                    trajectory, stop = stopped.trajectory, stopped.report
                frame_steps = step + np.rint(np.asarray(trajectory.times) / dt).astype(np.int64)
                first = 1 if step > 0 or writer.frames > 0 else 0
                energy = np.asarray(trajectory.observables["total_energy"])
                if math.isnan(initial_energy):
                    initial_energy = float(energy[0])
                with phases("output"):
                    writer.append(
                        frame_steps[first:],
                        frame_steps[first:] * dt,
                        State(*(np.asarray(a)[first:] for a in trajectory.states)),
                        {k: np.asarray(v)[first:] for k, v in trajectory.observables.items()},
                    )
                max_error = max(max_error, float(np.max(_relative_error(energy, initial_energy))))
                last_energy = float(energy[-1])
                if stop is not None:
                    raise SimulationStopped(_stop_message(stop, step, dt, built.inertia.labels,
                                                          writer.frames, output))
                state = State(*(np.asarray(a)[-1] for a in trajectory.states))
                lists = trajectory.neighbors
                step += length
            if step % interval == 0 or step == total:
                with phases("output"):
                    save_checkpoint(ckpt_file, Checkpoint(step, state, writer.frames,
                                                          config_hash))
            if progress is not None:
                progress(step, total, float(_relative_error(np.asarray([last_energy]),
                                                             initial_energy)[0]))
        frames = writer.frames
    return RunSummary(output, start, total, frames, time.perf_counter() - started,
                      initial_energy, last_energy, max_error, bodies=config.bodies_count,
                      phases=phases.seconds, compile_seconds=compiling.seconds)


def _stop_message(report, offset: int, dt: float, labels, frames: int, output: Path) -> str:
    step = offset + report.step
    body = labels[report.body] if report.body < len(labels) else str(report.body)
    if report.reason == "left the group":
        cause = ("det phi crossed 0, the body left its configuration group (time step too "
                 "large or potential too weak to keep det phi > 0; group = \"L\" allows it)")
    else:
        cause = report.reason
    return (f"simulation stopped at step {step} (t = {step * dt:.6g}), body {report.body} "
            f"({body}): {cause}; the {frames} frames before it are kept in {output}")


# --------------------------------------------------------------------------- CLI
def _fail(message: str, code: int = 1):
    click.echo(message.splitlines()[0] if message else "error", err=True)
    sys.exit(code)


def one_line_errors(command):
    """Turn every exception of a command into one line on stderr and a non-zero exit."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except SimulationStopped as err:
            _fail(f"error: {err}", 3)
        except KeyboardInterrupt:
            _fail("interrupted: frames written so far are kept; continue with --resume", 130)
        except ValueError as err:
            text = str(err)
            _fail(text if text.startswith(("config error", "error")) else f"error: {text}")
        except OSError as err:
            _fail(f"error: {err.strerror or err}: {err.filename or ''}".rstrip(": "))
        except (click.exceptions.Exit, click.ClickException, SystemExit):
            raise
        except Exception as err:  # noqa: BLE001 - the CLI never shows a traceback
            _fail(f"internal error: {type(err).__name__}: {err}")

    return wrapper


def _progress_callback(quiet: bool):
    """A rich progress bar (steps/s, ETA, energy drift), or None when quiet or not a TTY."""
    from rich.console import Console

    console = Console()
    if quiet or not console.is_terminal:
        return None, None
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    bar = Progress(
        TextColumn("[bold]{task.fields[phase]}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]} steps/s"),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("|dE/E| {task.fields[drift]}"),
        console=console,
        transient=False,
    )
    task = {}

    def update(step: int, total: int, drift: float) -> None:
        now = time.perf_counter()
        if "id" not in task:  # the first chunk compiles: no rate until it is done
            task["id"] = bar.add_task("run", total=total, completed=step, rate="-", drift="-",
                                      phase="compiling")
            task["since"] = None
            return
        if task["since"] is None:
            task["since"] = (now, step)
            bar.update(task["id"], completed=step, phase="integrating", drift=f"{drift:.2e}")
            return
        t0, s0 = task["since"]
        rate = (step - s0) / (now - t0) if now > t0 else 0.0
        bar.update(task["id"], completed=step, rate=f"{rate:.3g}", drift=f"{drift:.2e}",
                   phase="integrating")

    return bar, update


def _run_with_progress(config: Config, output: Path, steps, resume: bool, quiet: bool):
    bar, update = _progress_callback(quiet)
    if bar is None:
        return run_simulation(config, output, steps=steps, resume=resume)
    with bar:
        return run_simulation(config, output, steps=steps, resume=resume, progress=update)


@click.command("run")
@click.argument("config_file", metavar="CONFIG.toml", type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="Output H5MD file (default: CONFIG with suffix .h5).")
@click.option("--steps", type=int, default=None, help="Number of steps (overrides run.steps).")
@click.option("--resume", is_flag=True, help="Continue from the last checkpoint of OUTPUT.")
@click.option("--quiet", is_flag=True, help="No progress bar and no summary.")
@click.option("--verbose", is_flag=True,
              help="Also print the seconds spent in each phase (set-up stages, neighbour lists, "
                   "integration with its compilation, output).")
@one_line_errors
def run(config_file, output, steps, resume, quiet, verbose):
    """Integrate the system of CONFIG.toml and write an H5MD trajectory."""
    started = time.perf_counter()
    enable_x64()
    config = load_config(config_file)
    loaded = time.perf_counter() - started
    output = Path(output) if output else Path(config_file).with_suffix(".h5")
    summary = _run_with_progress(config, output, steps, resume, quiet)
    if not quiet:
        for line in summary.lines():
            click.echo(line)
    if verbose:
        click.echo("phases:")
        click.echo(f"  {'load and validate':<22} {loaded:9.3f} s")
        for line in summary.phase_lines():
            click.echo(line)


def demo_config_text() -> str:
    """The built-in demo config (a 2D crystal of affine bodies), as TOML text."""
    return resources.files("affinebody.examples").joinpath("demo.toml").read_text("utf-8")


@click.command("demo")
@click.option("-o", "--output-dir", type=click.Path(file_okay=False), default="affinebody-demo",
              show_default=True, help="Folder for the trajectory and the plots.")
@click.option("--steps", type=int, default=None, help="Override the demo's number of steps.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@one_line_errors
def demo(output_dir, steps, quiet):
    """Run the built-in example: a small 2D crystal of affine bodies; write H5MD, PNG and XYZ."""
    from affinebody.export import write_xyz
    from affinebody.plotting import plot_all

    enable_x64()
    folder = Path(output_dir)
    folder.mkdir(parents=True, exist_ok=True)
    text = demo_config_text()
    (folder / "demo.toml").write_text(text, encoding="utf-8")
    config = check_config(parse_config(text, "demo.toml"))
    output = folder / "demo.h5"
    summary = _run_with_progress(config, output, steps, False, quiet)
    trajectory = read_trajectory(output)
    images = plot_all(trajectory, folder)
    xyz = folder / "demo.xyz"
    write_xyz(trajectory, xyz)
    for line in summary.lines():
        click.echo(line)
    click.echo(f"config:     {folder / 'demo.toml'}")
    click.echo(f"trajectory: {output}")
    click.echo(f"plots:      {', '.join(str(p) for p in images)}")
    click.echo(f"OVITO:      {xyz}")


@click.command("plot")
@click.argument("trajectory_file", metavar="OUT.h5", type=click.Path(dir_okay=False))
@click.option("-o", "--output-dir", type=click.Path(file_okay=False), default=None,
              help="Folder for the PNG files (default: OUT_plots next to OUT.h5).")
@click.option("--animate", type=click.Choice(["gif", "mp4"]), default=None,
              help="Also write an animation of the bodies (n = 2).")
@click.option("--fps", type=int, default=20, show_default=True, help="Animation frame rate.")
@one_line_errors
def plot(trajectory_file, output_dir, animate, fps):
    """Plot energy, momentum maps, deformation invariants, volumes and (n = 2) the bodies."""
    from affinebody.plotting import plot_all

    enable_x64()
    source = Path(trajectory_file)
    folder = Path(output_dir) if output_dir else source.with_name(source.stem + "_plots")
    with open_trajectory(trajectory_file) as trajectory:  # frames read one at a time
        folder.mkdir(parents=True, exist_ok=True)
        for path in plot_all(trajectory, folder, animate=animate, fps=fps):
            click.echo(str(path))


@click.command("export")
@click.argument("trajectory_file", metavar="OUT.h5", type=click.Path(dir_okay=False))
@click.option("--xyz", "xyz_file", required=True, type=click.Path(dir_okay=False),
              help="Extended XYZ file to write (OVITO reads it).")
@click.option("--every", type=int, default=1, show_default=True, help="Keep every k-th frame.")
@click.option("--thickness", type=float, default=0.05, show_default=True,
              help="Third semi-axis of 2D bodies, as a fraction of the radius.")
@one_line_errors
def export(trajectory_file, xyz_file, every, thickness):
    """Export a trajectory as extended XYZ with ellipsoid shapes and orientations."""
    from affinebody.export import write_xyz

    enable_x64()
    with open_trajectory(trajectory_file) as trajectory:  # frames read one at a time
        count = write_xyz(trajectory, xyz_file, every=every, thickness=thickness)
    click.echo(f"wrote {count} frames to {xyz_file}")


@click.command("validate")
@click.argument("config_file", metavar="CONFIG.toml", type=click.Path(dir_okay=False))
@one_line_errors
def validate(config_file):
    """Check a config file without running it."""
    enable_x64()
    config = load_config(config_file)
    build(config)
    k = config.kinetic
    click.echo(
        f"{config_file}: ok (n = {config.n}, {config.bodies_count} bodies, group "
        f"{config.system.group}, kinetic {k.translational} + {k.internal}, "
        f"{len(config.potential)} potential terms, {config.run.steps} steps of dt = "
        f"{config.run.dt} with {config.run.integrator}, neighbour list "
        f"{'on' if uses_neighbor_list(config) else 'off'})"
    )


COMMANDS = (run, demo, plot, export, validate)
