"""A run killed with SIGKILL at any instant loses no flushed frame and resumes bit for bit.

Each case starts a real ``affinebody run`` process (the CLI's ``run`` command in a fresh Python)
that kills itself with SIGKILL at a chosen instant of its writes: in the middle of appending a
block of frames, before or after the flush of a block, while a checkpoint is being renamed into
place, or while the output file is being laid out. Afterwards the file must open, hold exactly
the frames committed before the kill (equal to the uninterrupted run's), and ``--resume`` must
reproduce the uninterrupted run bit for bit.

The tiny run: every = 500, checkpoint = 2000 and compiled calls of 1000 steps, so each block
appended holds 2 frames (the first 3, with frame 0) and a checkpoint follows every second block:
after block 4, 9 frames are committed and the checkpoint is at step 4000.
"""

import os
import random
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from affinebody.checkpoint import checkpoint_path, load_checkpoint
from affinebody.h5md import OBSERVABLES, STATE_ELEMENTS, read_trajectory
from test_cli_sim import TINY, TOTAL, assert_bitwise_equal, invoke

#: h5py writes per appended block: (value, step, time) for every element and observable, and
#: the commit count.
WRITES_PER_BLOCK = 3 * (len(STATE_ELEMENTS) + len(OBSERVABLES)) + 1

CHILD = textwrap.dedent('''
    import os, signal, sys
    import h5py
    from affinebody.cli.run import run

    seen = [0]

    def dying(original, when):
        def wrapper(*args, **kwargs):
            if when(*args):
                seen[0] += 1
                if seen[0] == {count}:
                    os.kill(os.getpid(), signal.SIGKILL)
            return original(*args, **kwargs)
        return wrapper

    {patch}
    run.main([{config!r}, "-o", {out!r}, "--quiet"])
''')

PATCHES = {
    "write": "h5py.Dataset.__setitem__ = dying(h5py.Dataset.__setitem__, lambda *a: True)",
    "flush": "h5py.File.flush = dying(h5py.File.flush, lambda *a: True)",
    "checkpoint": ("os.replace = dying(os.replace, "
                   "lambda src, dst: str(dst).endswith('.checkpoint.npz'))"),
    "create": "os.replace = dying(os.replace, lambda src, dst: str(src).endswith('.creating'))",
}

# (what is patched, which call kills, the frames that may be committed then): block 5 is cut
# (its writes, the flush of its frames, the flush of its commit count: the count is written
# then, so 9 or 11), or the third checkpoint (after block 6) is being renamed into place
CASES = {
    "in the middle of a block": ("write", 4 * WRITES_PER_BLOCK + 5, (9,)),
    "before a block's flush": ("flush", 1 + 2 * 4 + 1, (9,)),
    "between a block's flush and its commit": ("flush", 1 + 2 * 4 + 2, (9, 11)),
    "renaming a checkpoint": ("checkpoint", 3, (13,)),
    "at a random write": ("write", random.Random(2026).randrange(
        2 * WRITES_PER_BLOCK + 1, 8 * WRITES_PER_BLOCK), None),
}


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("crash")
    (path / "tiny.toml").write_text(TINY)
    reference = invoke("run", path / "tiny.toml", "-o", path / "ref.h5", "--quiet")
    assert reference.exit_code == 0, reference.stderr
    return path


def killed_run(folder, name: str, patch: str, count: int):
    out = folder / f"{name.replace(' ', '_')}.h5"
    code = CHILD.format(count=count, patch=PATCHES[patch], config=str(folder / "tiny.toml"),
                        out=str(out))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=300)
    assert proc.returncode == -9, proc.stderr.decode()[-2000:]
    return out


@pytest.mark.parametrize("case", list(CASES))
def test_a_run_killed_at_any_instant_keeps_its_frames_and_resumes_bit_for_bit(folder, case):
    patch, count, committed = CASES[case]
    out = killed_run(folder, case, patch, count)
    kept = read_trajectory(out)  # opens: never a corrupt file
    reference = read_trajectory(folder / "ref.h5")
    if committed is not None:
        assert kept.frames in committed
    assert kept.frames >= 5  # at least the blocks before the first checkpoint
    for name in STATE_ELEMENTS:  # the frames it holds are the uninterrupted run's, bit for bit
        np.testing.assert_array_equal(getattr(kept, name),
                                      getattr(reference, name)[: kept.frames])
    for name in OBSERVABLES:
        np.testing.assert_array_equal(kept.observables[name],
                                      reference.observables[name][: kept.frames])
    assert load_checkpoint(checkpoint_path(out)).step <= int(kept.step[-1])
    resumed = invoke("run", folder / "tiny.toml", "-o", out, "--resume", "--steps", TOTAL,
                     "--quiet")
    assert resumed.exit_code == 0, resumed.stderr
    assert_bitwise_equal(out, folder / "ref.h5")


def test_a_run_killed_while_laying_out_its_file_leaves_no_output(folder):
    """Before the file is a complete SWMR trajectory it has a temporary name: a kill then leaves
    no output (and a run started again writes it normally)."""
    out = killed_run(folder, "creating", "create", 1)
    assert not out.exists()
    again = invoke("run", folder / "tiny.toml", "-o", out, "--steps", 2000, "--quiet")
    assert again.exit_code == 0, again.stderr
    assert read_trajectory(out).frames == 5


