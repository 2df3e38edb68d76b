"""Third-party readers read back exactly what we wrote (issue 18): MDAnalysis and pyh5md the
H5MD file (positions, times, the per-frame box, units), OVITO the extended XYZ (phi from its
Deformation Gradient, the ellipsoids from Aspherical Shape and Orientation, the cell); and the
H5MD 1.1 letter (fixed-length strings, superblock version 3 = HDF5 >= 1.10).

One tiny 3D periodic run in GROMACS units (2 bodies, 40 steps) goes through the whole path
config -> runner -> file; one synthetic file in reduced units covers the default.
"""

import re
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from affinebody.config import ConfigError, parse_config
from affinebody.export import rotation_from_quaternion, write_xyz
from affinebody.h5md import (
    UNIT_SYSTEMS,
    H5MDWriter,
    copy_frames_from_file,
    open_trajectory,
    read_trajectory,
)
from affinebody.state import State

README = Path(__file__).resolve().parents[1] / "README.md"
BOX = [4.0, 5.0, 6.0]
RUN3 = textwrap.dedent('''
    [system]
    n = 3
    bodies = 2
    box = [4.0, 5.0, 6.0]
    units = "gromacs"
    [body]
    mass = 1.0
    inertia = 0.5
    radius = 0.3
    [kinetic]
    translational = "dalembert"
    internal = "dalembert"
    [[potential]]
    kind = "one-body"
    expr = "2*(det - 1)**2 + 0.5*(trG - 3)**2"
    [initial]
    x = [[0.5, 0.5, 0.5], [2.0, 2.5, 3.0]]
    momentum = [[0.1, 0.0, 0.2], [0.0, -0.1, 0.0]]
    phi_momentum = [[[0.0, 0.1, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.1]],
                    [[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.0, 0.02]]]
    [run]
    dt = 0.01
    steps = 40
    every = 10
''')


@pytest.fixture(scope="module")
def gromacs_run(tmp_path_factory):
    from affinebody.config import load_config
    from affinebody.runner import run_simulation

    folder = tmp_path_factory.mktemp("interop")
    (folder / "run3.toml").write_text(RUN3)
    run_simulation(load_config(folder / "run3.toml"), folder / "run3.h5")
    return folder / "run3.h5"


def synthetic3(frames=4, bodies=3, seed=3):
    rng = np.random.default_rng(seed)
    phi = np.eye(3) + 0.3 * rng.normal(size=(frames, bodies, 3, 3))
    state = State(rng.uniform(0, 4, size=(frames, bodies, 3)), phi,
                  rng.normal(size=(frames, bodies, 3)), rng.normal(size=(frames, bodies, 3, 3)))
    obs = {"total_energy": rng.normal(size=frames), "kinetic_energy": rng.normal(size=frames),
           "potential_energy": rng.normal(size=frames),
           "linear_momentum": rng.normal(size=(frames, 3)),
           "affine_momentum": rng.normal(size=(frames, 3, 3)),
           "angular_momentum": rng.normal(size=(frames, 3, 3)),
           "translational_temperature": rng.normal(size=frames),
           "internal_temperature": rng.normal(size=frames)}
    return state, obs


@pytest.fixture(scope="module")
def reduced_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("reduced") / "reduced.h5"
    state, obs = synthetic3()
    with H5MDWriter(path, mass=np.array([1.0, 2.0, 3.0]), radius=np.array([0.3, 0.4, 0.5]), n=3,
                    box=BOX, parameters={"dt": 0.25}) as w:
        w.append(np.arange(4) * 10, np.arange(4) * 2.5, state, obs)
    return path, state


# --------------------------------------------------------------------------- MDAnalysis
def test_mdanalysis_reads_a_reduced_unit_file_with_convert_units_false(reduced_file):
    H5MD = pytest.importorskip("MDAnalysis.coordinates.H5MD",
                               reason="MDAnalysis not installed (pip install -e .[dev])")
    path, state = reduced_file
    reader = H5MD.H5MDReader(str(path), convert_units=False)
    assert reader.n_frames == 4
    for k, ts in enumerate(reader):
        np.testing.assert_array_equal(ts.positions, state.x[k].astype(np.float32))
        assert ts.time == 2.5 * k and ts.data["step"] == 10 * k
        np.testing.assert_array_equal(ts.dimensions, [*BOX, 90, 90, 90])
    reader.close()
    # reduced numbers carry no unit MDAnalysis could convert: its default refuses them
    with pytest.raises(ValueError, match="readable units"):
        H5MD.H5MDReader(str(path))


def test_mdanalysis_reads_a_gromacs_unit_run_and_converts_it(gromacs_run):
    H5MD = pytest.importorskip("MDAnalysis.coordinates.H5MD",
                               reason="MDAnalysis not installed (pip install -e .[dev])")
    ours = read_trajectory(gromacs_run)
    reader = H5MD.H5MDReader(str(gromacs_run))  # convert_units=True, MDAnalysis's default
    assert reader.units["length"] == "nm" and reader.units["time"] == "ps"
    assert reader.n_frames == ours.frames == 5
    for k, ts in enumerate(reader):  # MDAnalysis works in Angstrom and ps (float32)
        np.testing.assert_allclose(ts.positions, 10 * ours.x[k], rtol=2e-7, atol=1e-6)
        assert ts.time == pytest.approx(ours.time[k], rel=1e-15)
        np.testing.assert_allclose(ts.dimensions[:3], 10 * np.asarray(BOX), rtol=1e-7)
    reader.close()


