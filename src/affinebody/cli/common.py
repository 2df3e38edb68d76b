"""What every ``affinebody`` command shares: float64, and one policy for errors and exit codes.

Bad input never gives a traceback: one line on stderr naming the field and the fix (a warning
is one line too, ``warning: ...``), and

- exit 1 (:data:`EXIT_BAD_INPUT`): a bad config, flag or file (``ValueError``, ``OSError``) and
  any unexpected error ("internal error: ...");
- exit 3 (:data:`EXIT_STOPPED`): a computation that stopped or did not converge, with what it
  produced kept: a run stopped on a non-finite or singular state (frames and the last
  checkpoint are kept), densities above their tolerance (written and flagged), a spectrum
  with no converged level (written);
- exit 130 (:data:`EXIT_INTERRUPTED`): interrupted (Ctrl-C); what was written is kept (the
  first Ctrl-C stops a run: :func:`raise_if_interrupted`);
- exit 141 (:data:`EXIT_BROKEN_PIPE`, 128 + SIGPIPE as a shell reports a tool the signal
  ended): the reader of stdout went away (``affinebody ... | head``); nothing is printed;
- exit 2: a usage error that click finds before a command runs (a flag's value of the wrong
  type, an unknown option, a missing argument), one line too (``affinebody.cli.main``).
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
import warnings

import click

EXIT_BAD_INPUT = 1
EXIT_STOPPED = 3
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141


def fail(message: str, code: int = EXIT_BAD_INPUT):
    """Print the first line of ``message`` on stderr and exit with ``code``."""
    click.echo(message.splitlines()[0] if message else "error", err=True)
    sys.exit(code)


#: Set by Ctrl-C while a command runs (:func:`raise_if_interrupted`).
_INTERRUPTED = threading.Event()


def _note_interrupt(signum, frame):
    """SIGINT: Python's own KeyboardInterrupt, and a note of it for :func:`raise_if_interrupted`."""
    _INTERRUPTED.set()
    raise KeyboardInterrupt


def raise_if_interrupted() -> None:
    """KeyboardInterrupt if Ctrl-C was pressed while the command ran. Python drops a
    KeyboardInterrupt raised inside a garbage-collector callback (JAX registers one: the
    interrupt was printed as "Exception ignored in: <function _xla_gc_callback ...>" and a run
    went on until a second Ctrl-C); the long loops of the commands call this between chunks,
    so the first Ctrl-C stops them."""
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt


@contextlib.contextmanager
def _interrupts_noted():
    """:func:`_note_interrupt` as the SIGINT handler while the command runs (main thread
    only: elsewhere Python's handler stays), and no "Exception ignored ... KeyboardInterrupt"
    block from Python's default unraisable hook where it dropped one (the command raises it
    again, :func:`raise_if_interrupted`; a hook installed by someone else still sees it)."""
    _INTERRUPTED.clear()
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous, previous_hook = signal.signal(signal.SIGINT, _note_interrupt), sys.unraisablehook

    def quiet_interrupts(unraisable):
        if not (issubclass(unraisable.exc_type, KeyboardInterrupt)
                and previous_hook is sys.__unraisablehook__):
            previous_hook(unraisable)
    sys.unraisablehook = quiet_interrupts
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    """``warnings.showwarning`` of the commands: the warning's first line, on stderr."""
    text = str(message).strip()
    click.echo(f"warning: {text.splitlines()[0] if text else category.__name__}", err=True)