GROWING = textwrap.dedent('''
    [system]
    n = 2
    bodies = 300
    [body]
    mass = 1.0
    inertia = 0.5
    [kinetic]
    internal = "af-is"
    I = 1.0
    A = 0.2
    [[potential]]
    kind = "one-body"
    expr = "2*(det - 1)**2 + 0.5*(trG - 2)**2"
    [initial]
    generator = "lattice"
    spacing = 1.0
    phi_momentum_scale = 0.3
    seed = 5
    [run]
    dt = 0.01
    steps = 2000
    every = 10
    checkpoint = 100
''')


def test_a_full_disk_stops_the_run_in_one_line_and_keeps_every_frame(folder):
    """The output may not grow past a size limit (as on a full disk; here the process's file-
    size limit): the run stops before the block that does not fit, with one line and exit 1;
    the file holds every frame before it, the checkpoint is intact, and once there is room
    --resume finishes the run exactly as an uninterrupted one.

    GROWING writes 201 frames of 300 bodies (a file of 6.3 MB) in 2000 steps: the file's size
    comes from its frames, not from the steps between them (20,000 steps, every 100, wrote the
    same 6.3 MB in 10 s more of integration)."""
    (folder / "growing.toml").write_text(GROWING)
    reference = folder / "growing_ref.h5"
    whole = invoke("run", folder / "growing.toml", "-o", reference, "--quiet")
    assert whole.exit_code == 0, whole.stderr
    limit = reference.stat().st_size // 2
    out = folder / "growing.h5"

    # the limit is set by the child itself (a write past it then fails with EFBIG)
    code = ("import resource, signal; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit})); "
            "from affinebody.cli.run import run; "
            f"run.main([{str(folder / 'growing.toml')!r}, '-o', {str(out)!r}, '--quiet'])")
    # without the suite's compilation cache, as a user runs it: on some Intel CPUs XLA logs
    # two lines per executable it loads from that cache (openxla/xla#44565, harmless)
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, env=env)
    message = proc.stderr.strip()
    assert proc.returncode == 1 and "\n" not in message, message
    assert "no room" in message and "--resume" in message
    kept = read_trajectory(out)
    complete = read_trajectory(reference)
    assert 1 < kept.frames < complete.frames
    np.testing.assert_array_equal(kept.phi, complete.phi[: kept.frames])
    assert load_checkpoint(checkpoint_path(out)).step <= int(kept.step[-1])
    resumed = invoke("run", folder / "growing.toml", "-o", out, "--resume", "--quiet")
    assert resumed.exit_code == 0, resumed.stderr
    assert_bitwise_equal(out, reference)


def test_ctrl_c_stops_a_run_at_once_keeps_its_frames_and_says_how_to_resume(folder):
    """Ctrl-C (SIGINT) in the middle of a long run: exit 130 (not 139, which the interpreter's
    finalisation gave in native code when the interrupt came while XLA compiled or ran, in
    3 of 6 tries), one line saying how to continue, a file that opens with its frames, and a
    checkpoint from which --resume continues."""
    import signal
    import time

    out = folder / "interrupted.h5"
    proc = subprocess.Popen(
        [sys.executable, "-c", "from affinebody.cli import entry; entry()", "run",
         str(folder / "tiny.toml"), "-o", str(out), "--steps", "1000000000", "--quiet"],
        stderr=subprocess.PIPE, text=True,  # no XLA log lines of the tests' compilation cache
        env={k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"})
    deadline = time.monotonic() + 240
    while not checkpoint_path(out).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr[-2000:]
    assert stderr.startswith("interrupted: ") and "--resume continues" in stderr
    assert len(stderr.strip().splitlines()) == 1
    step = load_checkpoint(checkpoint_path(out)).step
    assert step <= int(read_trajectory(out).step[-1])
    resumed = invoke("run", folder / "tiny.toml", "-o", out, "--resume", "--steps", step + 2000,
                     "--quiet")
    assert resumed.exit_code == 0, resumed.stderr
    assert int(read_trajectory(out).step[-1]) == step + 2000


def test_a_ctrl_c_that_python_drops_in_a_garbage_collector_callback_still_stops(monkeypatch):
    """Python drops a KeyboardInterrupt raised inside a gc callback (JAX registers one): the
    interrupt was printed as "Exception ignored" and a run went on. The commands note the
    interrupt and raise it again between chunks (cli.common.raise_if_interrupted)."""
    import gc
    import signal

    from affinebody.cli.common import EXIT_INTERRUPTED, one_line_errors, raise_if_interrupted

    dropped = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: dropped.append(u.exc_type))

    def interrupted_during_collection(phase, info):
        if phase == "start":
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(10000))  # Python runs the handler here: its exception is dropped

    @one_line_errors
    def command():
        gc.callbacks.append(interrupted_during_collection)
        try:
            gc.collect()
        finally:
            gc.callbacks.remove(interrupted_during_collection)
        assert dropped == [KeyboardInterrupt]  # Python dropped it: the run would go on
        raise_if_interrupted()
        return "went on"

    with pytest.raises(SystemExit) as done:
        command()
    assert done.value.code == EXIT_INTERRUPTED
