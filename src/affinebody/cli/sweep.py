"""``affinebody sweep``: ensembles and parameter sweeps on Dask (:mod:`affinebody.sweep` does
the work; this module parses the command line, shows progress and prints the summary table)."""

from __future__ import annotations

import contextlib
import io
import math
from collections import Counter
from pathlib import Path

import click

from affinebody._json import json_text
from affinebody.cli.common import (
    EXIT_STOPPED,
    enable_x64,
    fail,
    one_line_errors,
    raise_if_interrupted,
)


def _format(value: float, digits: int = 3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}g}"


def _parameter(value) -> str:
    """A scanned parameter's value as written (0.15, not the 0.15000000000000002 of a
    ``{start, stop, num}`` range's arithmetic)."""
    return f"{value:.12g}" if isinstance(value, float) else str(value)


def _horizon(summary: dict, phrase: str) -> tuple[str, bool]:
    """The title's horizon (``phrase`` formatting its value), or "horizon per point" where
    the points' horizons differ (run.dt or run.steps scanned): then the table has a column."""
    horizons = {point["horizon"] for point in summary["points"]
                if math.isfinite(point.get("horizon", math.nan))}
    if len(horizons) > 1:
        return "horizon per point", True
    return phrase.format(summary["horizon"]), False


def _with_error(mean: float, error: float) -> str:
    """``mean ± error``: the error to two significant digits and the mean to the same decimal
    place (``0.979 ± 0.014``, ``420 ± 110``), the convention of a measured value; far from 1
    (below 1e-7 or above 1e7) in exponent form; without a finite error the mean to five
    digits."""
    if mean is None or not math.isfinite(mean):
        return "-"
    if error is None or not math.isfinite(error) or error <= 0:
        return f"{_format(mean, 5)} ± -"
    error = float(f"{error:.2g}")  # 0.0999 is 0.10: the mean to 0.01
    place = math.floor(math.log10(error)) - 1  # the decimal place of the error's second digit
    if -7 <= place and abs(mean) < 1e7:
        decimals = max(0, -place)
        return f"{round(mean, -place):.{decimals}f} ± {error:.{decimals}f}"
    magnitude = math.floor(math.log10(abs(mean))) if mean else place + 1
    digits = max(1, magnitude - place + 1)
    return f"{mean:.{digits - 1}e} ± {error:.1e}"


def _thermal_lines(summary: dict) -> list[str]:
    """The table of a thermostatted sweep: per point, the averages over its samples with their
    standard errors."""
    from rich import box
    from rich.table import Table

    # no vertical rules: the columns of "mean ± error" take less room
    horizon, per_point = _horizon(summary, "{:.6g} time units")
    table = Table(box=box.SIMPLE_HEAD,
                  title=f"{summary['ensemble']} sweep: {summary['samples']} samples per point, "
                        f"{horizon}, averages after {summary['equilibration']} steps")
    names = list(summary["points"][0]["parameters"]) if summary["points"] else []
    shown = {"horizon": "horizon"} if per_point else {}
    shown |= {"mean_total_energy": "<E>", "mean_translational_temperature": "<T_tr>",
             "mean_internal_temperature": "<T_int>", "mean_pressure": "<P>",
             "mean_volume": "<V>", "heat_capacity": "C"}
    if summary["ensemble"] == "NPT":
        # how far var(V) (hence kappa_T and C) can be trusted: the moves' length against the
        # volume's relaxation time, and with tested moves the fraction rejected
        shown |= {"compressibility": "kappa_T", "move_length": "move"}
        if any(math.isfinite(point["rejected_fraction"]) for point in summary["points"]):
            shown["rejected_fraction"] = "rejected"
    for name in [*names, "sampled", "failed", *shown.values()]:
        table.add_column(name, justify="right", no_wrap=True)
    def cell(point, key):
        if key == "horizon":
            return _format(point[key], 6)
        if key == "move_length" and point[key] < 0:
            # a negative bulk modulus under a move (docs/pressure.md): the box is mechanically
            # unstable there, and a move has no relaxation time to be measured against
            return "unstable (K < 0)"
        return _with_error(point[key], point[key + "_error"])

    for point in summary["points"]:
        table.add_row(*(_parameter(point["parameters"][k]) for k in names), str(point["sampled"]),
                      str(point["failed"]), *(cell(point, k) for k in shown))
    return _rendered(table, summary, f"{summary['total_samples'] - summary['failed']} samples "
                                     f"({summary['failed']} failed)")


def _rendered(table, summary: dict, totals: str) -> list[str]:
    """The table as text, the totals line with the time and the cluster, the failures."""
    from rich.console import Console

    # wide enough for the table's own width (no value broken over two lines); a terminal
    # narrower than the table wraps whole lines
    console = Console(width=400, record=True, file=io.StringIO())
    console.print(table)
    lines = [line.rstrip() for line in console.export_text().rstrip("\n").splitlines()]
    lines.append(f"{totals}, {summary['wall_seconds']:.1f} s on {summary['workers']} worker(s) "
                 f"({summary['scheduler']})")
    for point in summary["points"]:
        for reason, count in point["failures"].items():
            lines.append(f"point {point['index']}: {count} failed: {reason}")
    return lines


