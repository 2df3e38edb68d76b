"""H5MD files and checkpoints: the public layout, round trips, crash safety, bad files."""

import os
import signal
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest

from affinebody.checkpoint import (
    Checkpoint,
    CheckpointError,
    checkpoint_path,
    load_checkpoint,
    save_checkpoint,
)
from affinebody.h5md import H5MDWriter, TrajectoryFileError, read_trajectory
from affinebody.state import State


def synthetic(frames=5, bodies=3, n=2, seed=0):
    rng = np.random.default_rng(seed)
    state = State(rng.normal(size=(frames, bodies, n)), rng.normal(size=(frames, bodies, n, n)),
                  rng.normal(size=(frames, bodies, n)), rng.normal(size=(frames, bodies, n, n)))
    obs = {
        "total_energy": rng.normal(size=frames), "kinetic_energy": rng.normal(size=frames),
        "potential_energy": rng.normal(size=frames),
        "linear_momentum": rng.normal(size=(frames, n)),
        "affine_momentum": rng.normal(size=(frames, n, n)),
        "angular_momentum": rng.normal(size=(frames, n, n)),
        "translational_temperature": rng.normal(size=frames),
        "internal_temperature": rng.normal(size=frames),
    }
    return state, obs


def write(path, frames=5, blocks=1, box=None, n=2):
    state, obs = synthetic(frames * blocks, n=n)
    with H5MDWriter(path, mass=np.array([1.0, 2.0, 3.0]), radius=np.full(3, 0.4), n=n, box=box,
                    parameters={"config": "[run]\ndt = 0.1", "seed": 42, "dt": 0.1}) as w:
        for b in range(blocks):
            sl = slice(b * frames, (b + 1) * frames)
            steps = np.arange(sl.start, sl.stop) * 10
            w.append(steps, steps * 0.1, State(*(a[sl] for a in state)),
                     {k: v[sl] for k, v in obs.items()})
    return state, obs


def test_layout_follows_the_contract(tmp_path):
    path = tmp_path / "t.h5"
    write(path, frames=4, blocks=2, box=[5.0, 6.0])
    with h5py.File(path, "r") as f:
        assert list(f["h5md"].attrs["version"]) == [1, 1]
        assert f["h5md/creator"].attrs["name"] == b"affinebody"  # fixed-length (H5MD 1.1)
        assert "affine_bodies" in f["h5md/modules"]
        shapes = {"position": (8, 3, 2), "momentum": (8, 3, 2), "phi": (8, 3, 2, 2),
                  "phi_momentum": (8, 3, 2, 2)}
        for name, shape in shapes.items():
            group = f[f"particles/bodies/{name}"]
            assert group["value"].shape == shape
            np.testing.assert_array_equal(group["step"][()], np.arange(8) * 10)
            np.testing.assert_allclose(group["time"][()], np.arange(8) * 1.0)
        np.testing.assert_array_equal(f["particles/bodies/mass"][()], [1.0, 2.0, 3.0])
        box = f["particles/bodies/box"]
        assert box.attrs["dimension"] == 2
        assert [b.decode() if isinstance(b, bytes) else b for b in box.attrs["boundary"]] == [
            "periodic", "periodic"]
        # per frame (what MDAnalysis reads), its step and time those of position
        np.testing.assert_array_equal(box["edges/value"][()], np.tile([5.0, 6.0], (8, 1)))
        assert box["edges/step"] == f["particles/bodies/position/step"]  # the same dataset
        assert box["edges/time"] == f["particles/bodies/position/time"]
        obs_shapes = {"total_energy": (8,), "kinetic_energy": (8,), "potential_energy": (8,),
                      "linear_momentum": (8, 2), "affine_momentum": (8, 2, 2),
                      "angular_momentum": (8, 2, 2), "translational_temperature": (8,),
                      "internal_temperature": (8,)}
        for name, shape in obs_shapes.items():
            assert f[f"observables/{name}/value"].shape == shape
            assert f[f"observables/{name}/step"].shape == (8,)
        assert f["parameters/config"][()].decode().startswith("[run]")
        assert f["parameters/seed"][()] == 42
        assert f["parameters/version"][()].decode()


def test_round_trip_is_exact(tmp_path):
    path = tmp_path / "t.h5"
    state, obs = write(path, frames=3, blocks=3)
    traj = read_trajectory(path)
    for got, want in zip(traj.state, state, strict=True):
        np.testing.assert_array_equal(got, want)
    for key, value in obs.items():
        np.testing.assert_array_equal(traj.observables[key], value)
    assert traj.seed == 42 and traj.dt == 0.1 and traj.box is None
    np.testing.assert_array_equal(traj.frame(-1).phi, state.phi[-1])


def test_frames_are_readable_while_the_writer_is_open(tmp_path):
    path = tmp_path / "t.h5"
    state, obs = synthetic(4)
    with H5MDWriter(path, mass=np.ones(3), radius=np.ones(3), n=2) as w:
        w.append(np.arange(2), np.arange(2) * 1.0, State(*(a[:2] for a in state)),
                 {k: v[:2] for k, v in obs.items()})
        traj = read_trajectory(path)  # a second reader sees the flushed frames
        assert traj.frames == 2
        np.testing.assert_array_equal(traj.x, state.x[:2])


