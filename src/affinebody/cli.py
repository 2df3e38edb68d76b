"""The ``affinebody`` command line: one click group, one subcommand per job."""

from __future__ import annotations

import click

from affinebody import __version__


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="affinebody")
def main() -> None:
    """Classical and quantum mechanics of affinely-rigid bodies (Slawianowski's affine models)."""


def _enable_x64() -> None:
    import jax

    jax.config.update("jax_enable_x64", True)


@main.command("kinematics-demo")
def kinematics_demo() -> None:
    """Print a worked example of the kinematics of one affine body (paper §1)."""
    _enable_x64()
    from affinebody.demo_kinematics import print_worked_example

    print_worked_example()



def _register_commands() -> None:
    from affinebody.quantum.cli import density, spectrum
    from affinebody.runner import COMMANDS  # run, demo, plot, export, validate
    from affinebody.sweep import sweep

    for command in (*COMMANDS, spectrum, density, sweep):
        main.add_command(command)


_register_commands()
