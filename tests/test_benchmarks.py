"""The benchmark commands that a session lent a GPU machine runs first
(``benchmarks/gpu_session.sh run``: ``step_phases.py`` with ``--pair-program``,
``--f-in-xla``, ``--no-padding-skip``, ``--triton-blocks`` and ``--pair-parts``), run here
on the CPU at 512 bodies with the JAX pair kernel (the GPU's kernel): they must run through,
and the forces of the Triton kernels (in Pallas' interpreter here; f inside the first kernel
or in XLA) and of the XLA program must be those of the product's forces.
A GPU session has a few minutes; a benchmark option broken by a change of the library (as
the patched ``pair_kernels.pair_program`` was once, when it gained arguments) would spend
them."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_gpu_sessions_first_command_runs_and_its_programs_agree():
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.pop("AFFINEBODY_PAIR_PROGRAM", None)
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "step_phases.py"), "--bodies", "512",
         "--loop-steps", "0", "--pair-program", "xla", "--f-in-xla", "--no-padding-skip",
         "--triton-blocks", "64", "--jax-kernel", "--pair-parts"],
        capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    assert "forces, pair program xla" in out and "forces, Triton block 64" in out
    assert "forces, Triton with f in XLA" in out and "forces, no pass skipped" in out
    assert "partials kernel" in out and "rows kernel" in out and "the whole pass" in out
    differences = [float(d) for d in re.findall(r"\(largest difference, relative\)\s+(\S+)",
                                                 out)]
    # the XLA program, the Triton kernels with f in XLA, no pass skipped, the Triton kernels
    # at block 64: each against the forces
    assert len(differences) == 4
    assert all(d <= 1e-12 for d in differences), out
