"""End to end through the CLI: run, resume (also after SIGKILL), failures, plot, export, validate.

All runs share one tiny config (3 bodies in 2D), so JAX compiles its chunk function once.
"""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import click
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from matplotlib.image import imread

from affinebody.checkpoint import checkpoint_path, load_checkpoint
from affinebody.cli.run import COMMANDS
from affinebody.export import rotation_from_quaternion
from affinebody.h5md import read_trajectory

CLI = click.Group("affinebody", commands={c.name: c for c in COMMANDS})
TOTAL = 20000

TINY = textwrap.dedent('''
    [system]
    n = 2
    bodies = 3
    [body]
    mass = 1.0
    inertia = 0.5
    radius = 0.3
    [kinetic]
    translational = "dalembert"
    internal = "dalembert"
    [[potential]]
    kind = "pair"
    expr = "(r - 1)**2 + 0.1*(M1 - 2)**2"
    [[potential]]
    kind = "one-body"
    expr = "2*(det - 1)**2 + 0.5*(trG - 2)**2"
    [initial]
    x = [[0.0, 0.0], [1.1, 0.0], [0.0, 0.9]]
    momentum = [[0.1, 0.0], [0.0, -0.1], [-0.1, 0.1]]
    phi_momentum = [[[0.0, 0.1], [0.0, 0.0]], [[0.0, 0.0], [0.05, 0.0]], [[0.0, 0.0], [0.0, 0.02]]]
    [run]
    dt = 0.01
    steps = 20000
    every = 500
    checkpoint = 2000
''')


def invoke(*args):
    result = CliRunner().invoke(CLI, [str(a) for a in args])
    return result


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli")
    (path / "tiny.toml").write_text(TINY)
    return path


@pytest.fixture(scope="module")
def reference(folder):
    result = invoke("run", folder / "tiny.toml", "-o", folder / "ref.h5")
    assert result.exit_code == 0, result.output + result.stderr
    assert "max relative error" in result.output
    return folder / "ref.h5"


def datasets(path):
    out = {}
    with h5py.File(path, "r") as f:
        for top in ("particles/bodies", "observables"):
            for name, group in f[top].items():
                if isinstance(group, h5py.Group) and "value" in group:
                    for key in ("step", "time", "value"):
                        out[f"{top}/{name}/{key}"] = group[key][()]
    return out


def assert_bitwise_equal(path, reference):
    got, want = datasets(path), datasets(reference)
    assert got.keys() == want.keys()
    for key in want:
        assert got[key].shape == want[key].shape, key
        assert np.array_equal(got[key], want[key]), key


def test_run_writes_the_h5md_layout_and_conserves(reference):
    with h5py.File(reference, "r") as f:
        assert list(f["h5md"].attrs["version"]) == [1, 1]
        assert "affine_bodies" in f["h5md/modules"]
        frames = TOTAL // 500 + 1
        for name, shape in (("position", (3, 2)), ("momentum", (3, 2)), ("phi", (3, 2, 2)),
                            ("phi_momentum", (3, 2, 2))):
            assert f[f"particles/bodies/{name}/value"].shape == (frames, *shape)
            np.testing.assert_array_equal(f[f"particles/bodies/{name}/step"][()],
                                          np.arange(frames) * 500)
        np.testing.assert_allclose(f["particles/bodies/phi/time"][()], np.arange(frames) * 5.0)
        assert f["particles/bodies/mass"].shape == (3,)
        assert "box" in f["particles/bodies"]
        for name in ("total_energy", "kinetic_energy", "potential_energy", "linear_momentum",
                     "affine_momentum", "angular_momentum"):
            assert f[f"observables/{name}/value"].shape[0] == frames
        assert f["parameters/config"][()].decode() == TINY
        assert f["parameters/seed"][()] == 0 and f["parameters/version"][()]
    traj = read_trajectory(reference)
    obs = traj.observables
    energy = obs["total_energy"]
    assert np.max(np.abs(energy - energy[0])) < 1e-3 * abs(energy[0])
    np.testing.assert_allclose(obs["kinetic_energy"] + obs["potential_energy"], energy,
                               rtol=1e-12)
    # translation- and rotation-invariant H: exact sub-flows keep p and J - J^T to round-off
    assert np.max(np.abs(obs["linear_momentum"] - obs["linear_momentum"][0])) < 1e-11
    assert np.max(np.abs(obs["angular_momentum"] - obs["angular_momentum"][0])) < 1e-10
    np.testing.assert_allclose(obs["linear_momentum"], traj.p.sum(axis=1), atol=1e-15)