# --------------------------------------------------------------------------- pyh5md
def test_pyh5md_reads_positions_times_box_and_mass(gromacs_run):
    pyh5md = pytest.importorskip("pyh5md", reason="pyh5md not installed (pip install -e .[dev])")
    ours = read_trajectory(gromacs_run)
    with pyh5md.File(str(gromacs_run), "r") as f:
        bodies = f.particles_group("bodies")
        position = pyh5md.element(bodies, "position")
        np.testing.assert_array_equal(position.value[()], ours.x)
        np.testing.assert_array_equal(position.step[()], ours.step)
        np.testing.assert_array_equal(position.time[()], ours.time)
        edges = pyh5md.element(bodies["box"], "edges")
        assert edges.element_type == "TimeElement"
        np.testing.assert_array_equal(edges.value[()], np.tile(BOX, (ours.frames, 1)))
        np.testing.assert_array_equal(edges.step[()], ours.step)
        np.testing.assert_array_equal(pyh5md.element(bodies, "mass")[()], [1.0, 1.0])
        assert position.value.attrs["unit"] == "nm" and position.time.attrs["unit"] == "ps"


# --------------------------------------------------------------------------- H5MD letter
def test_h5md_strings_are_fixed_length_and_units_are_declared(gromacs_run, reduced_file):
    def fixed(attrs, name):
        kind = attrs.get_id(name).get_type()
        return isinstance(kind, h5py.h5t.TypeStringID) and not kind.is_variable_str()

    for path, system in ((gromacs_run, "gromacs"), (reduced_file[0], "reduced")):
        with h5py.File(path, "r") as f:
            assert fixed(f["h5md/author"].attrs, "name")
            assert fixed(f["h5md/creator"].attrs, "name")
            assert fixed(f["h5md/creator"].attrs, "version")
            box = f["particles/bodies/box"].attrs
            assert fixed(box, "boundary") and list(box["boundary"]) == [b"periodic"] * 3
            assert f["h5md/modules/units"].attrs["system"] == system.encode()
            units = {name: f[f"particles/bodies/{name}/value"].attrs.get("unit")
                     for name in ("position", "momentum", "phi", "phi_momentum")}
            units["box"] = f["particles/bodies/box/edges/value"].attrs.get("unit")
            units["energy"] = f["observables/total_energy/value"].attrs.get("unit")
            units["time"] = f["particles/bodies/position/time"].attrs.get("unit")
        table = UNIT_SYSTEMS[system]
        assert units == {"position": table.get("length"), "momentum": table.get("momentum"),
                         "phi": None, "phi_momentum": table.get("action"),
                         "box": table.get("length"), "energy": table.get("energy"),
                         "time": table.get("time")}
        assert read_trajectory(path).units == system
        # libver="latest" (needed for SWMR): superblock version 3, readable by HDF5 >= 1.10
        assert Path(path).read_bytes()[8] == 3
    assert "HDF5 ≥ 1.10" in README.read_text()


def test_config_names_its_unit_system_in_one_line():
    base = RUN3.replace('units = "gromacs"\n', "")
    assert parse_config(base).system.units == "reduced"
    # the default leaves the hash (and so --resume of earlier files) unchanged
    assert parse_config(base).hash() == parse_config(
        base.replace("box =", 'units = "reduced"\nbox =')).hash()
    assert parse_config(RUN3).hash() != parse_config(base).hash()
    with pytest.raises(ConfigError) as err:
        parse_config(RUN3.replace('"gromacs"', '"si"'))
    assert "system.units" in str(err.value) and "\n" not in str(err.value)


def test_files_with_the_box_stored_once_still_read_resume_and_export(reduced_file, tmp_path):
    """Files of earlier versions have box/edges as one dataset: every reader takes both."""
    old = tmp_path / "old.h5"
    old.write_bytes(reduced_file[0].read_bytes())
    with h5py.File(old, "r+") as f:
        box = f["particles/bodies/box"]
        del box["edges"]
        box.create_dataset("edges", data=np.asarray(BOX))
        del f["h5md/modules/units"]
    new = read_trajectory(reduced_file[0])
    got = read_trajectory(old)
    np.testing.assert_array_equal(got.box, BOX)
    np.testing.assert_array_equal(got.boxes, new.boxes)
    np.testing.assert_array_equal(got.x, new.x)
    assert got.units == "reduced"
    copy = tmp_path / "copy.h5"
    with H5MDWriter(copy, mass=got.mass, radius=got.radius, n=3, box=BOX) as writer:
        assert copy_frames_from_file(old, writer, through_step=20)[0] == 3
    np.testing.assert_array_equal(read_trajectory(copy).boxes, np.tile(BOX, (3, 1)))
    with open_trajectory(old) as lazy:
        write_xyz(lazy, tmp_path / "old.xyz")
    assert 'Lattice="4 0 0 0 5 0 0 0 6"' in (tmp_path / "old.xyz").read_text()


