"""``%%bash`` for the executed tutorials: the cell's commands, their output in order.

IPython's own ``%%bash`` copies the output from a helper thread in 100-byte chunks, which the
Jupyter kernel (ipykernel 7) can split and repeat in the saved output. This one runs the cell
with ``bash -e`` (stop at the first failing command), waits, prints stdout and stderr as they
interleaved, and raises ``CalledProcessError`` on a non-zero exit, as IPython's does, so a
failing command fails ``make docs``. Each tutorial loads it in a hidden first cell
(``%load_ext notebook_shell``; docs/conf.py puts this folder on the kernel's path).
"""

from __future__ import annotations

import subprocess


def bash(line: str, cell: str) -> None:
    """Run ``cell`` in ``bash -e``; print its output; raise if it exits non-zero."""
    result = subprocess.run(["bash", "-e", "-c", cell], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, check=False)
    print(result.stdout, end="")
    if result.returncode:
        raise subprocess.CalledProcessError(result.returncode, cell.strip())


def load_ipython_extension(ipython) -> None:
    ipython.register_magic_function(bash, magic_kind="cell", magic_name="bash")