def test_resume_reproduces_the_uninterrupted_run_bit_for_bit(folder, reference):
    out = folder / "resumed.h5"
    first = invoke("run", folder / "tiny.toml", "-o", out, "--steps", 8000, "--quiet")
    assert first.exit_code == 0 and first.output == ""
    assert load_checkpoint(checkpoint_path(out)).step == 8000
    second = invoke("run", folder / "tiny.toml", "-o", out, "--resume", "--quiet")
    assert second.exit_code == 0, second.stderr
    assert_bitwise_equal(out, reference)


def test_a_resume_of_a_finished_run_says_nothing_was_integrated(folder, reference):
    """--resume of a run already at its last step integrates nothing: the summary said
    "0 steps in 4.43 s: ... integrating 4.43 s", the copying and set-up given as integration."""
    import shutil

    out = folder / "finished.h5"
    shutil.copy(reference, out)
    shutil.copy(checkpoint_path(reference), checkpoint_path(out))
    result = invoke("run", folder / "tiny.toml", "-o", out, "--resume")
    assert result.exit_code == 0, result.stderr
    lines = result.output.splitlines()
    assert lines[0].endswith(f"steps 0..{TOTAL} (resumed at step {TOTAL}), to {out}")
    assert lines[1].startswith(f"nothing integrated: the run was already complete at step "
                               f"{TOTAL} (")
    assert "integrating" not in result.output and "steps/s" not in result.output
    assert_bitwise_equal(out, reference)


def test_a_resume_refused_says_what_changed_and_which_steps_to_give(folder, reference):
    import shutil

    out = folder / "edited.h5"
    shutil.copy(reference, out)
    shutil.copy(checkpoint_path(reference), checkpoint_path(out))
    # dt edited in the config: the refusal names the setting with both values
    edited = folder / "edited.toml"
    edited.write_text(TINY.replace("dt = 0.01", "dt = 0.02"))
    result = invoke("run", edited, "-o", out, "--resume", "--quiet")
    assert result.exit_code == 1
    assert "(changed: run.dt = 0.01 -> 0.02)" in result.stderr, result.stderr
    assert "[initial] file" in result.stderr
    # a run extended with --steps beyond run.steps: the config's steps is named as such, not
    # as a --steps the user never gave, and the count that continues it is given
    short = folder / "short.toml"
    short.write_text(TINY.replace("steps = 20000", "steps = 10000"))
    result = invoke("run", short, "-o", out, "--resume", "--quiet")
    assert result.exit_code == 1
    assert "run.steps = 10000 is before the checkpoint at step 20000" in result.stderr
    assert "--steps 20000 or more" in result.stderr
    assert "--steps 10000" not in result.stderr


def test_a_run_killed_with_sigkill_resumes_bit_for_bit(folder, reference):
    out = folder / "killed.h5"
    code = (f"from affinebody.cli.run import run; run.main([{str(folder / 'tiny.toml')!r}, "
            f"'-o', {str(out)!r}, '--steps', '100000000', '--quiet'])")
    proc = subprocess.Popen([sys.executable, "-c", code])
    ckpt = checkpoint_path(out)
    deadline = time.monotonic() + 240
    while not ckpt.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    step = load_checkpoint(ckpt).step
    assert 0 < step < TOTAL
    # the killed file is readable up to where it got (frames past the checkpoint included)
    assert read_trajectory(out).frames >= step // 500 + 1
    result = invoke("run", folder / "tiny.toml", "-o", out, "--resume", "--steps", TOTAL,
                    "--quiet")
    assert result.exit_code == 0, result.stderr
    assert_bitwise_equal(out, reference)


