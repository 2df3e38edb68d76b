"""``affinebody transitions`` and ``affinebody evolve``: transition strengths between the levels
of a quantum affine body and the time evolution of a wave packet (docs/quantum-transitions.md).

``affinebody transitions CONFIG.toml --operator EXPR [--levels K] [--from I] [--json]``: the
reduced strengths B(I -> F) = (1/d_I) sum |<f|O|i>|^2 of the operator EXPR (in q1..qn, Q1..Qn,
trG, K1..Kn, det, and the components phi11.., G11.., C11..: any smooth expression, projected
numerically on the angles where it is not a polynomial in the components) from level I
(default 0; levels numbered as the ``states`` of ``affinebody spectrum --json``, the converged
levels ascending, the ``level`` column of its table; a level of multiplicity m holds m
states, which ``density --state`` numbers, the table's ``states`` column) to each of the levels
computed; with --json one object
``{"transitions": [{"initial", "final", "E_initial", "E_final", "strength", "sector_final",
"sector_initial", "allowed", "states_initial", "states_final"}, ...], "operator",
"selection_rule", "energy_weighted_sum", "projection_error", ...}``.

``affinebody evolve CONFIG.toml --at X1,X2 [--momentum P1,P2] [--width W] [--time T]
[--steps N] [--json] [--plot FILE.png]`` (n = 2; n = 3 with --at X1,X2,X3 and --momentum
P1,P2,P3, quantum.evolution3): a Gaussian packet of the sector spin = vorticity = 0 centred
at X (the signed singular values Q for d'Alembert, q = ln Q for the affine models; n = 3 the
Gaussian symmetrised over the Weyl group) with mean momentum P conjugate to X, propagated
exactly by its expansion in
eigenstates; prints the means and spreads of the invariants, the survival probability
|<psi(0)|psi(t)>|^2, the norm and the energy at N + 1 times in [0, T]. Instead of --at,
``--phi A11,A12,A21,A22 [--pi P11,P12,P21,P22]`` (every model; the affine ones on GL+(2), the
Gaussian times det phi): a Gaussian in phi around a classical (phi, pi) with any spin and
vorticity, a superposition of every sector it populates.
"""

from __future__ import annotations

import math
import sys

import click
import numpy as np

from affinebody._json import json_text
from affinebody.cli.common import check_output_file, enable_x64, one_line_errors, output_console


def _numbers(text: str, flag: str, count: int) -> tuple[float, ...]:
    """``count`` finite numbers separated by commas, or a one-line error naming ``flag``."""
    word = {2: "two", 3: "three"}[count]
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"{flag} takes {word} numbers separated by commas (got "
                         f"{text!r})") from None
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{flag} takes {word} finite numbers separated by commas (got "
                         f"{text!r})")
    _within_magnitudes(values, flag)
    return values


def _within_magnitudes(values, flag: str) -> None:
    """A flag's numbers within what the solvers handle (a momentum of 1e308 made every
    result nan): :func:`affinebody.quantum.config.check_magnitude`."""
    from affinebody.quantum.config import check_magnitude

    largest = max(abs(v) for v in values)
    check_magnitude(largest, f"{flag}: {largest:g}", small_too=False)


@click.command("transitions")
@click.argument("config", type=click.Path(exists=True, dir_okay=False))
@click.option("--operator", "operator", required=True,
              help="expression in q1..qn, Q1..Qn, trG, K1..Kn, det and phi11.., G11.., C11.. "
                   "(any smooth expression)")
@click.option("--levels", "levels", type=int, default=None, help="number of states K")
@click.option("--from", "initial", type=int, default=0,
              help="initial level (0: the ground): the 'level' column of spectrum's table, "
                   "not a state number # of density --state")