def exit_broken_pipe():
    """Exit :data:`EXIT_BROKEN_PIPE`, silently: the reader of stdout has gone. What is left in
    stdout's buffer goes to the null device (flushed to the closed pipe at exit, it raised
    again: "Exception ignored ... BrokenPipeError", exit 120)."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    sys.exit(EXIT_BROKEN_PIPE)


@contextlib.contextmanager
def broken_pipe_exits():
    """Around a whole command: a BrokenPipeError, raised while it prints or when its output is
    flushed at the end, exits :data:`EXIT_BROKEN_PIPE` (click's own handling exits 1)."""
    try:
        yield
        sys.stdout.flush()
    except BrokenPipeError:
        exit_broken_pipe()


@functools.cache
def _console_class():
    from rich.console import Console

    class ExitingConsole(Console):
        """rich's Console, whose broken pipe exits :data:`EXIT_BROKEN_PIPE` (rich's own
        ``on_broken_pipe`` exits 1, which read as a failed command)."""

        def on_broken_pipe(self) -> None:
            exit_broken_pipe()

    return ExitingConsole


def output_console(**options):
    """The rich Console of a command's output (``options`` as rich's)."""
    return _console_class()(**options)


def enable_x64() -> None:
    """:func:`affinebody._checks.enable_x64` for the command that runs, JAX imported then: a
    command module imports it from here, so ``affinebody CMD --help`` loads no JAX."""
    from affinebody._checks import enable_x64 as enable

    enable()


def _stopped_run(err: Exception) -> bool:
    """Whether ``err`` is a run's :class:`affinebody.runner.SimulationStopped`. Only a command
    that imported the runner can raise one, so the runner (JAX, Numba: seconds) is looked up,
    never imported, here."""
    runner = sys.modules.get("affinebody.runner")
    return runner is not None and isinstance(err, runner.SimulationStopped)


def one_line_errors(command):
    """Turn every exception of a command into one line on stderr and a non-zero exit, and
    every warning into one line ``warning: ...`` on stderr (no source line). Nothing is
    imported here: ``affinebody CMD --help`` loads no JAX (:func:`_stopped_run`)."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            with warnings.catch_warnings(), _interrupts_noted():
                warnings.showwarning = _one_line_warning
                return command(*args, **kwargs)
        except KeyboardInterrupt as err:  # a command may say what it kept: KeyboardInterrupt(text)
            fail(f"interrupted: {str(err) or 'what was written so far is kept'}", EXIT_INTERRUPTED)
        except BrokenPipeError:  # the reader of stdout has gone (`affinebody ... | head`)
            exit_broken_pipe()
        except ValueError as err:
            text = str(err)
            fail(text if text.startswith(("config error", "error")) else f"error: {text}")
        except OSError as err:
            fail(f"error: {err.strerror or err}: {err.filename or ''}".rstrip(": "))
        except (click.exceptions.Exit, click.ClickException, SystemExit):
            raise
        except Exception as err:  # noqa: BLE001 - the CLI never shows a traceback
            if _stopped_run(err):
                fail(f"error: {err}", EXIT_STOPPED)
            fail(f"internal error: {type(err).__name__}: {err}")

    return wrapper


@contextlib.contextmanager
def not_finite_as(what: str, fix: str):
    """LAPACK's refusal of a matrix that is not finite (SciPy's ValueError "... must not
    contain infs or NaNs", NumPy's LinAlgError) said as one line, ``{what} ({LAPACK's
    words}): {fix}``; NumPy's overflow and invalid-value warnings on the way there are left
    out (the error says it)."""
    import numpy as np

    try:
        with np.errstate(over="ignore", invalid="ignore"):
            yield
    except ValueError as err:
        if not (isinstance(err, np.linalg.LinAlgError)
                or "must not contain infs or NaNs" in str(err)):
            raise
        raise ValueError(f"{what} ({err}): {fix}") from None


def refuse_writing_over(written, read, what: str) -> None:
    """A ValueError (one line) when the file a command would write, ``written``, is a file it
    reads, ``read`` (the same path, or a link to it): writing first would destroy it."""
    from pathlib import Path

    written, read = Path(written), Path(read)
    same = (written.samefile(read) if written.exists() and read.exists()
            else written.resolve() == read.resolve())
    if same:
        raise ValueError(f"{what} {written} is the file this command reads: write elsewhere")


def check_output_file(path, what: str, image: bool = False) -> None:
    """A ValueError (one line, naming the flag ``what``) before any work when the file a
    command will write cannot be: its folder missing or not a folder, or, for an ``image``,
    a suffix matplotlib does not write (found after the whole computation otherwise)."""
    from pathlib import Path

    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise ValueError(f"{what} {path}: the folder {folder} does not exist (create it first)")
    if image:
        from matplotlib.backend_bases import FigureCanvasBase

        formats = FigureCanvasBase.get_supported_filetypes()
        if path.suffix.lstrip(".").lower() not in formats:
            raise ValueError(f"{what} {path}: an image needs one of the suffixes "
                             f"{', '.join('.' + k for k in sorted(formats))}")


__all__ = ["EXIT_BAD_INPUT", "EXIT_BROKEN_PIPE", "EXIT_INTERRUPTED", "EXIT_STOPPED", "fail",
           "not_finite_as", "one_line_errors", "raise_if_interrupted", "refuse_writing_over",
           "check_output_file", "exit_broken_pipe", "broken_pipe_exits", "output_console",
           "enable_x64"]