def test_a_blow_up_stops_with_step_body_and_cause_and_keeps_the_frames(folder):
    (folder / "stiff.toml").write_text(TINY.replace("dt = 0.01", "dt = 3.0"))
    out = folder / "stiff.h5"
    result = invoke("run", folder / "stiff.toml", "-o", out, "--quiet")
    assert result.exit_code not in (0, None)
    message = result.stderr.strip()
    assert "\n" not in message and "Traceback" not in message
    assert "step" in message and "body" in message and "t =" in message
    traj = read_trajectory(out)
    assert traj.frames >= 1
    assert all(np.all(np.isfinite(a)) for a in traj.state)


def test_a_body_sheared_singular_stops_the_run_with_exit_3_not_as_a_bad_initial_state(folder):
    """A free d'Alembert body sheared at a constant rate: phi = [[1, 1e5 t], [0, 1]], det phi = 1
    throughout, so no step fails the loop's checks (finite, det of its sign), but past t = 84
    phi is singular to float64. The run stops there with exit 3, the step, the body and the
    cause, and keeps the last checkpoint, which holds an invertible phi; the next chunk refused
    that state as a bad initial state ("start on the group"), exit 1."""
    from affinebody._checks import SINGULAR_RTOL, reciprocal_condition
    from affinebody.cli.common import EXIT_STOPPED

    (folder / "shear.toml").write_text(textwrap.dedent("""
        [system]
        n = 2
        bodies = 1
        [body]
        mass = 1.0
        inertia = 1.0
        [kinetic]
        translational = "dalembert"
        internal = "dalembert"
        [initial]
        x = [[0.0, 0.0]]
        phi_momentum = [[[0.0, 1.0e5], [0.0, 0.0]]]
        [run]
        dt = 1.0
        steps = 400
        every = 10
        checkpoint = 10
    """))
    out = folder / "shear.h5"
    result = invoke("run", folder / "shear.toml", "-o", out, "--quiet")
    assert result.exit_code == EXIT_STOPPED, result.stderr
    message = result.stderr.strip()
    assert "\n" not in message and "start on the group" not in message
    assert "body 0" in message and "singular" in message
    stopped = int(message.split("simulation stopped at step ")[1].split()[0])
    assert 84 < stopped <= 100  # sigma_min / sigma_max ~ (1e5 t)^-2 < 64 eps: t > 84
    saved = load_checkpoint(checkpoint_path(out))
    assert saved.step < stopped
    assert float(reciprocal_condition(np.asarray(saved.state.phi[0]))) > SINGULAR_RTOL
    traj = read_trajectory(out)
    assert all(np.all(np.isfinite(a)) for a in traj.state)
    assert traj.step[-1] == stopped  # its frame is written: "up to it", not "before it"
    assert f"the {traj.frames} frames up to it are kept" in message


def test_a_warning_of_a_command_is_one_line_and_its_errors_keep_their_exit_codes():
    """What a command warns (e.g. the GPU's Triton kernels not building, pair_kernels) reaches
    stderr as one line "warning: ..." without the source line Python adds; the command
    still completes, and an error after it is still its one line."""
    import warnings

    from affinebody.cli.common import EXIT_BAD_INPUT, one_line_errors

    @click.command()
    @click.option("--fail", is_flag=True)
    @one_line_errors
    def noisy(fail):
        warnings.warn("first line of the warning\nsecond line", RuntimeWarning, stacklevel=1)
        if fail:
            raise ValueError("config error: x must be > 0")
        click.echo("done")

    result = CliRunner().invoke(noisy, [])
    assert result.exit_code == 0 and result.stdout == "done\n"
    assert result.stderr == "warning: first line of the warning\n"
    result = CliRunner().invoke(noisy, ["--fail"])
    assert result.exit_code == EXIT_BAD_INPUT
    assert result.stderr.splitlines() == ["warning: first line of the warning",
                                          "config error: x must be > 0"]
    assert warnings.showwarning.__name__ != "_one_line_warning"  # restored after the command


def test_plot_writes_nonempty_images(folder, reference):
    result = invoke("plot", reference, "-o", folder / "plots")
    assert result.exit_code == 0, result.stderr
    names = {"energy.png", "momenta.png", "deformation.png", "bodies.png", "temperature.png"}
    assert names <= {p.name for p in (folder / "plots").iterdir()}
    for name in names:
        image = imread(folder / "plots" / name)
        assert image.shape[0] > 100 and image.shape[1] > 100
        assert float(np.std(image[..., :3])) > 0.01  # something is drawn