@click.option("--json", "as_json", is_flag=True, help="print one JSON object")
@one_line_errors
def transitions(config: str, operator: str, levels: int | None, initial: int,
                as_json: bool) -> None:
    """Reduced transition strengths of an operator from one level of CONFIG to every level."""
    enable_x64()
    from affinebody.quantum import config as qconfig
    from affinebody.quantum import transitions as tr
    from affinebody.quantum.cli import solve_config

    cfg = qconfig.load(config)
    try:  # a bad expression is refused before solving
        op = tr.Operator(operator, cfg.system.n)
    except ValueError as err:
        raise ValueError(str(err).removeprefix("config error: ")) from None
    count = cfg.quantum.levels if levels is None else levels
    if count < 1:
        raise ValueError(f"--levels must be >= 1 (got {count})")
    if count > tr.MAX_STATES:
        raise ValueError(f"--levels {count}: transitions are computed between at most "
                               f"{tr.MAX_STATES} states (every pair of levels is integrated): "
                               f"ask for fewer")
    if initial < 0:
        raise ValueError(f"--from must be >= 0 (got {initial})")
    result, count = solve_config(config, levels)
    table = tr.transitions(result, op, initial)
    warnings = list(result.warnings)
    if not result.complete(count):
        warnings.append(f"the levels are not certified to be the {count} lowest: "
                        f"{result.certificate}")
    if as_json:
        click.echo(json_text({
            # with the state numbers of each level, as density --state numbers states
            "transitions": [{**t.as_dict(),
                             "states_initial": list(result.state_range(t.initial)),
                             "states_final": list(result.state_range(t.final))}
                            for t in table.transitions],
            "operator": table.operator,
            "selection_rule": table.selection_rule,
            "energy_weighted_sum": tr.trk_sum(table),
            "orthonormality_error": table.orthonormality_error,
            "projection_error": table.projection_error,
            "model": result.model, "n": result.n, "levels": count,
            "warnings": warnings,
        }))
        return
    from rich.table import Table

    from affinebody.quantum.levels import states_text

    out = Table(title=f"|<F|{operator}|{initial}>|^2 summed over the states of F, averaged over "
                      f"those of level {initial} (states "
                      f"{states_text(result.state_range(initial))}, E = "
                      f"{result.levels[initial].energy:.10g}; {result.model}, n = {result.n})")
    for col in ("F", "states", "E_F", "E_F - E_I", "strength", "sectors of F"):
        out.add_column(col, justify="right")
    for t in table.transitions:
        sectors = " ".join(f"({s.spin},{s.vorticity})" for s in t.sector_final)
        strength = f"{t.strength:.6e}" if t.allowed else "0 (forbidden)"
        out.add_row(str(t.final), states_text(result.state_range(t.final)), f"{t.E_final:.10g}",
                    f"{t.E_final - t.E_initial:.6g}", strength, sectors)
    console = output_console()
    console.print(out)
    console.print(f"selection rule: {table.selection_rule}")
    console.print(f"energy-weighted sum over these levels: {tr.trk_sum(table):.10g}")
    if table.projection_error is not None:
        console.print(f"angular projection: the elements of two grids agree to "
                      f"{table.projection_error:.1e} of the largest")
    for text in warnings:
        console.print(f"[bold red]warning:[/] {text}")


@click.command("evolve")
@click.argument("config", type=click.Path(exists=True, dir_okay=False))
@click.option("--at", "centre", default=None,
              help="packet centre X1,X2 (n = 3: X1,X2,X3): Q (d'Alembert) or q = ln Q (affine "
                   "models), a packet of the sector (0, 0)")
@click.option("--phi", "phi", default=None,
              help="a packet around the matrix phi = A11,A12,A21,A22, every sector it populates "
                   "(instead of --at)")
@click.option("--pi", "pi", default="0,0,0,0", help="with --phi: mean momentum P11,P12,P21,P22")
@click.option("--momentum", "momentum", default=None,
              help="mean momentum P1,P2 (n = 3: P1,P2,P3) conjugate to X (default 0)")
@click.option("--width", "width", type=float, default=None,
              help="standard deviation of the packet's probability density in each variable "
                   "(default sqrt(hbar/2))")
@click.option("--time", "duration", type=float, default=10.0, help="final time T")
@click.option("--steps", "steps", type=int, default=200, help="number of intervals in [0, T]")
@click.option("--json", "as_json", is_flag=True, help="print one JSON object")
@click.option("--plot", "plot", type=click.Path(dir_okay=False), default=None,
              help="write a PNG of the means, spreads and survival probability")
