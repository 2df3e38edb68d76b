"""``affinebody spectrum`` and ``affinebody density``: click commands for the main group.

``affinebody spectrum CONFIG.toml [--levels K] [--json]``: the lowest K states; with --json one
JSON object with ``energies`` (the K lowest states ascending, each repeated by its
multiplicity; ``null`` where the state is an unconverged candidate: it keeps its place and no
higher level replaces it), ``unknown_states`` (the indices of those nulls), ``complete`` (true
only when every one of the K states is converged and the sector search is certified to hold the
K lowest), ``certified`` and ``certificate`` (the stopping proof, or why the list is
conditional: docs/theory/two-polar.md, "Lower bounds of a sector"), ``states`` (the converged
levels: ``energy``, ``multiplicity``, ``spin``, ``vorticity``, ``parity``, all ``sectors``,
``error``, ``converged``), ``unconverged`` (the candidates among the K states whose estimate
exceeds the tolerance: pseudo-levels of a continuous spectrum or an insufficient basis, with
their estimate and error; never listed as levels), ``sectors`` ("all";
for n = 3 also "scalar", "spin1", "scalar+spin1"), ``bounded_below`` (false for af-af, whose
sector sum is unbounded below) and ``warnings`` (af-af; n = 3 spectra that hold only some
sectors; a sector search stopped by max_spin), also printed under the table.
``affinebody density CONFIG.toml --state k -o DIR [--json] [--orientation]`` (or
``--superpose 0:1,8:0.5j`` or ``--temperature T`` instead of ``--state``: the orientation
densities only, orientation.json / .npz / .png; n = 3: rotation angles and principal-axis
directions of the state, superposition or thermal mixture, quantum.orientations3, and with
--g-components G11,G12 the densities of those components of G, quantum.green3): the
exact marginal densities of the invariants (Q_a or q_a, det phi, Tr G) and of the orientations
for the k-th state (0-based), each with a quadrature error estimate, written as densities.npz,
densities.json and one PNG per density; with --json the same JSON object (arrays included) on
stdout, else a table. Densities whose error exceeds quantum.density_tolerance x their peak
or that are not finite (those of orientation.json with --orientation too) are flagged
(``converged: false``, a one-line warning each) and the command exits with status 3.
"""

from __future__ import annotations

import math
import sys

import click

from affinebody._json import json_text
from affinebody.cli.common import (
    EXIT_STOPPED,
    enable_x64,
    not_finite_as,
    one_line_errors,
    output_console,
)


def finite_hamiltonian(potential: str):
    """A Hamiltonian that LAPACK refuses as not finite, said as the potential's fault (it is
    infinite, nan or beyond float64 at a quadrature point of the basis):
    :func:`affinebody.cli.common.not_finite_as`."""
    return not_finite_as(f"quantum.potential = {potential!r} is not finite in float64 at some "
                         f"quadrature point of the basis",
                         "bound it (log(det) or 1/det where det -> 0, exp of a growing "
                         "invariant, a huge coefficient), or set quantum.scale (n = 2 affine "
                         "models: also scale_sigma and centre) to keep the basis where it is "
                         "finite")


def solve_config(config_path: str, levels: int | None):
    """Solve CONFIG; on a terminal, a status line on stderr names the sector being solved (an
    n = 3 spectrum over every sector can take minutes)."""
    from contextlib import nullcontext

    from affinebody.quantum import config as qconfig
    from affinebody.quantum.spectra import solve

    cfg = qconfig.load(config_path)
    kwargs = qconfig.solver_arguments(cfg)
    if levels is not None:
        if levels < 1:
            raise ValueError(f"--levels must be >= 1 (got {levels})")
        kwargs["levels"] = levels
    status = nullcontext(None)
    if sys.stderr.isatty():
        from rich.console import Console

        status = Console(stderr=True).status("solving ...")
    with status as live, finite_hamiltonian(cfg.quantum.potential):
        if live is not None:
            kwargs["progress"] = lambda text: live.update(f"solving {text} ...")
        return solve(**kwargs), kwargs["levels"]


def solve_thermal(config_path: str, temperature: float):
    """Solve CONFIG for its thermal mixture at ``temperature``: quantum.levels states, then
    requests of at least twice as many and more than it has (a level is solved whole; up to
    :data:`~affinebody.quantum.densities.MAX_THERMAL_STATES`) until the last converged
    state's Boltzmann factor is below the densities' tolerance, or until a larger solve
    converges no more states. A mixture still truncated is warned of where its densities are
    computed (:func:`~affinebody.quantum.densities.truncation_warning`)."""
    from affinebody.quantum.densities import G_TOLERANCE, MAX_THERMAL_STATES, boltzmann_factors

    result, count = solve_config(config_path, None)
    converged = 0
    while True:
        energies = [e for e in result.energies() if not math.isnan(e)]
        if (not energies or len(energies) <= converged or count >= MAX_THERMAL_STATES
                or boltzmann_factors(energies, temperature)[-1] <= G_TOLERANCE):
            return result
        # a level is solved whole, so the states may already exceed twice the request
        converged = len(energies)
        count = min(max(2 * count, len(result.energies()) + 1), MAX_THERMAL_STATES)
        result, _ = solve_config(config_path, count)