def test_plot_of_an_n1_run_draws_its_bodies_as_rods_and_warns_nothing(folder):
    """n = 1 (README: n = 1, 2, 3): bodies.png draws each body as its rod, one row per body
    (no bodies.png had been written), and momenta.png has no panel for J - J^T, which n = 1
    does not have (its empty legend had leaked matplotlib's "No artists with labels found to
    put in legend")."""
    import warnings

    one = (TINY.replace("n = 2", "n = 1").replace("inertia = 0.5", "inertia = [[0.5]]")
           .replace('expr = "(r - 1)**2 + 0.1*(M1 - 2)**2"', 'expr = "(r - 1)**2"')
           .replace('expr = "2*(det - 1)**2 + 0.5*(trG - 2)**2"', 'expr = "2*(det - 1)**2"')
           .replace("x = [[0.0, 0.0], [1.1, 0.0], [0.0, 0.9]]", "x = [[0.0], [1.1], [2.0]]")
           .replace("momentum = [[0.1, 0.0], [0.0, -0.1], [-0.1, 0.1]]",
                    "momentum = [[0.1], [0.0], [-0.1]]")
           .replace("phi_momentum = [[[0.0, 0.1], [0.0, 0.0]], [[0.0, 0.0], [0.05, 0.0]], "
                    "[[0.0, 0.0], [0.0, 0.02]]]", "phi_momentum = [[[0.1]], [[0.0]], [[-0.02]]]")
           .replace("steps = 20000", "steps = 100").replace("every = 500", "every = 10")
           .replace("checkpoint = 2000", "checkpoint = 100"))
    (folder / "one.toml").write_text(one)
    assert invoke("run", folder / "one.toml", "-o", folder / "one.h5", "--quiet").exit_code == 0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = invoke("plot", folder / "one.h5", "-o", folder / "one-plots")
    assert result.exit_code == 0, result.stderr
    assert [str(w.message) for w in caught] == [] and "warning" not in result.stderr
    written = [Path(line).name for line in result.output.splitlines()]
    assert written == ["energy.png", "momenta.png", "deformation.png", "temperature.png",
                       "bodies.png"]
    image = imread(folder / "one-plots" / "bodies.png")[..., :3]
    red = (image[..., 0] > 0.6) & (image[..., 1] < 0.4) & (image[..., 2] < 0.4)
    assert np.count_nonzero(red) > 20  # the material axes (C3) are drawn
    with h5py.File(folder / "one.h5", "r") as f:
        assert f["particles/bodies/phi/value"].shape[-2:] == (1, 1)


def test_plot_of_a_file_without_its_energies_is_one_line(folder, reference):
    """A file whose total_energy was deleted (an edited or foreign file): one line naming what
    is missing, exit 1, no plot written (was "internal error: KeyError: 'total_energy'")."""
    import shutil

    edited = folder / "edited.h5"
    shutil.copy(reference, edited)
    with h5py.File(edited, "a") as f:
        del f["observables/total_energy"]
    result = invoke("plot", edited, "-o", folder / "edited-plots")
    assert result.exit_code == 1
    assert "lacks the observables total_energy" in result.stderr
    assert "\n" not in result.stderr.strip() and "internal error" not in result.stderr


def test_an_output_that_cannot_be_written_is_refused_before_any_work(folder, reference):
    """-o and --xyz into a folder that does not exist: one line naming the flag, exit 1, before
    the run or the export (the errors said "No such file or directory" without the flag); an
    evolve --plot with a suffix matplotlib does not write is refused before the evolution
    (it failed after it, "Format 'txt' is not supported")."""
    from affinebody.cli.common import check_output_file

    missing = folder / "no-such-folder"
    result = invoke("run", folder / "tiny.toml", "-o", missing / "x.h5", "--quiet")
    assert result.exit_code == 1 and result.stderr.startswith("error: -o ")
    assert "does not exist" in result.stderr and not missing.exists()
    result = invoke("export", reference, "--xyz", missing / "o.xyz")
    assert result.exit_code == 1 and result.stderr.startswith("error: --xyz ")
    with pytest.raises(ValueError, match="--plot .*suffixes .*png"):
        check_output_file(folder / "means.txt", "--plot", image=True)
    check_output_file(folder / "means.png", "--plot", image=True)  # accepted


