"""The ``affinebody`` command line: one click group, one subcommand per job.

``run``, ``demo``, ``plot``, ``export``, ``validate`` (:mod:`.run`), ``sweep`` (:mod:`.sweep`),
``spectrum`` and ``density`` (:mod:`affinebody.quantum.cli`), ``phonons`` (:mod:`.phonons`)
and ``kinematics-demo``. Every
command turns JAX's float64 mode on for its own process and reports errors as one line
(:mod:`.common`).
"""

from __future__ import annotations

import click

from affinebody import __version__
from affinebody._checks import enable_x64


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="affinebody")
def main() -> None:
    """Classical and quantum mechanics of affinely-rigid bodies (Slawianowski's affine models)."""


@main.command("kinematics-demo")
def kinematics_demo() -> None:
    """Print a worked example of the kinematics of one affine body (paper §1)."""
    enable_x64()
    from affinebody.demo_kinematics import print_worked_example

    print_worked_example()


def _register_commands() -> None:
    from affinebody.cli.phonons import phonons_command
    from affinebody.cli.run import COMMANDS  # run, demo, plot, export, validate
    from affinebody.cli.sweep import sweep
    from affinebody.quantum.cli import density, spectrum

    for command in (*COMMANDS, spectrum, density, sweep, phonons_command):
        main.add_command(command)


_register_commands()

__all__ = ["main"]
