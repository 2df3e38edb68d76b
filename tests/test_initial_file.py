"""``[initial] file = "..."``: a run that starts from a frame of another run's trajectory (an
equilibration, then a production run; an NPT run, then NVT in the box of its mean volume).

One periodic run of 3 bodies in 2D writes the file; a run started from its frame k is the
same motion as the rest of that run, bit for bit (NVE is deterministic and a frame holds x,
phi, p and pi in float64), and every way the frame may not fit the
config is refused in one line naming the field and the fix.
"""

import textwrap

import numpy as np
import pytest
from click.testing import CliRunner

from affinebody.cli.run import validate
from affinebody.config import ConfigError, build, check_config, parse_config
from affinebody.h5md import read_trajectory
from affinebody.runner import run_simulation

BOX = textwrap.dedent('''
    [system]
    n = 2
    bodies = 3
    box = [3.0, 2.5]
    [body]
    mass = 1.0
    inertia = 0.5
    [kinetic]
    translational = "dalembert"
    internal = "af-is"
    I = 1.0
    A = 0.2
    [[potential]]
    kind = "pair"
    expr = "(r - 1)**2 + 0.1*(M1 - 2)**2"
    r_cut = 1.2
    [[potential]]
    kind = "one-body"
    expr = "2*(det - 1)**2 + 0.5*(trG - 2)**2"
    [initial]
    x = [[0.2, 0.3], [1.1, 0.3], [0.2, 1.2]]
    momentum = [[0.1, 0.0], [0.0, -0.1], [-0.1, 0.1]]
    phi_momentum = [[[0.0, 0.1], [0.0, 0.0]], [[0.0, 0.0], [0.05, 0.0]], [[0.0, 0.0], [0.0, 0.02]]]
    [run]
    dt = 0.01
    steps = 200
    every = 50
    neighbor_list = "off"
''')
ARRAYS = '''x = [[0.2, 0.3], [1.1, 0.3], [0.2, 1.2]]
momentum = [[0.1, 0.0], [0.0, -0.1], [-0.1, 0.1]]
phi_momentum = [[[0.0, 0.1], [0.0, 0.0]], [[0.0, 0.0], [0.05, 0.0]], [[0.0, 0.0], [0.0, 0.02]]]
'''


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    folder = tmp_path_factory.mktemp("initial-file")
    run_simulation(check_config(parse_config(BOX)), folder / "first.h5")
    return folder / "first.h5"


def from_file(path, lines="", replace=()):
    text = BOX.replace(ARRAYS, f'file = "{path}"\n{lines}')
    for old, new in replace:
        text = text.replace(old, new)
    return text


def test_a_run_from_frame_k_continues_the_run_that_wrote_it(first, tmp_path):
    whole = read_trajectory(first)
    assert whole.frames == 5
    config = check_config(parse_config(from_file(first, "frame = 2\n").replace(
        "steps = 200", "steps = 100")))
    assert config.bodies_count == 3
    start = build(config).state
    for name in ("x", "phi", "p", "pi"):
        np.testing.assert_array_equal(getattr(start, name), getattr(whole, name)[2])
    run_simulation(config, tmp_path / "second.h5")
    second = read_trajectory(tmp_path / "second.h5")
    assert second.frames == 3
    for name in ("x", "phi", "p", "pi"):
        np.testing.assert_array_equal(getattr(second, name), getattr(whole, name)[2:])
    np.testing.assert_allclose(second.observables["total_energy"],
                               whole.observables["total_energy"][2:], rtol=1e-12)


def test_the_last_frame_by_default_and_momenta_from_the_options_when_asked(first):
    last = read_trajectory(first).frame(-1)
    state = build(check_config(parse_config(from_file(first, "file_momenta = false\n")))).state
    np.testing.assert_array_equal(state.x, last.x)
    np.testing.assert_array_equal(state.phi, last.phi)
    assert not np.any(state.p) and not np.any(state.pi)  # momentum_scale 0: at rest
    given = from_file(first, "file_momenta = false\nmomentum = [[0.5, 0.0], [0.0, 0.0], "
                             "[-0.5, 0.0]]\n")
    np.testing.assert_array_equal(build(check_config(parse_config(given))).state.p[:, 0],
                                  [0.5, 0.0, -0.5])