def summary_lines(summary: dict) -> list[str]:
    """A plain-text table of the per-point summaries (used when rich is not a terminal)."""
    from rich.table import Table

    if "ensemble" in summary:
        return _thermal_lines(summary)

    horizon, per_point = _horizon(summary, "horizon {:.6g}")
    table = Table(title=f"sweep: {summary['samples']} samples per point, {horizon}, bound "
                        f"{summary['bound']:.6g}")
    names = list(summary["points"][0]["parameters"]) if summary["points"] else []
    for name in [*names, *(["horizon"] if per_point else []), "bounded", "unbounded", "failed",
                 "fraction bounded", "|dE/E| median", "max rel. volume", "det phi range"]:
        table.add_column(name, justify="right")
    for point in summary["points"]:
        fraction = _with_error(point["fraction_bounded"], point["fraction_bounded_error"])
        table.add_row(
            *(_parameter(point["parameters"][k]) for k in names),
            *([_format(point["horizon"], 6)] if per_point else []),
            str(point["bounded"]), str(point["unbounded"]), str(point["failed"]), fraction,
            _format(point["energy_error_median"], 2), _format(point["max_relative_volume"]),
            f"{_format(point['min_det'])} .. {_format(point['max_det'])}")
    overall = _with_error(summary["fraction_bounded"], summary["fraction_bounded_error"])
    return _rendered(table, summary,
                     f"fraction bounded (all points): {overall} over "
                     f"{summary['total_samples'] - summary['failed']} classified samples "
                     f"({summary['failed']} failed)")


def exit_code(summary: dict) -> int:
    """The exit status of a sweep that ran: 0, with failed samples among its results (README:
    a failed sample is recorded, not fatal), but :data:`~affinebody.cli.common.EXIT_STOPPED`
    (3) when every sample failed: nothing was measured."""
    total = summary["total_samples"]
    return EXIT_STOPPED if total and summary["failed"] == total else 0


def _all_failed(summary: dict, folder: Path) -> str:
    """The one line of a sweep whose every sample failed: how many, the commonest reason."""
    reasons = Counter()
    for point in summary["points"]:
        reasons.update(point["failures"])
    reason, count = reasons.most_common(1)[0] if reasons else ("unknown", summary["failed"])
    total = summary["total_samples"]
    return (f"error: all {total} samples of the sweep failed ({reason}: {count} of {total}); "
            f"the results are in {folder}")


def _progress_bar(enabled: bool):
    from rich.console import Console

    console = Console(stderr=True)
    if not enabled or not console.is_terminal:
        return contextlib.nullcontext(), None
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("samples"), TimeElapsedColumn(), console=console)
    task = {}

    def update(done: int, total: int) -> None:
        if "id" not in task:
            task["id"] = bar.add_task("sweep", total=total)
        bar.update(task["id"], completed=done)

    return bar, update


@click.command("sweep")
@click.argument("config_file", metavar="CONFIG.toml", type=click.Path(dir_okay=False))
@click.option("--samples", type=int, default=None, help="Samples per point (overrides "
              "sweep.samples).")
@click.option("--seed", type=int, default=None, help="Random seed (overrides sweep.seed).")
@click.option("--scheduler", metavar="ADDRESS", default=None,
              help="Dask scheduler to use, e.g. tcp://host:8786 (default: a local cluster).")
@click.option("--workers", type=int, default=None,
              help="Processes of the local cluster (default: all cores; 0: no Dask).")
@click.option("-o", "--output-dir", "output_dir", type=click.Path(file_okay=False), default=None,
              help="Folder for task files, samples.csv, summary.json (default: CONFIG_sweep).")
@click.option("--json", "as_json", is_flag=True,
              help="Print the summary as one JSON object on stdout.")
@one_line_errors
def sweep(config_file, samples, seed, scheduler, workers, output_dir, as_json):
    """Run an ensemble / parameter sweep of CONFIG.toml ([sweep] table) on Dask."""
    from affinebody._host import keep_freed_memory
    from affinebody.config import load_config
    from affinebody.sweep import run_sweep

    enable_x64()
    keep_freed_memory()  # samples run here too (without workers)
    config = load_config(config_file)
    folder = Path(output_dir) if output_dir else Path(config_file).with_name(
        Path(config_file).stem + "_sweep")
    bar, update = _progress_bar(True)

    def progress(done: int, total: int) -> None:
        raise_if_interrupted()  # the first Ctrl-C stops the sweep
        if update is not None:
            update(done, total)
    try:
        with bar:
            result = run_sweep(config, samples=samples, seed=seed, scheduler=scheduler,
                               workers=workers, output=folder, progress=progress,
                               keep_draws=False,  # the task files hold them
                               refuse_bad_points=True)  # before any sample runs, exit 1
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"the task files written so far are kept in "
                                f"{folder / 'tasks'}") from None
    if as_json:
        click.echo(json_text(result.summary))
    else:
        for line in summary_lines(result.summary):
            click.echo(line)
        click.echo(f"results: {folder}")
    if exit_code(result.summary):
        fail(_all_failed(result.summary, folder), exit_code(result.summary))


__all__ = [
    "exit_code", "summary_lines", "sweep"
]