@one_line_errors
def evolve(config: str, centre: str | None, phi: str | None, pi: str, momentum: str | None,
           width: float | None, duration: float, steps: int, as_json: bool,
           plot: str | None) -> None:
    """Time evolution of a wave packet of the body of CONFIG (n = 2, 3)."""
    enable_x64()
    from contextlib import nullcontext

    from affinebody.quantum import config as qconfig
    from affinebody.quantum import evolution as ev
    from affinebody.quantum.cli import finite_hamiltonian

    if plot is not None:
        check_output_file(plot, "--plot", image=True)
    cfg = qconfig.load(config)
    n = cfg.system.n
    if (centre is None) == (phi is None):
        raise ValueError("evolve: give the packet's centre by exactly one of --at X1,X2 (sector "
                         "(0, 0)) and --phi A11,A12,A21,A22")
    if phi is not None:
        if n != 2:
            raise ValueError(f"evolve --phi is for n = 2 (got system.n = {n}); for n = 3 give "
                             f"--at Q1,Q2,Q3 (a packet of the sector (0, 0))")
        with finite_hamiltonian(cfg.quantum.potential):
            return _evolve_matrix(cfg, phi, pi, width, duration, steps, as_json, plot)
    X0 = _numbers(centre, "--at", n)
    P0 = _numbers(",".join(["0"] * n) if momentum is None else momentum, "--momentum", n)
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"--time must be > 0 (got {duration})")
    if not 1 <= steps <= ev.MAX_STEPS:
        raise ValueError(f"--steps must be between 1 and {ev.MAX_STEPS} (got {steps})")
    kwargs = qconfig.solver_arguments(cfg)
    model, hbar, settings = kwargs["model"], kwargs["hbar"], kwargs["settings"]
    constants = dict(inertia=kwargs.get("inertia", 1.0), I=kwargs.get("I", 1.0),
                     A=kwargs.get("A", 0.0), B=kwargs.get("B", 0.0))
    w = math.sqrt(hbar / 2) if width is None else width
    times = np.linspace(0.0, duration, steps + 1)
    if n == 2:
        ev.check_work(settings.basis_size, steps + 1)
        packet = ev.Packet(X0, P0, w)
        ev.check_packet(model, packet)
        functions = settings.basis_size**2
    else:
        from affinebody.quantum import evolution3 as ev3

        ev3.check_degree(model, settings.basis_size, steps + 1)
        ev3.check_packet3(model, X0, w)
        functions = ev3.sector_states(model, settings.basis_size)
    status = nullcontext(None)
    if sys.stderr.isatty():
        from rich.console import Console

        status = Console(stderr=True).status(
            f"solving the sector (0, 0) with {functions} functions ...")
    with status, finite_hamiltonian(cfg.quantum.potential):
        if n == 2:
            spectrum = ev.sector_spectrum(model, kwargs["potential"], hbar, settings=settings,
                                          **constants)
            result = ev.evolve(spectrum, packet, times, hbar)
        else:
            reach = float(np.linalg.norm(X0)) + 10 * w if model == "dalembert" else 0.0
            sector = ev3.scalar_sector3(model, kwargs["potential"], hbar, settings=settings,
                                        reach=reach, **constants)
            result = ev3.evolve3(sector, X0, P0, w, times, hbar)
    ev.check_phases(result, hbar)
    if plot is not None:
        _plot(result, plot, model)
    if as_json:
        payload = result.as_dict()
        payload.update(model=model, n=n, sector={"spin": 0, "vorticity": 0},
                       hbar=hbar, centre=list(X0), momentum=list(P0), width=w,
                       lines=ev.spectrum_lines(result))
        click.echo(json_text(payload))
        return
    from rich.console import Console
    from rich.table import Table

    names = list(result.mean)
    table = Table(title=f"packet at {X0}, momentum {P0}, width {w:.4g} "
                        f"({model}, n = {n}, hbar = {hbar}, {len(result.energies)} states, "
                        f"captured {result.captured:.10f})")
    for col in ["t", *(f"<{k}> +- spread" for k in names), "survival"]:
        table.add_column(col, justify="right")
    for k in range(0, len(times), max(1, len(times) // 20)):
        table.add_row(f"{times[k]:.4g}",
                      *(f"{result.mean[n][k]:.6g} +- {result.spread[n][k]:.3g}" for n in names),
                      f"{result.survival[k]:.6f}")
    console = output_console()
    console.print(table)
    console.print(f"norm {result.norm[0]:.15f} (spread over t {np.ptp(result.norm):.1e}), "
                  f"energy {result.energy[0]:.12g} (spread {np.ptp(result.energy):.1e}), "
                  f"eigenvalue error estimate weighted by the packet {result.energy_error:.1e}")


def _matrix(text: str, flag: str) -> np.ndarray:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{flag} takes four finite numbers A11,A12,A21,A22 (got {text!r})")
    _within_magnitudes(values, flag)
    return np.array(values).reshape(2, 2)


def _evolve_matrix(cfg, phi: str, pi: str, width: float | None, duration: float, steps: int,
                   as_json: bool, plot: str | None) -> None:
    """evolve --phi: a packet around a classical (phi, pi), every sector it populates
    (quantum.evolution.evolve_matrix_packet; the affine models on GL+(2))."""
    from contextlib import nullcontext

    from affinebody.quantum import config as qconfig
    from affinebody.quantum import evolution as ev

    phi0, pi0 = _matrix(phi, "--phi"), _matrix(pi, "--pi")
    kwargs = qconfig.solver_arguments(cfg)
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"--time must be > 0 (got {duration})")
    if not 1 <= steps <= ev.MAX_STEPS:
        raise ValueError(f"--steps must be between 1 and {ev.MAX_STEPS} (got {steps})")
    hbar, settings = kwargs["hbar"], kwargs["settings"]
    ev.check_work(settings.basis_size, steps + 1)
    packet = ev.MatrixPacket(phi0.tolist(), pi0.tolist(),
                             math.sqrt(hbar / 2) if width is None else width)
    ev.check_matrix_packet(kwargs["model"], packet)
    times = np.linspace(0.0, duration, steps + 1)
    status = nullcontext(None)
    if sys.stderr.isatty():
        from rich.console import Console

        status = Console(stderr=True).status("solving the sectors of the packet ...")
    with status as live:
        progress = None if live is None else (lambda text: live.update(f"solving {text} ..."))
        result = ev.evolve_matrix_packet(
            kwargs["potential"], hbar, kwargs.get("inertia", 1.0), settings, packet, times,
            progress, model=kwargs["model"], I=kwargs.get("I", 1.0), A=kwargs.get("A", 0.0),
            B=kwargs.get("B", 0.0))
    ev.check_phases(result, hbar)
    if plot is not None:
        _plot(result, plot, kwargs["model"])
    payload = result.as_dict()
    payload.update(model=kwargs["model"], n=2, hbar=hbar, phi=phi0.tolist(), pi=pi0.tolist(),
                   width=packet.width, lines=ev.spectrum_lines(result))
    if as_json:
        click.echo(json_text(payload))
        return
    click.echo(f"packet around phi = {phi0.tolist()}, pi = {pi0.tolist()}, width "
               f"{packet.width:.4g}: {len(result.energies)} states, captured "
               f"{result.captured:.10f}")
    for k in range(0, len(times), max(1, len(times) // 20)):
        click.echo(f"t = {times[k]:.4g}  " + "  ".join(
            f"<{n}> = {result.mean[n][k]:.6g} +- {result.spread[n][k]:.3g}" for n in result.mean)
            + f"  survival {result.survival[k]:.6f}")
    click.echo(f"norm spread {np.ptp(result.norm):.1e}, energy {result.energy[0]:.12g} (spread "
               f"{np.ptp(result.energy):.1e})")


def _plot(result, path: str, model: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = result.times
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    variables = list(result.mean)[:-2]  # the model's variables, then det and trG
    for ax, names in ((axes[0], variables), (axes[1], list(result.mean)[-2:])):
        for name in names:
            m, s = result.mean[name], result.spread[name]
            ax.plot(t, m, label=f"<{name}>")
            ax.fill_between(t, m - s, m + s, alpha=0.25)
        ax.set_xlabel("t")
        ax.legend()
    axes[2].plot(t, result.survival)
    axes[2].set_xlabel("t")
    axes[2].set_ylabel("|<psi(0)|psi(t)>|^2")
    fig.suptitle(f"wave packet of the {model} body")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["transitions", "evolve"]
