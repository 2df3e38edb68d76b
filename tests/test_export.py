"""Extended-XYZ export: quaternions are unit and reproduce L of phi = L D R^T, semi-axes are the
singular values times the radius, and the file parses as OVITO expects."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody.export import (
    PROPERTIES,
    ellipsoids,
    quaternion_from_rotation,
    rotation_from_quaternion,
    write_xyz,
)
from affinebody.h5md import Trajectory


def random_rotation(rng, n=3):
    q, r = np.linalg.qr(rng.normal(size=(n, n)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_quaternion_round_trip(seed):
    rng = np.random.default_rng(seed)
    rotation = random_rotation(rng)
    q = quaternion_from_rotation(rotation)
    assert abs(np.linalg.norm(q) - 1) < 1e-14 and q[3] >= 0
    np.testing.assert_allclose(rotation_from_quaternion(q), rotation, atol=1e-13)


def test_half_turns_and_identity():
    for rotation in (np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
                     np.diag([-1.0, -1.0, 1.0])):
        q = quaternion_from_rotation(rotation)
        np.testing.assert_allclose(rotation_from_quaternion(q), rotation, atol=1e-15)
    # a quarter turn about z: q = (0, 0, sin(pi/4), cos(pi/4))
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(quaternion_from_rotation(quarter),
                               [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


@pytest.mark.parametrize("n", [2, 3])
def test_ellipsoid_is_the_image_of_the_ball(n):
    """The ellipsoid {x: x^T B^-1 x <= r^2}, B = phi phi^T, has axes L and semi-axes r sigma:
    R(q) diag(a)^2 R(q)^T = r^2 phi phi^T (independent of the decomposition)."""
    rng = np.random.default_rng(n)
    phi = rng.normal(size=(4, n, n)) + 2 * np.eye(n)
    phi[1] = -phi[1]  # include det phi < 0 for n odd
    radius = np.array([0.5, 1.0, 2.0, 0.25])
    axes, quat, deform = ellipsoids(phi, radius, thickness=0.1)
    rotation = rotation_from_quaternion(quat)
    left = np.einsum("kij,kj,klj->kil", rotation, axes**2, rotation)
    b = radius[:, None, None] ** 2 * phi @ np.swapaxes(phi, -1, -2)
    np.testing.assert_allclose(left[:, :n, :n], b, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(np.sort(axes[:, :n], axis=-1),
                               np.sort(np.linalg.svd(phi, compute_uv=False), -1) * radius[:, None],
                               rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, rtol=1e-14)
    np.testing.assert_array_equal(deform[:, :n, :n], phi)
    if n == 2:
        np.testing.assert_allclose(axes[:, 2], 0.1 * radius)
        np.testing.assert_allclose(rotation[:, 2, 2], 1.0, atol=1e-14)  # rotations about z


def parse_xyz(path):
    """A minimal extended-XYZ reader (independent of the writer)."""
    lines = path.read_text().splitlines()
    frames, k = [], 0
    while k < len(lines):
        count = int(lines[k])
        header = lines[k + 1]
        rows = [line.split() for line in lines[k + 2: k + 2 + count]]
        frames.append((header, rows))
        k += 2 + count
    return frames


def test_written_file_parses_with_the_declared_columns(tmp_path):
    rng = np.random.default_rng(1)
    frames, bodies = 3, 2
    phi = rng.normal(size=(frames, bodies, 2, 2)) + 2 * np.eye(2)
    traj = Trajectory(
        step=np.array([0, 10, 20]), time=np.array([0.0, 0.1, 0.2]),
        x=rng.normal(size=(frames, bodies, 2)), phi=phi,
        p=np.zeros((frames, bodies, 2)), pi=np.zeros((frames, bodies, 2, 2)),
        mass=np.ones(bodies), radius=np.array([0.5, 0.7]), box=np.array([4.0, 5.0]))
    path = tmp_path / "t.xyz"
    assert write_xyz(traj, path) == 3
    parsed = parse_xyz(path)
    assert len(parsed) == 3
    columns = PROPERTIES.split(":")
    widths = [int(w) for w in columns[2::3]]
    assert sum(widths) == 1 + 3 + 3 + 4 + 9
    for f, (header, rows) in enumerate(parsed):
        assert f"Properties={PROPERTIES}" in header
        assert 'Lattice="4 0 0 0 5 0 0 0 1"' in header and 'pbc="T T F"' in header
        assert f"Step={traj.step[f]}" in header
        assert [row[0] for row in rows] == ["body"] * bodies  # OVITO: no element (interop)
        values = np.array([[float(v) for v in row[1:]] for row in rows])
        np.testing.assert_allclose(values[:, :2], traj.x[f], rtol=1e-15)
        np.testing.assert_array_equal(values[:, 2], 0.0)
        quat = values[:, 6:10]
        np.testing.assert_allclose(np.linalg.norm(quat, axis=-1), 1.0, rtol=1e-14)
        rotation = rotation_from_quaternion(quat)[:, :2, :2]
        semi = values[:, 3:5]
        b = traj.radius[:, None, None] ** 2 * traj.phi[f] @ np.swapaxes(traj.phi[f], -1, -2)
        np.testing.assert_allclose(np.einsum("kij,kj,klj->kil", rotation, semi**2, rotation), b,
                                   rtol=1e-12, atol=1e-13)
        deform = values[:, 10:].reshape(bodies, 3, 3).swapaxes(1, 2)  # column by column
        np.testing.assert_array_equal(deform[:, :2, :2], traj.phi[f])


def test_the_species_is_one_word_given_to_every_body(tmp_path):
    traj = Trajectory(step=np.array([0]), time=np.array([0.0]), x=np.zeros((1, 2, 1)),
                      phi=np.ones((1, 2, 1, 1)), p=np.zeros((1, 2, 1)),
                      pi=np.zeros((1, 2, 1, 1)), mass=np.ones(2), radius=np.ones(2), box=None)
    write_xyz(traj, tmp_path / "a.xyz", species="Ar")
    assert [row[0] for row in parse_xyz(tmp_path / "a.xyz")[0][1]] == ["Ar", "Ar"]
    for bad in ("", "two words", "a\nb", "µ"):
        with pytest.raises(ValueError, match="--species must be one word"):
            write_xyz(traj, tmp_path / "b.xyz", species=bad)
    assert not (tmp_path / "b.xyz").exists()


def test_a_frame_with_a_non_finite_or_singular_phi_is_named_by_export_and_plot(tmp_path):
    """A run writes finite frames only; a file changed by other software may hold a nan or a
    singular phi: export and plot say which frame and body (plot had said "SVD did not
    converge"), and write nothing past it."""
    from affinebody import plotting
    from affinebody.h5md import TrajectoryFileError

    rng = np.random.default_rng(2)
    frames, bodies = 3, 3
    phi = rng.normal(size=(frames, bodies, 2, 2)) * 0.1 + np.eye(2)
    phi[2, 2, 0, 1] = np.nan  # the last frame: every plot of the bodies draws it
    traj = Trajectory(
        step=np.array([0, 10, 20]), time=np.array([0.0, 0.1, 0.2]),
        x=rng.normal(size=(frames, bodies, 2)), phi=phi,
        p=np.zeros((frames, bodies, 2)), pi=np.zeros((frames, bodies, 2, 2)),
        mass=np.ones(bodies), radius=np.full(bodies, 0.5), box=None, source="t.h5")
    named = r"t\.h5: frame 2 \(step 20\) holds a non-finite x or phi of body 2"
    with pytest.raises(TrajectoryFileError, match=named):
        write_xyz(traj, tmp_path / "t.xyz")
    for plot in (plotting.plot_bodies, plotting.plot_deformation):
        with pytest.raises(TrajectoryFileError, match=named):
            plot(traj, tmp_path / "t.png")
    phi[2, 2] = np.eye(2)
    phi[1, 1] = [[1.0, 2.0], [2.0, 4.0]]  # singular
    with pytest.raises(ValueError, match=r"frame 1 \(step 10\): phi is singular or not finite at "
                                         r"batch index \(1,\)"):
        write_xyz(traj, tmp_path / "t.xyz")
    # nothing of the failed exports is left: no partial file, no temporary
    assert list(tmp_path.iterdir()) == []
    # and an earlier export to the same name survives a failed one intact
    good = Trajectory(**{**traj.__dict__, "phi": np.broadcast_to(np.eye(2), phi.shape)})
    assert write_xyz(good, tmp_path / "t.xyz") == 3
    before = (tmp_path / "t.xyz").read_bytes()
    with pytest.raises(ValueError, match=r"frame 1 \(step 10\)"):
        write_xyz(traj, tmp_path / "t.xyz")
    assert (tmp_path / "t.xyz").read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["t.xyz"]


def test_n1_bodies_export_as_rods_along_x(tmp_path):
    """n = 1 (README: n = 1, 2, 3): semi-axis r |phi| along x, two thin axes, no rotation,
    deform phi (+) 1 (+) 1, the box edge on x; export had refused it after creating an empty
    file."""
    phi = np.array([[[[1.2]], [[0.7]]], [[[1.1]], [[0.8]]]])
    traj = Trajectory(
        step=np.array([0, 10]), time=np.array([0.0, 0.1]), x=np.array([[[0.0], [1.0]]] * 2),
        phi=phi, p=np.zeros((2, 2, 1)), pi=np.zeros((2, 2, 1, 1)), mass=np.ones(2),
        radius=np.array([0.5, 1.0]), box=np.array([4.0]))
    axes, quat, deform = ellipsoids(phi[0], traj.radius, thickness=0.1)
    np.testing.assert_allclose(axes, [[0.6, 0.05, 0.05], [0.7, 0.1, 0.1]], rtol=1e-15)
    np.testing.assert_array_equal(quat, [[0, 0, 0, 1.0]] * 2)
    np.testing.assert_array_equal(deform[0], np.diag([1.2, 1.0, 1.0]))
    assert write_xyz(traj, tmp_path / "rods.xyz") == 2
    (header, rows), _ = parse_xyz(tmp_path / "rods.xyz")
    assert 'Lattice="4 0 0 0 1 0 0 0 1" pbc="T F F"' in header
    assert [float(v) for v in rows[1][1:4]] == [1.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"phi is singular or not finite at batch index \(1,\)"):
        ellipsoids(np.array([[[1.0]], [[0.0]]]), np.ones(2))
