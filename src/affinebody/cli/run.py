"""``affinebody run | demo | plot | export | validate``: the simulator's commands.

The work is done by :func:`affinebody.runner.run_simulation` (config -> H5MD with checkpoints),
:mod:`affinebody.plotting` and :mod:`affinebody.export`; this module parses the command line,
shows the progress bar (steps/s, ETA, energy drift; "compiling" until the first chunk is done)
and prints the summaries.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from typing import TYPE_CHECKING

import click

from affinebody.cli.common import (
    check_output_file,
    enable_x64,
    one_line_errors,
    output_console,
    raise_if_interrupted,
    refuse_writing_over,
)
from affinebody.export import SPECIES  # NumPy only: the commands' help loads no JAX

if TYPE_CHECKING:
    from affinebody.config import Config


def _progress_callback(quiet: bool):
    """A rich progress bar (steps/s, ETA, energy drift), or None when quiet or not a TTY."""

    console = output_console()
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


def _run_with_progress(config: Config, output: Path, steps, resume: bool, quiet: bool,
                       overwrite: bool = False, resumable: bool = True):
    """``run_simulation`` with the progress bar, stopped by the first Ctrl-C (checked after
    each chunk, :func:`~affinebody.cli.common.raise_if_interrupted`); an interrupted run
    (``resumable``: of a command with --resume) says whether it can be resumed."""
    from affinebody.checkpoint import checkpoint_path
    from affinebody.runner import run_simulation

    bar, update = _progress_callback(quiet)

    def progress(step: int, total: int, drift: float) -> None:
        raise_if_interrupted()
        if update is not None:
            update(step, total, drift)
    try:
        with bar if bar is not None else contextlib.nullcontext():
            return run_simulation(config, output, progress=progress, steps=steps,
                                  resume=resume, overwrite=overwrite)
    except KeyboardInterrupt:
        if not resumable:
            raise
        if checkpoint_path(output).exists():
            raise KeyboardInterrupt(f"{output} and its checkpoint are kept: the same command "
                                    f"with --resume continues the run") from None
        raise KeyboardInterrupt(f"before the first checkpoint: {output} keeps the frames "
                                f"written so far, and there is no checkpoint to --resume "
                                f"from (run again with --overwrite)") from None


@click.command("run")
@click.argument("config_file", metavar="CONFIG.toml", type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False),
              help="Output H5MD file (default: CONFIG with suffix .h5).")
@click.option("--steps", type=int, default=None, help="Number of steps (overrides run.steps).")
@click.option("--resume", is_flag=True, help="Continue from the last checkpoint of OUTPUT.")
@click.option("--overwrite", is_flag=True,
              help="Replace OUTPUT if it exists (without it an existing OUTPUT is refused).")
@click.option("--quiet", is_flag=True, help="No progress bar and no summary.")
@click.option("--verbose", is_flag=True,
              help="Also print the seconds spent in each phase (set-up stages, neighbour lists, "
                   "integration with its compilation, output).")
@one_line_errors
def run(config_file, output, steps, resume, overwrite, quiet, verbose):
    """Integrate the system of CONFIG.toml and write an H5MD trajectory."""
    started = time.perf_counter()
    from affinebody.checkpoint import checkpoint_path
    from affinebody.config import load_config
    from affinebody.runner import prepare_process

    enable_x64()
    config = load_config(config_file)
    single_xla_thread = prepare_process(config)  # before JAX starts its backend
    loaded = time.perf_counter() - started
    output = Path(output) if output else Path(config_file).with_suffix(".h5")
    if resume and overwrite:
        raise click.UsageError("--resume continues OUTPUT and --overwrite replaces it: give one")
    refuse_writing_over(output, config_file, "-o")
    check_output_file(output, "-o")
    refuse_writing_over(checkpoint_path(output), config_file, "-o's checkpoint")
    summary = _run_with_progress(config, output, steps, resume, quiet, overwrite)
    if not quiet:
        for line in summary.lines():
            click.echo(line)
    if verbose:
        import jax

        device = jax.devices()[0]
        click.echo(f"device: {device.platform} {device.device_kind} (JAX {jax.__version__})")
        if summary.pair_forces:
            click.echo(f"pair forces: {summary.pair_forces}")
        if single_xla_thread:
            click.echo("threads: XLA's CPU client 1 (the host kernels split the work over the "
                       "cores)")
        click.echo("phases:")
        click.echo(f"  {'load and validate':<22} {loaded:9.3f} s")
        for line in summary.phase_lines():
            click.echo(line)


@click.command("demo")
@click.option("-o", "--output-dir", type=click.Path(file_okay=False), default="affinebody-demo",
              show_default=True, help="Folder for the trajectory and the plots.")
@click.option("--steps", type=int, default=None, help="Override the demo's number of steps.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@one_line_errors
def demo(output_dir, steps, quiet):
    """Run the built-in example: a small 2D crystal of affine bodies; write H5MD, PNG and XYZ."""
    from affinebody.config import check_config, parse_config
    from affinebody.export import write_xyz
    from affinebody.h5md import read_trajectory
    from affinebody.plotting import plot_all
    from affinebody.runner import demo_config_text, prepare_process

    enable_x64()
    folder = Path(output_dir)
    folder.mkdir(parents=True, exist_ok=True)
    text = demo_config_text()
    (folder / "demo.toml").write_text(text, encoding="utf-8")
    config = check_config(parse_config(text, "demo.toml"))
    prepare_process(config)
    output = folder / "demo.h5"
    # the demo's folder is its own: a repeated `make demo` replaces its trajectory
    summary = _run_with_progress(config, output, steps, False, quiet, overwrite=True,
                                 resumable=False)
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
    """Plot energy, momentum maps, deformation invariants, temperatures, pressure and volume
    (NPT), and the bodies (rods for n = 1, ellipses for n = 2, ellipsoids for n = 3)."""
    from affinebody.h5md import open_trajectory
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
@click.option("--species", default=SPECIES, show_default=True,
              help="The species column of every body (OVITO gives a name that begins with a "
                   "capitalised element symbol, e.g. B, that element's colour and radius).")
@one_line_errors
def export(trajectory_file, xyz_file, every, thickness, species):
    """Export a trajectory as extended XYZ with ellipsoid shapes and orientations."""
    from affinebody.export import write_xyz
    from affinebody.h5md import open_trajectory

    enable_x64()
    refuse_writing_over(xyz_file, trajectory_file, "--xyz")
    check_output_file(xyz_file, "--xyz")
    with open_trajectory(trajectory_file) as trajectory:  # frames read one at a time
        count = write_xyz(trajectory, xyz_file, every=every, thickness=thickness,
                          species=species)
    click.echo(f"wrote {count} frames to {xyz_file}")


@click.command("validate")
@click.argument("config_file", metavar="CONFIG.toml", type=click.Path(dir_okay=False))
@one_line_errors
def validate(config_file):
    """Check a config file without running it."""
    from affinebody.config import build, load_config, uses_neighbor_list

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


__all__ = [
    "run", "demo", "plot", "export", "validate", "COMMANDS"
]
