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

import click

from affinebody import __version__
from affinebody._checks import enable_x64
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


class _LazyGroup(click.Group):
    """A click group whose subcommands of :data:`COMMANDS` are imported on first use."""

    def list_commands(self, ctx):
        return sorted({*super().list_commands(ctx), *COMMANDS})

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
    enable_x64()
    from affinebody.demo_kinematics import print_worked_example

    print_worked_example()


__all__ = ["COMMANDS", "main"]