@click.command("spectrum")
@click.argument("config", type=click.Path(exists=True, dir_okay=False))
@click.option("--levels", "levels", type=int, default=None, help="number of states K")
@click.option("--json", "as_json", is_flag=True, help="print one JSON object")
@one_line_errors
def spectrum(config: str, levels: int | None, as_json: bool) -> None:
    """Lowest energy levels of the quantum affine body described by CONFIG."""
    enable_x64()
    result, count = solve_config(config, levels)
    energies = result.energies(count)
    unknown = result.unknown_states(count)
    complete = result.complete(count)
    stopped = not energies or len(unknown) == len(energies)  # exit 3 after the output
    if stopped:
        result.warnings.append("no level converged: raise quantum.basis_size, or check that the "
                               "potential binds (a continuous spectrum has no levels)")
    if as_json:
        payload = {
            "energies": [None if i in unknown else e for i, e in enumerate(energies)],
            "unknown_states": unknown,
            "complete": complete,
            "certified": result.certified,
            "certificate": result.certificate,
            "states": [lv.as_dict() for lv in result.levels],
            "unconverged": [lv.as_dict() for lv in result.unconverged],
            "sectors": result.sectors,
            "bounded_below": result.bounded_below,
            "warnings": result.warnings,
            "model": result.model,
            "n": result.n,
            "settings": result.settings,
        }
        click.echo(json_text(payload))
        if stopped:
            click.echo(f"warning: {result.warnings[-1]}", err=True)
            sys.exit(EXIT_STOPPED)
        return
    from rich.table import Table

    from affinebody.quantum.levels import states_text

    title = f"{result.model}, n = {result.n}, sectors: {result.sectors}"
    table = Table(title=title)
    for col in ("level", "#", "energy", "mult.", "spin", "vorticity", "parity", "error"):
        table.add_column(col, justify="right")
    for level, states, lv in result.numbered():
        d = lv.as_dict()
        energy = f"{lv.energy:.12g}" if lv.converged else f"unconverged (~{lv.energy:.6g})"
        table.add_row("-" if level is None else str(level), states_text(states), energy,
                      str(lv.multiplicity), str(d["spin"]), str(d["vorticity"]),
                      str(d["parity"]), f"{lv.error:.1e}")
    console = output_console()
    console.print(table)
    console.print("level: the number of transitions --from and F (the index in --json's "
                  "'states'); #: the states of the level, as density --state and --superpose "
                  "number them")
    if len(energies) < count:
        console.print(f"only {len(energies)} of {count} states found")
    if unknown:
        console.print(f"only {len(energies) - len(unknown)} of {count} states converged: states "
                      f"{unknown} are unconverged candidates (their energies are estimates)")
    console.print(("the list is complete: " if complete else "the list is NOT certified "
                   "complete: ") + result.certificate)
    for text in result.warnings:
        console.print(f"[bold red]warning:[/] {text}")
    if result.unconverged:
        shown = result.unconverged[:count]
        extra = Table(title=f"unconverged candidates: error estimate above quantum.tolerance, not "
                            f"levels (continuous spectrum or too small a basis); lowest "
                            f"{len(shown)} of {len(result.unconverged)}")
        for col in ("energy", "mult.", "spin", "vorticity", "error estimate"):
            extra.add_column(col, justify="right")
        for lv in shown:
            d = lv.as_dict()
            extra.add_row(f"{lv.energy:.9g}", str(lv.multiplicity), str(d["spin"]),
                          str(d["vorticity"]), f"{lv.error:.1e}")
        console.print(extra)
        console.print("to converge them: raise quantum.basis_size (n = 2: up to 80, n = 3: up "
                      "to 16; n = 3 d'Alembert also quantum.radial_size, up to 60), or accept "
                      "them with a larger quantum.tolerance")
    if stopped:
        sys.exit(EXIT_STOPPED)


@click.command("density")
@click.argument("config", type=click.Path(exists=True, dir_okay=False))
@click.option("--state", "state", type=int, default=None, help="state index (0-based)")
@click.option("-o", "--output", "output", type=click.Path(file_okay=False), required=True)
@click.option("--json", "as_json", is_flag=True, help="print the JSON object (with the arrays)")
@click.option("--orientation", is_flag=True,
              help="also the densities of the orientations of L, R (n = 2: their angles and "
                   "G11, G22, G12; n = 3: rotation angles and principal-axis directions)")
@click.option("--superpose", default=None,
              help="orientation densities of a superposition, e.g. 0:1,8:0.5j")