def test_rescale_maps_the_positions_into_the_new_box_and_keeps_the_shapes(first):
    frame = read_trajectory(first).frame(-1)
    text = from_file(first, replace=[("box = [3.0, 2.5]", "box = [3.3, 2.75]")])
    with pytest.raises(ConfigError, match=r"has the box \[3, 2.5\].*initial.rescale = true"):
        check_config(parse_config(text))
    state = build(check_config(parse_config(text.replace(
        f'file = "{first}"', f'file = "{first}"\nrescale = true')))).state
    np.testing.assert_allclose(state.x, frame.x * np.array([1.1, 1.1]), rtol=1e-15)
    np.testing.assert_array_equal(state.phi, frame.phi)
    np.testing.assert_array_equal(state.p, frame.p)


@pytest.mark.parametrize("lines, replace, message", [
    ("frame = 5\n", (), "initial.frame = 5 is beyond the 5 frames of"),
    ("frame = -6\n", (), "initial.frame = -6 is beyond the 5 frames"),
    ("", [("bodies = 3", "bodies = 4")],
     "the number of bodies disagrees: system.bodies gives 4, initial.file gives 3"),
    ("", [("n = 2", "n = 3"), ("box = [3.0, 2.5]", "box = [3.0, 2.5, 3.0]")],
     "holds bodies in n = 2, but system.n = 3"),
    ("", [("box = [3.0, 2.5]\n", "")], "is in a periodic box: set system.box = [3, 2.5]"),
    ("", [("[system]\n", '[system]\nunits = "gromacs"\n')],
     "is in reduced units, but system.units = 'gromacs': set it to 'reduced'"),
    ("momentum = [[0.5, 0.0], [0.0, 0.0], [-0.5, 0.0]]\n", (),
     "initial.momentum: the momenta come from initial.file; set initial.file_momenta = false"),
    ('generator = "lattice"\n', (), "initial.file is read with initial.generator = 'file'"),
    ("rescale = true\n", [("box = [3.0, 2.5]\n", "")], "initial.rescale maps the frame's"),
])
def test_a_frame_that_does_not_fit_is_refused_in_one_line(first, lines, replace, message):
    with pytest.raises(ConfigError) as refused:
        check_config(parse_config(from_file(first, lines, replace)))
    assert message in str(refused.value) and "\n" not in str(refused.value)


def test_missing_or_foreign_files_and_stray_keys_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="initial.file: cannot read .*nowhere.h5 .*working"):
        check_config(parse_config(from_file(tmp_path / "nowhere.h5")))
    (tmp_path / "notes.h5").write_text("not HDF5")
    with pytest.raises(ConfigError, match="initial.file: .*notes.h5"):
        check_config(parse_config(from_file(tmp_path / "notes.h5")))
    with pytest.raises(ConfigError, match="initial.file is required when initial.generator"):
        check_config(parse_config(BOX.replace(ARRAYS, 'generator = "file"\n')))
    with pytest.raises(ConfigError, match="initial.frame, initial.file_momenta and "
                                          "initial.rescale apply to initial.file"):
        check_config(parse_config(BOX.replace("[initial]\n", "[initial]\nframe = 2\n")))
    # a config dumped with every field (as a sweep's points are) holds the defaults: accepted
    dumped = check_config(parse_config(BOX)).model_dump(exclude={"source_text"})
    check_config(type(check_config(parse_config(BOX))).model_validate(dumped))


def test_validate_reads_the_frame_and_names_a_bad_one(first, tmp_path):
    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text(from_file(first))
    bad.write_text(from_file(first, "frame = 9\n"))
    assert CliRunner().invoke(validate, [str(good)]).exit_code == 0
    refused = CliRunner().invoke(validate, [str(bad)])
    assert refused.exit_code == 1
    assert "initial.frame = 9 is beyond the 5 frames" in refused.output + refused.stderr