WRITER = textwrap.dedent('''
    import sys, numpy as np
    from affinebody.h5md import H5MDWriter
    from affinebody.state import State
    w = H5MDWriter(sys.argv[1], mass=np.ones(3), radius=np.ones(3), n=2)
    k = 0
    while True:
        s = State(np.full((1, 3, 2), k, float), np.full((1, 3, 2, 2), k, float),
                  np.zeros((1, 3, 2)), np.zeros((1, 3, 2, 2)))
        obs = {"total_energy": np.zeros(1), "kinetic_energy": np.zeros(1),
               "potential_energy": np.zeros(1), "linear_momentum": np.zeros((1, 2)),
               "affine_momentum": np.zeros((1, 2, 2)), "angular_momentum": np.zeros((1, 2, 2)),
               "translational_temperature": np.zeros(1), "internal_temperature": np.zeros(1)}
        w.append(np.array([k]), np.array([k * 0.5]), s, obs)
        if k == 20:
            print("ready", flush=True)
        k += 1
''')


def test_a_writer_killed_mid_write_leaves_a_readable_file(tmp_path):
    path = tmp_path / "killed.h5"
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path)], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "ready"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    traj = read_trajectory(path)
    assert traj.frames >= 21
    # every frame that reads back is complete and consistent: value k at step k
    np.testing.assert_array_equal(traj.x[:, 0, 0], traj.step)
    np.testing.assert_array_equal(traj.time, 0.5 * traj.step)


def test_truncated_and_foreign_files_are_refused_in_one_line(tmp_path):
    path = tmp_path / "t.h5"
    write(path, frames=50)
    data = path.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 3])
    for bad in (cut, tmp_path / "missing.h5"):
        with pytest.raises(TrajectoryFileError) as info:
            read_trajectory(bad)
        assert "\n" not in str(info.value)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = 1.0
    with pytest.raises(TrajectoryFileError, match="not an affinebody H5MD file"):
        read_trajectory(foreign)


def test_checkpoint_round_trip_is_bit_exact_and_atomic(tmp_path):
    state, _ = synthetic(1)
    state = State(*(a[0] for a in state))
    path = checkpoint_path(tmp_path / "out.h5")
    save_checkpoint(path, Checkpoint(120, state, 13, "abc"))
    save_checkpoint(path, Checkpoint(240, state, 25, "abc"))  # replaces the first
    loaded = load_checkpoint(path, "abc")
    assert (loaded.step, loaded.frames) == (240, 25)
    for got, want in zip(loaded.state, state, strict=True):
        np.testing.assert_array_equal(got, want)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]  # no temporary left
    with pytest.raises(CheckpointError, match="different configuration"):
        load_checkpoint(path, "other")
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="unreadable"):
        load_checkpoint(path)
    # garbage, which NumPy takes for pickled data: no advice to load it unsafely, the fix named
    path.write_bytes(b"not a checkpoint\n" * 10)
    with pytest.raises(CheckpointError, match="unreadable") as info:
        load_checkpoint(path)
    assert "pickled" in str(info.value) and "unsafely" not in str(info.value)
    assert "without --resume" in str(info.value)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "none.npz")


def test_lazy_reader_gives_the_same_frames_and_streaming_copies_them(tmp_path):
    """open_trajectory reads frames on demand (O(N) memory) and gives exactly the arrays of
    read_trajectory; copy_frames_from_file (--resume) copies the frames up to a step in
    blocks, identical to the source."""
    from affinebody.h5md import copy_frames_from_file, open_trajectory

    path = tmp_path / "lazy.h5"
    write(path, frames=4, blocks=3)
    eager = read_trajectory(path)
    with open_trajectory(path) as lazy:
        assert lazy.frames == eager.frames == 12 and lazy.bodies == 3
        for k in (0, 5, -1):
            for name in ("x", "phi", "p", "pi"):
                np.testing.assert_array_equal(getattr(lazy, name)[k], getattr(eager, name)[k])
        np.testing.assert_array_equal(lazy.phi[::5], eager.phi[::5])
        np.testing.assert_array_equal(np.asarray(lazy.pi), eager.pi)
    target = tmp_path / "copy.h5"
    with H5MDWriter(target, mass=eager.mass, radius=eager.radius, n=2) as writer:
        count, energies = copy_frames_from_file(path, writer, int(eager.step[6]),
                                                block_bytes=1)  # one frame per block
    assert count == 7
    copied = read_trajectory(target)
    np.testing.assert_array_equal(copied.phi, eager.phi[:7])
    np.testing.assert_array_equal(energies, eager.observables["total_energy"][:7])


def test_every_recorded_observable_is_one_the_driver_computes():
    """The file's observables and the driver's registry are one list of names (up to H5MD's
    total_energy), so a run can record every observable the file layout promises."""
    from affinebody.h5md import DRIVER_NAMES, OBSERVABLES
    from affinebody.simulate import NAMED_OBSERVABLES

    for name in OBSERVABLES:
        assert DRIVER_NAMES.get(name, name) in NAMED_OBSERVABLES, name