@click.option("--temperature", type=float, default=None,
              help="orientation densities of the thermal mixture at T (k_B = 1)")
@click.option("--g-components", "g_components", default=None,
              help="n = 3: also the densities of these components of G, e.g. G11,G33,G12 "
                   "(about a second per point each)")
@one_line_errors
def density(config: str, state: int | None, output: str, as_json: bool, orientation: bool,
            superpose: str | None, temperature: float | None,
            g_components: str | None) -> None:
    """Exact marginal densities of q (or Q), det phi, Tr G and orientations for one state;
    with --orientation, --superpose or --temperature the densities of the orientations of the
    principal axes of C and G and of the components of G (orientation.json, .npz, .png)."""
    enable_x64()
    from affinebody.quantum import config as qconfig
    from affinebody.quantum.density_files import (
        parse_superposition,
        write_densities,
        write_orientation,
    )
    from affinebody.quantum.spectra import MAX_LEVELS

    if sum(v is not None for v in (state, superpose, temperature)) != 1:
        raise ValueError("give exactly one of --state, --superpose and --temperature")
    green = () if g_components is None else tuple(
        name.strip() for name in g_components.split(",") if name.strip())
    if green and state is not None and not orientation:
        raise ValueError("--g-components needs --orientation, --superpose or --temperature")
    if temperature is not None and not (math.isfinite(temperature) and temperature > 0):
        raise ValueError(f"--temperature must be a finite kT > 0 (got {temperature})")
    if superpose is not None or temperature is not None:
        superposition = None if superpose is None else parse_superposition(superpose)
        if superposition is not None and not 0 <= min(superposition) <= max(
                superposition) < MAX_LEVELS:
            raise ValueError(f"--superpose: state indices must be from 0 to {MAX_LEVELS - 1} "
                             f"(got {sorted(superposition)})")
        qc = qconfig.load(config).quantum
        if superposition is None:
            result = solve_thermal(config, temperature)
        else:
            result, _ = solve_config(config, max(superposition) + 1)
        payload = write_orientation(result, output, superposition=superposition,
                                    temperature=temperature, points=qc.density_points,
                                    green=green)
        mixed = ("" if superposition is not None else
                 f" of {len(result.energies()) - len(result.unknown_states())} states")
        click.echo(json_text(payload) if as_json else
                   f"wrote {output}/orientation.json, orientation.npz, orientation.png "
                   f"({payload['kind']}{mixed})")
        for text in payload["warnings"]:
            click.echo(f"warning: {text}", err=True)
        if payload["warnings"]:
            sys.exit(EXIT_STOPPED)
        return
    if not 0 <= state < MAX_LEVELS:
        raise ValueError(f"--state must be from 0 to {MAX_LEVELS - 1}, an index of the "
                         f"{MAX_LEVELS} lowest states the solver finds (got {state})")
    qc = qconfig.load(config).quantum
    result, _ = solve_config(config, state + 1)
    stopped = False  # an orientation or G density unconverged or not finite: exit 3 below
    if orientation:
        extra = write_orientation(result, output, state=state, points=qc.density_points,
                                  green=green)
        for text in extra["warnings"]:
            click.echo(f"warning: {text}", err=True)
        stopped = bool(extra["warnings"])
    payload = write_densities(result, state, output, qc.density_points, qc.density_tolerance)
    why = result.incomplete_because(state + 1)
    if why is not None:  # a caveat on the index, not on the densities
        click.echo(f"warning: state {state} is indexed in a list of states 0..{state} that is "
                   f"not known to be complete: {why}", err=True)
    if as_json:
        click.echo(json_text(payload))
    else:
        from rich.table import Table

        level = next(number for number, states, _ in result.numbered() if state in states)
        table = Table(title=f"state {state} (level {level}: transitions --from {level}), "
                            f"E = {payload['energy']:.12g}, variables "
                            f"{payload['variables']} ({output})")
        for col in ("density", "from", "to", "peak", "error", "integral"):
            table.add_column(col, justify="right")
        for name, d in payload["densities"].items():
            table.add_row(name, f"{d['x'][0]:.4g}", f"{d['x'][-1]:.4g}",
                          f"{max(d['density']):.6g}", f"{d['error']:.1e}",
                          f"{d['integral']:.12f}")
        console = output_console()
        console.print(table)
        for text in payload["warnings"]:
            console.print(f"[bold red]warning:[/] {text}")
    if payload["warnings"]:
        if as_json:
            for text in payload["warnings"]:
                click.echo(f"warning: {text}", err=True)
        sys.exit(EXIT_STOPPED)  # densities above the tolerance: written, flagged
    if stopped:
        sys.exit(EXIT_STOPPED)  # orientation.json's densities: written, flagged (warned above)


__all__ = ["finite_hamiltonian", "solve_config", "solve_thermal", "spectrum", "density"]