def test_plot_can_animate(folder, reference):
    result = invoke("plot", reference, "-o", folder / "anim", "--animate", "gif")
    assert result.exit_code == 0, result.stderr
    gif = folder / "anim" / "bodies.gif"
    assert gif.read_bytes()[:6] in (b"GIF87a", b"GIF89a")
    for fps in ("0", "-5"):  # were a ZeroDivisionError / OverflowError (fuzzing the CLI)
        result = invoke("plot", reference, "-o", folder / "anim0", "--animate", "gif",
                        "--fps", fps)
        message = result.stderr.strip()
        assert result.exit_code == 1 and message.startswith("error: --fps must be"), message


def test_export_quaternions_reproduce_phi(folder, reference):
    xyz = folder / "out.xyz"
    result = invoke("export", reference, "--xyz", xyz)
    assert result.exit_code == 0, result.stderr
    traj = read_trajectory(reference)
    lines = xyz.read_text().splitlines()
    per_frame = traj.bodies + 2
    assert len(lines) == traj.frames * per_frame
    for f in (0, traj.frames - 1):
        header = lines[f * per_frame + 1]
        assert "aspherical_shape:R:3" in header and "orientation:R:4" in header
        assert "deform:R:9" in header
        rows = np.array([[float(v) for v in line.split()[1:]]
                         for line in lines[f * per_frame + 2:(f + 1) * per_frame]])
        quat, semi = rows[:, 6:10], rows[:, 3:6]
        np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, rtol=1e-14)
        rotation = rotation_from_quaternion(quat)
        left = rotation[:, :2, :2]  # L of phi = L D R^T, a rotation about z
        np.testing.assert_allclose(np.linalg.det(left), 1.0, rtol=1e-13)
        b = 0.3**2 * traj.phi[f] @ np.swapaxes(traj.phi[f], -1, -2)
        np.testing.assert_allclose(np.einsum("kij,kj,klj->kil", left, semi[:, :2] ** 2, left),
                                   b, rtol=1e-12, atol=1e-13)
        assert np.all(semi[:, 2] < semi[:, :2].min(axis=1))  # a thin third axis