# --------------------------------------------------------------------------- OVITO
def test_ovito_reads_phi_the_ellipsoids_and_the_cell(reduced_file, tmp_path):
    pytest.importorskip("ovito", reason="ovito not installed (pip install -e .[dev]; "
                                        "manylinux_2_34 wheels only)")
    from ovito.io import import_file

    path, state = reduced_file
    xyz = tmp_path / "bodies.xyz"
    with open_trajectory(path) as trajectory:
        write_xyz(trajectory, xyz)
        radius = trajectory.radius
    pipeline = import_file(str(xyz))
    assert pipeline.source.num_frames == 4
    for k in (0, 3):
        data = pipeline.compute(k)
        particles = data.particles
        gradient = particles["Deformation Gradient"]
        # components named row-column ("YX": row y, column x); OVITO stores them in that order
        index = {name: i for i, name in enumerate(gradient.component_names)}
        values = np.asarray(gradient)
        phi = np.asarray([[[values[b, index[f"{r}{c}"]] for c in "XYZ"] for r in "XYZ"]
                          for b in range(values.shape[0])])
        np.testing.assert_allclose(phi, state.phi[k], rtol=1e-15, atol=1e-15)
        # the ellipsoid OVITO draws, R diag(shape^2) R^T, is {x + phi a : |a| <= r}
        rotation = rotation_from_quaternion(np.asarray(particles["Orientation"]))
        shape = np.asarray(particles["Aspherical Shape"], dtype=np.float64)
        drawn = np.einsum("kij,kj,klj->kil", rotation, shape**2, rotation)
        want = radius[:, None, None] ** 2 * state.phi[k] @ np.swapaxes(state.phi[k], -1, -2)
        np.testing.assert_allclose(drawn, want, rtol=1e-6, atol=1e-6)  # float32 in OVITO
        np.testing.assert_allclose(np.asarray(particles["Position"]), state.x[k], rtol=1e-15)
        np.testing.assert_array_equal(np.asarray(data.cell[...])[:, :3], np.diag(BOX))
        assert list(data.cell.pbc) == [True, True, True]
        # one particle type, "body", which OVITO takes for no chemical element (the species
        # "B" had been boron: its colour, radius 2.01 and mass 10.811 on every body)
        (kind,) = particles.particle_types.types
        assert kind.name == "body" and set(np.asarray(particles.particle_types)) == {kind.id}
        assert (kind.mass, kind.radius, kind.vdw_radius) == (0.0, 0.0, 0.0)


# --------------------------------------------------------------------------- plots
def test_plot_of_a_3d_run_draws_the_ellipsoids_with_units(gromacs_run, tmp_path, monkeypatch):
    from matplotlib.image import imread

    from affinebody import plotting

    with open_trajectory(gromacs_run) as trajectory:
        x, phi = np.asarray(trajectory.x[0]), np.asarray(trajectory.phi[0])
        surface = plotting.ellipsoid_surface(x, phi, trajectory.radius)  # [N, 3, P, 2P]
        a = np.einsum("kij,kjpq->kipq", np.linalg.inv(phi), surface - x[:, :, None, None])
        np.testing.assert_allclose(np.linalg.norm(a, axis=1), 0.3, rtol=1e-13)
        figures = []
        monkeypatch.setattr(plotting, "_save", lambda fig, path: figures.append(fig) or path)
        plotting.plot_all(trajectory, tmp_path)
    energy, momenta, deformation, temperature, bodies = figures
    assert energy.axes[0].get_ylabel() == "energy [kJ/mol]"
    assert temperature.axes[0].get_ylabel() == "kT [kJ/mol]"  # the temperatures, in units
    assert energy.axes[1].get_xlabel() == "time [ps]"
    assert [bodies.axes[0].get_xlabel(), bodies.axes[0].get_ylabel(),
            bodies.axes[0].get_zlabel()] == ["x [nm]", "y [nm]", "z [nm]"]
    titles = " ".join(ax.get_title() for fig in figures for ax in fig.axes)
    assert not re.search(r"\(\d+[a-z]?\)", titles)  # no equation numbers of the paper
    assert "periodic box" in momenta.axes[2].get_title()  # the drift is physical: said so
    legend = [t.get_text() for t in momenta.axes[0].get_legend().get_texts()]
    assert legend == ["$P_{x}$", "$P_{y}$", "$P_{z}$"]
    assert all(ax.get_ylabel() for ax in momenta.axes)
    assert [t.get_text() for t in deformation.legends[0].get_texts()] == ["body 1", "body 2"]
    assert bodies.axes[0].name == "3d"
    bodies.savefig(tmp_path / "bodies.png", dpi=60)
    image = imread(tmp_path / "bodies.png")
    assert float(np.std(image[..., :3])) > 0.01
    for fig in figures:
        plotting.plt.close(fig)
