"""The ``affinebody`` command line: one click group, one subcommand per job.

``run``, ``demo``, ``plot``, ``export``, ``validate`` (:mod:`.run`), ``sweep`` (:mod:`.sweep`),
``spectrum`` and ``density`` (:mod:`affinebody.quantum.cli`), ``transitions`` and ``evolve``
(:mod:`.quantum_dynamics`), ``phonons`` (:mod:`.phonons`)
and ``kinematics-demo``. Every
command turns JAX's float64 mode on for its own process (and XLA's faster compilation,
``_xla.compile_faster``) and reports errors as one line (:mod:`.common`).
"""

from __future__ import annotations

import importlib
import sys

import click

from affinebody import __version__
from affinebody._xla import compile_faster

#: Subcommand -> "module:attribute" of its click command, imported when the command is used
#: (so that ``affinebody run`` does not import the quantum solvers, and no command module
#: is imported by importing this package: they import ``cli.common`` themselves).
COMMANDS = {
    "run": "affinebody.cli.run:run",
    "demo": "affinebody.cli.run:demo",
    "plot": "affinebody.cli.run:plot",
    "export": "affinebody.cli.run:export",
    "validate": "affinebody.cli.run:validate",
    "sweep": "affinebody.cli.sweep:sweep",
    "spectrum": "affinebody.quantum.cli:spectrum",
    "density": "affinebody.quantum.cli:density",
    "transitions": "affinebody.cli.quantum_dynamics:transitions",
    "evolve": "affinebody.cli.quantum_dynamics:evolve",
    "phonons": "affinebody.cli.phonons:phonons_command",
}

#: Subcommand -> the first sentence of its help, which ``affinebody --help`` lists without
#: importing the command (that would import JAX and every command module: seconds);
#: tests/test_cli_sim.py checks that the listing is the one click makes from the commands.
SUMMARIES = {
    "run": "Integrate the system of CONFIG.toml and write an H5MD trajectory.",
    "demo": "Run the built-in example: a small 2D crystal of affine bodies; write H5MD, PNG "
            "and XYZ.",
    "plot": "Plot energy, momentum maps, deformation invariants, temperatures, pressure and "
            "volume (NPT), and the bodies (rods for n = 1, ellipses for n = 2, ellipsoids for "
            "n = 3).",
    "export": "Export a trajectory as extended XYZ with ellipsoid shapes and orientations.",
    "validate": "Check a config file without running it.",
    "sweep": "Run an ensemble / parameter sweep of CONFIG.toml ([sweep] table) on Dask.",
    "spectrum": "Lowest energy levels of the quantum affine body described by CONFIG.",
    "density": "Exact marginal densities of q (or Q), det phi, Tr G and orientations for one "
               "state; with --orientation, --superpose or --temperature the densities of the "
               "orientations of the principal axes of C and G and of the components of G "
               "(orientation.json, .npz, .png).",
    "transitions": "Reduced transition strengths of an operator from one level of CONFIG to "
                   "every level.",
    "evolve": "Time evolution of a wave packet of the body of CONFIG (n = 2, 3).",
    "phonons": "Dispersion relations of the crystal of CONFIG_PATH's periodic box: the n "
               "acoustic and the internal (affine) branches, DOS, sound speeds and elastic "
               "constants.",
}


class _LazyGroup(click.Group):
    """A click group whose subcommands of :data:`COMMANDS` are imported on first use (and
    listed by ``--help`` from :data:`SUMMARIES`)."""

    def list_commands(self, ctx):
        return sorted({*super().list_commands(ctx), *COMMANDS})

    def format_commands(self, ctx, formatter):
        """click's listing of the subcommands, the lazy ones' from :data:`SUMMARIES` (click
        shortens them as it shortens a command's help)."""
        rows = []
        for name in self.list_commands(ctx):
            command = (click.Command(name, help=SUMMARIES[name]) if name in COMMANDS
                       else self.commands[name])
            if not command.hidden:
                rows.append((name, command))
        limit = formatter.width - 6 - max(len(name) for name, _ in rows)
        with formatter.section("Commands"):
            formatter.write_dl([(name, c.get_short_help_str(limit)) for name, c in rows])

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True,
             **extra):
        """click's main, with a usage error (a flag's value of the wrong type, an unknown
        option, a missing argument) said in one line on stderr, exit status 2, as every other
        error of the commands is (:mod:`.common`), instead of click's usage block."""
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, False, **extra)
        try:
            code = super().main(args, prog_name, complete_var, False, **extra)
        except click.UsageError as err:
            if isinstance(err, getattr(click.exceptions, "NoArgsIsHelpError", ())):
                err.show()  # no command: the help, as click shows it
                sys.exit(err.exit_code)
            where = f" (see {err.ctx.command_path} --help)" if err.ctx is not None else ""
            click.echo(f"error: {err.format_message()}{where}", err=True)
            sys.exit(err.exit_code)
        except click.ClickException as err:
            err.show()
            sys.exit(err.exit_code)
        except click.Abort:
            click.echo("Aborted!", err=True)
            sys.exit(1)
        sys.exit(code if isinstance(code, int) else 0)  # an exit code (--help: 0) or None

    def invoke(self, ctx):
        """The subcommand, exiting 141 where the reader of its output has gone
        (``affinebody ... | head``) however it printed (:func:`.common.broken_pipe_exits`)."""
        from affinebody.cli.common import broken_pipe_exits

        with broken_pipe_exits():
            return super().invoke(ctx)

    def get_command(self, ctx, name):
        if name in COMMANDS:
            module, attribute = COMMANDS[name].split(":")
            return getattr(importlib.import_module(module), attribute)
        return super().get_command(ctx, name)


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="affinebody")
def main() -> None:
    """Classical and quantum mechanics of affinely-rigid bodies (Slawianowski's affine models)."""
    compile_faster()  # before any command starts JAX's backend


@main.command("kinematics-demo")
def kinematics_demo() -> None:
    """Print a worked example of the kinematics of one affine body (paper §1)."""
    from affinebody._checks import enable_x64
    from affinebody.cli.common import output_console
    from affinebody.demo_kinematics import print_worked_example

    enable_x64()

    print_worked_example(output_console())


def entry() -> None:
    """The ``affinebody`` console script: :func:`main` as a process of its own. An
    interrupted command leaves the process at once after its message and its files are closed
    (``os._exit``), without the interpreter's finalisation: with Ctrl-C pressed while XLA
    compiled or ran a run's first chunk, that finalisation crashed in native code (exit 139
    instead of 130, in 3 of 6 tries at 7-9 s into a run)."""
    import os

    from affinebody.cli.common import EXIT_INTERRUPTED

    try:
        main()
    except SystemExit as done:
        if done.code == EXIT_INTERRUPTED:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(EXIT_INTERRUPTED)
        raise


__all__ = ["COMMANDS", "SUMMARIES", "entry", "main"]