def test_a_reader_gone_from_stdout_ends_a_command_quietly(folder):
    """`affinebody ... | head`: stdout's reader has closed the pipe; the command ends with
    141 (128 + SIGPIPE, as a shell reports it) and prints nothing, not "error: Broken
    pipe". Also where the output goes through rich (kinematics-demo; spectrum, transitions,
    evolve print their tables so), whose own handling of a broken pipe exited 1."""
    import os
    import subprocess
    import sys

    for args in (["validate", str(folder / "tiny.toml")], ["kinematics-demo"]):
        proc = subprocess.Popen(
            [sys.executable, "-c", "from affinebody.cli import entry; entry()", *args],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            env={k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"})
        proc.stdout.close()  # the reader goes before the command writes
        _, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 141, (args, stderr.decode()[-2000:])
        assert stderr == b""


def test_validate_accepts_good_and_refuses_bad_configs(folder):
    ok = invoke("validate", folder / "tiny.toml")
    assert ok.exit_code == 0 and "ok" in ok.output
    (folder / "bad.toml").write_text(TINY.replace("mass = 1.0", "mass = 1.0\nmas = 2.0"))
    bad = invoke("validate", folder / "bad.toml")
    assert bad.exit_code == 1
    assert bad.stderr.strip() == "config error: body.mas: unknown key (check the spelling; see " \
                                 "the README for the fields)"
    missing = invoke("validate", folder / "nothere.toml")
    assert missing.exit_code == 1 and "nothere.toml" in missing.stderr
    assert "\n" not in missing.stderr.strip()


def test_truncated_output_is_refused_by_plot_and_export(folder, reference):
    data = reference.read_bytes()
    cut = folder / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    for args in (("plot", cut), ("export", cut, "--xyz", folder / "cut.xyz")):
        result = invoke(*args)
        assert result.exit_code == 1
        line = result.stderr.strip()
        assert "\n" not in line and "Traceback" not in line and "cut.h5" in line


def test_a_second_run_onto_an_existing_output_is_refused_unless_overwrite(folder, reference):
    """A repeated command never destroys a trajectory: the existing file is kept byte for
    byte, the refusal is one line naming --resume / --overwrite; --overwrite replaces it."""
    out = folder / "kept.h5"
    out.write_bytes(reference.read_bytes())
    before = out.read_bytes()
    again = invoke("run", folder / "tiny.toml", "-o", out, "--steps", 500, "--quiet")
    assert again.exit_code == 1
    message = again.stderr.strip()
    assert "\n" not in message and "exists" in message and "--overwrite" in message
    assert out.read_bytes() == before
    replaced = invoke("run", folder / "tiny.toml", "-o", out, "--steps", 500, "--quiet",
                      "--overwrite")
    assert replaced.exit_code == 0, replaced.stderr
    assert read_trajectory(out).frames == 2  # steps 0 and 500 (every = 500)



def test_no_command_writes_over_the_file_it_reads(folder, reference):
    """run -o CONFIG --overwrite replaced the config by an HDF5 file, and export --xyz OUT.h5
    emptied the trajectory before reading it (found by fuzzing the CLI): both are refused in
    one line, by path or through a link, and the files are kept byte for byte; a thickness
    that is not a positive number is refused too (it wrote nan into the XYZ file)."""
    config = folder / "own.toml"
    config.write_text(TINY)
    trajectory = folder / "own.h5"
    trajectory.write_bytes(reference.read_bytes())
    (folder / "own-link.h5").unlink(missing_ok=True)
    (folder / "own-link.h5").symlink_to(trajectory)
    attempts = [("run", config, "-o", config, "--overwrite", "--quiet"),
                ("run", config, "-o", folder / ".." / folder.name / "own.toml", "--overwrite"),
                ("export", trajectory, "--xyz", trajectory),
                ("export", trajectory, "--xyz", folder / "own-link.h5")]
    for args in attempts:
        result = invoke(*args)
        message = result.stderr.strip()
        assert result.exit_code == 1 and "\n" not in message, message
        assert "is the file this command reads" in message, message
    assert config.read_text() == TINY
    assert trajectory.read_bytes() == reference.read_bytes()
    nowhere = invoke("run", config, "-o", folder / "no" / "such" / "x.h5", "--quiet")
    assert nowhere.exit_code == 1 and "the folder" in nowhere.stderr, nowhere.stderr
    assert "does not exist" in nowhere.stderr and "\n" not in nowhere.stderr.strip()
    for thickness in ("nan", "inf", "0", "-1"):
        result = invoke("export", trajectory, "--xyz", folder / "thick.xyz",
                        "--thickness", thickness)
        assert result.exit_code == 1 and "--thickness" in result.stderr, result.stderr

def test_progress_says_compiling_first_and_the_summary_keeps_compilation_apart(folder, monkeypatch):
    """Issue 18 item 6: the bar exists (phase "compiling") before the first, compiling chunk
    and shows a rate only once integrating; the summary gives compilation and integration
    apart, the rate over integration alone."""
    from rich.console import Console

    from affinebody.cli import run as run_cli
    from affinebody.config import load_config
    from affinebody.runner import run_simulation

    monkeypatch.setattr(Console, "is_terminal", property(lambda self: True))
    bar, update = run_cli._progress_callback(quiet=False)
    seen = []

    def watch(step, total, drift):
        update(step, total, drift)
        task = bar.tasks[0]
        seen.append((step, task.fields["phase"], task.fields["rate"], time.perf_counter()))

    summary = run_simulation(load_config(folder / "tiny.toml"), folder / "progress.h5",
                             steps=6000, progress=watch)
    assert seen[0][:3] == (0, "compiling", "-")  # shown before anything is integrated
    # "compiling" stood on the bar while the first chunk compiled
    assert seen[1][3] - seen[0][3] >= 0.9 * summary.compile_seconds
    assert [phase for _, phase, _, _ in seen[1:]] == ["integrating"] * (len(seen) - 1)
    assert seen[-1][0] == 6000 and seen[-1][2] != "-"
    line = summary.lines()[1]
    assert f"compiling {summary.compile_seconds:.2f} s" in line
    assert f"integrating {summary.integrate_seconds:.2f} s" in line
    assert summary.steps_per_second == pytest.approx(6000 / summary.integrate_seconds)


def test_help_lists_the_commands_as_click_would_without_importing_them(monkeypatch):
    """``affinebody --help`` lists the lazily imported commands from ``cli.SUMMARIES``: the
    same text, at any terminal width, as click's own listing made from the commands (their
    help, imported), and in a fresh process it imports neither JAX nor any command module
    (it took seconds when it did)."""
    import affinebody.cli as cli

    widths = (50, 80, 200)  # 200: no command's first sentence is shortened
    lazy = [CliRunner().invoke(cli.main, ["--help"], terminal_width=w).output for w in widths]
    monkeypatch.setattr(cli._LazyGroup, "format_commands", click.Group.format_commands)
    eager = [CliRunner().invoke(cli.main, ["--help"], terminal_width=w).output for w in widths]
    assert lazy == eager
    assert set(cli.SUMMARIES) == set(cli.COMMANDS)
    loaded = _in_a_fresh_process("assert CliRunner().invoke(main, ['--help']).exit_code == 0\n"
                                 "print(sorted(m for m in sys.modules if m == 'jax' or "
                                 "m.startswith(('affinebody.cli.', 'affinebody.quantum'))))")
    assert loaded == "[]", loaded


def _in_a_fresh_process(code: str) -> str:
    """The stripped stdout of ``code`` run in a new Python process after ``import sys``, click's
    CliRunner and affinebody.cli's ``main`` and ``COMMANDS``."""
    head = ("import sys\nfrom click.testing import CliRunner\n"
            "from affinebody.cli import COMMANDS, main\n")
    return subprocess.run([sys.executable, "-c", head + code], capture_output=True, text=True,
                          check=True).stdout.strip()


def test_the_help_of_every_command_loads_no_jax_and_a_stopped_run_still_exits_3():
    """``affinebody CMD --help`` imports the command's module only: no JAX, Numba, h5py,
    matplotlib, SciPy or Dask (it imported JAX and the command's solvers, 2.6 s). The one-line
    error policy still tells a stopped run (exit 3) from an internal error (exit 1) without
    importing the runner itself."""
    loaded = _in_a_fresh_process(
        "for name in COMMANDS:\n"
        "    result = CliRunner().invoke(main, [name, '--help'])\n"
        "    assert result.exit_code == 0 and 'Usage:' in result.output, name\n"
        "print(sorted(m for m in ('jax', 'numba', 'h5py', 'matplotlib', 'scipy', 'dask') "
        "if m in sys.modules))")
    assert loaded == "[]", loaded

    from affinebody.cli.common import EXIT_STOPPED, one_line_errors
    from affinebody.runner import SimulationStopped

    @click.command()
    @one_line_errors
    def stops():
        raise SimulationStopped("non-finite state at step 7")

    @click.command()
    @one_line_errors
    def breaks():
        raise RuntimeError("a bug")

    stopped, broken = CliRunner().invoke(stops, []), CliRunner().invoke(breaks, [])
    assert (stopped.exit_code, stopped.stderr) == (EXIT_STOPPED,
                                                   "error: non-finite state at step 7\n")
    assert broken.exit_code == 1 and broken.stderr.startswith("internal error: RuntimeError")


def test_usage_errors_of_the_affinebody_command_are_one_line_with_exit_status_2(folder):
    """What click refuses before a command runs (a flag's value of the wrong type, an unknown
    option, a missing argument, flags that exclude each other) was click's four-line usage
    block (found by fuzzing the CLI): one line naming the flag and where the help is; the
    help itself is unchanged."""
    from affinebody.cli import main

    config = folder / "tiny.toml"
    for args, needle in ((["run", config, "--steps", "abc"], "Invalid value for '--steps'"),
                         (["run", config, "--bogus"], "No such option '--bogus'"),
                         (["run"], "Missing argument 'CONFIG.toml'"),
                         (["run", config, "--resume", "--overwrite"], "give one"),
                         (["nosuch"], "No such command 'nosuch'")):
        result = CliRunner().invoke(main, [str(a) for a in args])
        message = result.stderr.strip()
        assert result.exit_code == 2 and "\n" not in message, (args, message)
        assert message.startswith("error: ") and needle in message and "--help" in message
    helped = CliRunner().invoke(main, ["run", "--help"])
    assert helped.exit_code == 0 and helped.output.startswith("Usage: main run [OPTIONS]")
