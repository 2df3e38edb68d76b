"""run.neighbor_list and run.neighbor_skin through the CLI: a run that sums its pair forces over
a cell/neighbour list is the all-pairs run to round-off across list rebuilds, resumes bit for bit
(the list is rebuilt from the checkpoint state alone), and configs that cannot use a list are
refused in one line naming the field.

The runs share one periodic 2D crystal of 36 affine bodies (6 x 6 lattice in a 6 x 6 box), so
JAX compiles each chunk function once.
"""

import textwrap

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import neighbors as nb
from affinebody import pair_kernels
from affinebody._checks import enable_x64
from affinebody.checkpoint import checkpoint_path, load_checkpoint
from affinebody.config import (
    AUTO_NEIGHBOR_LIST_BODIES,
    INTEGRATOR_NAMES,
    SPLITTING_INTEGRATORS,
    ConfigError,
    build,
    check_config,
    parse_config,
    uses_neighbor_list,
)
from affinebody.h5md import read_trajectory
from affinebody.integrators import INTEGRATORS
from affinebody.state import State
from test_cli_sim import assert_bitwise_equal, datasets, invoke

SIDE, SKIN, STEPS = 6, 0.05, 200

CRYSTAL = textwrap.dedent(f'''
    [system]
    n = 2
    bodies = {SIDE * SIDE}
    box = [{float(SIDE)}, {float(SIDE)}]
    [body]
    mass = 1.0
    radius = 0.35
    [kinetic]
    translational = "dalembert"
    internal = "af-is"
    I = 0.5
    A = 0.1
    B = 0.05
    [[potential]]
    kind = "morse"
    depth = 1.0
    alpha = 3.0
    r0 = 1.0
    r_cut = 1.5
    [[potential]]
    kind = "pair"
    expr = "0.5 * exp(-D**2 / 4) * (M1 - 2)**2"
    r_cut = 1.5
    [[potential]]
    kind = "dilatation"
    stiffness = 5.0
    [[potential]]
    kind = "elastic"
    lam = 0.5
    mu = 1.0
    [initial]
    generator = "lattice"
    spacing = 1.0
    jitter = 0.03
    phi_noise = 0.1
    momentum_scale = 0.4
    phi_momentum_scale = 0.05
    seed = 3
    [run]
    dt = 0.01
    steps = {STEPS}
    every = 10
    checkpoint = 50
    neighbor_skin = {SKIN}
''')


def crystal(mode: str, text: str = CRYSTAL) -> str:
    return text + f'neighbor_list = "{mode}"\n'


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli_neighbors")
    for mode in ("on", "off"):
        (path / f"{mode}.toml").write_text(crystal(mode))
    return path


@pytest.fixture(scope="module")
def runs(folder):
    out = {}
    for mode in ("on", "off"):
        out[mode] = folder / f"{mode}.h5"
        result = invoke("run", folder / f"{mode}.toml", "-o", out[mode], "--quiet")
        assert result.exit_code == 0, result.stderr
    return out


def test_a_list_run_is_the_all_pairs_run_across_rebuilds(runs):
    with_list, all_pairs = datasets(runs["on"]), datasets(runs["off"])
    assert with_list.keys() == all_pairs.keys()
    for key, want in all_pairs.items():
        scale = max(1.0, float(np.max(np.abs(want))))
        np.testing.assert_allclose(with_list[key], want, rtol=0, atol=1e-10 * scale, err_msg=key)
    for path, mode in ((runs["on"], "on"), (runs["off"], "off")):
        with h5py.File(path, "r") as f:
            assert f["parameters/neighbor_list"][()].decode() == mode
            assert ("neighbor_skin" in f["parameters"]) == (mode == "on")
    traj = read_trajectory(runs["on"])
    assert traj.frames == STEPS // 10 + 1
    # the first list is built at x(0); it must be rebuilt once 2 max_K |x_K - x_K(0)| > skin
    # (neighbors.needs_rebuild): the run crossed several rebuilds
    moved = traj.x - traj.x[0]
    moved -= SIDE * np.round(moved / SIDE)  # minimum image in the box
    assert 2 * np.max(np.linalg.norm(moved, axis=-1)) > 4 * SKIN
    # real interacting motion: potential energy exchanged, total energy kept
    energy = traj.observables["total_energy"]
    assert np.ptp(traj.observables["potential_energy"]) > 0.05
    assert np.max(np.abs(energy - energy[0])) < 1e-3 * abs(energy[0])


def test_a_resumed_list_run_equals_the_uninterrupted_one_bit_for_bit(folder, runs):
    out = folder / "resumed.h5"
    first = invoke("run", folder / "on.toml", "-o", out, "--steps", 100, "--quiet")
    assert first.exit_code == 0, first.stderr
    assert load_checkpoint(checkpoint_path(out)).step == 100
    second = invoke("run", folder / "on.toml", "-o", out, "--resume", "--quiet")
    assert second.exit_code == 0, second.stderr
    assert_bitwise_equal(out, runs["on"])


def test_a_checkpoint_of_one_mode_does_not_resume_the_other(folder):
    # the list changes the motion at round-off: a resume must not mix the two modes
    on, off = (check_config(parse_config(crystal(m))) for m in ("on", "off"))
    assert on.hash() != off.hash()
    out = folder / "mixed.h5"
    first = invoke("run", folder / "off.toml", "-o", out, "--steps", 50, "--quiet")
    assert first.exit_code == 0, first.stderr
    mixed = invoke("run", folder / "on.toml", "-o", out, "--resume", "--quiet")
    assert mixed.exit_code == 1 and "different configuration" in mixed.stderr
    # the default keys keep the hashes of configs written before they existed
    plain = CRYSTAL.replace(f"neighbor_skin = {SKIN}\n", "")
    assert (parse_config(crystal("auto", plain)).hash()
            == parse_config(plain + "neighbor_skin = 0.3\n").hash() == parse_config(plain).hash())


@pytest.mark.parametrize(("change", "needs"), [
    (("box = [6.0, 6.0]\n", ""), "needs a periodic box: set system.box (got no box)"),
    (("checkpoint = 50\n", 'checkpoint = 50\nintegrator = "implicit-midpoint"\n'),
     "needs a splitting integrator, run.integrator = one of strang, yoshida4, suzuki4, "
     "yoshida6 (got 'implicit-midpoint')"),
    ((f"neighbor_skin = {SKIN}", "neighbor_skin = 1.6"),
     "needs r_cut + run.neighbor_skin <= half the shortest box edge: reduce run.neighbor_skin "
     "or enlarge system.box (got 1.5 + 1.6 > 3.0)"),
])
def test_on_without_what_a_list_needs_is_a_one_line_config_error(folder, change, needs):
    path = folder / "bad_on.toml"
    path.write_text(crystal("on", CRYSTAL.replace(*change)))
    for command in ("validate", "run"):
        result = invoke(command, path, "-o", folder / "bad_on.h5") if command == "run" else \
            invoke(command, path)
        assert result.exit_code == 1
        assert result.stderr.strip() == (f'config error: run.neighbor_list = "on" {needs}; or '
                                         f'set run.neighbor_list = "off"')
    assert not (folder / "bad_on.h5").exists()
    # with "off" the same config is fine (all pairs)
    assert not uses_neighbor_list(check_config(parse_config(
        crystal("off", CRYSTAL.replace(*change)))))


def test_on_without_pair_terms_is_refused():
    text = CRYSTAL.split("[[potential]]")
    no_pairs = text[0] + "[[potential]]" + text[3] + "[[potential]]" + text[4]
    with pytest.raises(ConfigError, match='run.neighbor_list = "on" needs pair potentials'):
        check_config(parse_config(crystal("on", no_pairs)))


@pytest.mark.parametrize("skin", ["0.0", "-0.1", "nan", "inf"])
def test_a_skin_that_is_not_positive_is_a_config_error(folder, skin):
    path = folder / "bad_skin.toml"
    path.write_text(crystal("off", CRYSTAL.replace(f"neighbor_skin = {SKIN}",
                                                   f"neighbor_skin = {skin}")))
    result = invoke("validate", path)
    assert result.exit_code == 1
    assert result.stderr.strip() == (f"config error: run.neighbor_skin must be a finite number "
                                     f"> 0 (got {float(skin)})")


def test_an_unknown_mode_is_a_config_error(folder):
    path = folder / "bad_mode.toml"
    path.write_text(crystal("always"))
    result = invoke("validate", path)
    assert result.exit_code == 1
    line = result.stderr.strip()
    assert line.startswith("config error: run.neighbor_list: must be ") and "'always'" in line


def big_crystal(side: int, integrator: str = "strang", box: bool = True) -> str:
    text = CRYSTAL.replace(f"bodies = {SIDE * SIDE}", f"bodies = {side * side}")
    text = text.replace(f"box = [{float(SIDE)}, {float(SIDE)}]",
                        f"box = [{float(side)}, {float(side)}]" if box else "")
    return text.replace("checkpoint = 50\n", f'checkpoint = 50\nintegrator = "{integrator}"\n')


def test_auto_uses_a_list_from_500_bodies_when_the_system_allows_one():
    assert AUTO_NEIGHBOR_LIST_BODIES == 500
    side = 23  # 529 bodies
    assert side * side >= 500 > (side - 1) ** 2
    for integrator in INTEGRATOR_NAMES:
        if integrator == "nonholonomic-rattle":
            continue  # needs [constraints]: refused before the list is considered
        config = check_config(parse_config(big_crystal(side, integrator)))
        # exactly the integrators with a neighbour-list step
        assert uses_neighbor_list(config) == (integrator in SPLITTING_INTEGRATORS) == INTEGRATORS[
            integrator].uses_neighbor_lists
    assert not uses_neighbor_list(check_config(parse_config(big_crystal(side - 1))))
    assert not uses_neighbor_list(check_config(parse_config(big_crystal(side, box=False))))


def test_the_list_at_a_checkpoint_depends_on_the_state_alone_and_grows_to_fit():
    # a base spec allocated for a sparse start, then a clustered state with far more pairs:
    # list_at grows the capacities by the one capacity rule, whatever spec was used before
    enable_x64()
    built = build(check_config(parse_config(crystal("on"))))
    space, cutoff, variable = built.system.neighbor_range()
    assert (cutoff, variable) == (1.5, "r")
    base, _ = nb.allocate(space, built.state.x, built.state.phi, cutoff, variable, SKIN)
    rng = np.random.default_rng(5)
    x = 2.0 + 1.5 * rng.uniform(size=built.state.x.shape)  # 36 bodies in a 1.5 x 1.5 square
    clustered = State(jnp.asarray(x), *built.state[1:])
    spec, lst = nb.list_at(base, clustered.x, clustered.phi)
    assert int(lst.overflow) == 0 and spec.capacity > base.capacity
    assert spec.cell_capacity >= base.cell_capacity  # the host build (CPU) has no cell limit
    want = nb.brute_force_pairs(space, x, cutoff + SKIN)
    assert len(want) > base.capacity
    got = nb.pairs_of(lst)
    assert {tuple(p) for p in got} == {tuple(p) for p in want} and len(got) == len(want)
    # called again (as a resumed run does): the same spec and list, bit for bit
    again, lst2 = nb.list_at(base, clustered.x, clustered.phi)
    assert again == spec
    assert all(np.array_equal(a, b) for a, b in zip(lst, lst2, strict=True))


def test_build_with_a_list_never_sums_over_all_pairs(monkeypatch):
    """Set-up is O(N): with a list, the initial energy (and its finiteness check) is summed
    over the list, and equals the all-pairs energy; the all-pairs path is never taken."""
    from affinebody.potentials import PairTerm

    enable_x64()
    config = check_config(parse_config(crystal("on")))
    all_pairs = build(check_config(parse_config(crystal("off"))))
    reference = float(all_pairs.system.hamiltonian(all_pairs.state))

    def refuse(*_args, **_kwargs):
        raise AssertionError("the all-pairs sum was called during an O(N) set-up")

    monkeypatch.setattr(PairTerm, "pair_energies", refuse)
    built = build(config)
    spec, lst = built.neighbors
    assert built.neighbor_list and spec.bodies == SIDE * SIDE
    energy = float(built.system.hamiltonian(built.state, lst))
    assert energy == pytest.approx(reference, rel=1e-12)
    assert set(built.timings) >= {"initial state", "neighbour list", "initial energy"}


def test_verbose_run_prints_the_phases_and_the_rate_without_compilation(folder):
    out = folder / "verbose.h5"
    result = invoke("run", folder / "on.toml", "-o", out, "--steps", 20, "--verbose")
    assert result.exit_code == 0, result.stderr
    text = result.stdout
    for phase in ("load and validate", "set-up: neighbour list", "set-up: initial energy",
                  "integrate", "output"):
        assert phase in text, text
    # and which kernel summed the pair forces: the backend's (the host kernel on a CPU)
    kernel = "host kernel (Numba" if pair_kernels.host_kernel_in_use() else "JAX kernel"
    assert f"pair forces: neighbour list, {kernel}" in text, text
    # the summary tells compiling and integrating apart; both are positive numbers
    line = next(s for s in text.splitlines() if s.startswith("20 steps in"))
    compiling = float(line.split("compiling ")[1].split(" s")[0])
    integrating = float(line.split("integrating ")[1].split(" s")[0])
    total = float(line.split("steps in ")[1].split(" s")[0])
    assert 0 <= compiling and 0 < integrating and compiling + integrating <= total


SWEEP_TABLE = textwrap.dedent('''
    [sweep]
    samples = 2
    batch = 2
    seed = 11
    x_velocity = "normal"
    x_velocity_scale = 1.0
''')


def sweep_config(mode: str):
    # spacing 1.2: the diagonal neighbours (1.70) lie just outside the list radius (1.55), so
    # moving bodies bring new pairs into it
    wide = float(1.2 * SIDE)
    text = (crystal(mode).replace(f"steps = {STEPS}", "steps = 30")
            .replace("spacing = 1.0", "spacing = 1.2")
            .replace(f"box = [{float(SIDE)}, {float(SIDE)}]", f"box = [{wide}, {wide}]"))
    return check_config(parse_config(text + SWEEP_TABLE))


@pytest.fixture(scope="module")
def all_pairs_sweep():
    from affinebody.sweep import run_sweep

    enable_x64()
    return run_sweep(sweep_config("off"), workers=0)


def test_sweep_samples_use_the_list_and_equal_the_all_pairs_samples(all_pairs_sweep,
                                                                    monkeypatch):
    """The samples of a sweep run the driver's step with the run's neighbour list (O(N) per
    step): never the all-pairs sum, and the same motion as the all-pairs sweep."""
    from affinebody import sweep
    from affinebody.potentials import PairTerm

    def refuse(*_args, **_kwargs):
        raise AssertionError("a sweep sample summed over all pairs")

    monkeypatch.setattr(PairTerm, "pair_energies", refuse)
    sweep._prepare.cache_clear()
    listed = sweep.run_sweep(sweep_config("on"), workers=0)
    sweep._prepare.cache_clear()
    assert list(listed.status.ravel()) == list(all_pairs_sweep.status.ravel()) == ["bounded"] * 2
    for key in ("initial_energy", "final_energy", "max_spread", "max_relative_volume"):
        np.testing.assert_allclose(listed.samples[key], all_pairs_sweep.samples[key],
                                   rtol=1e-10, err_msg=key)


def test_a_sweep_sample_whose_list_overflows_is_repeated_with_room(all_pairs_sweep,
                                                                   monkeypatch):
    """A list allocated with no room overflows as the bodies move: the sample is repeated with
    the list reallocated by the one capacity policy, and ends as the all-pairs sample does."""
    from affinebody import sweep

    real_allocate, real_reallocate = nb.allocate, nb.reallocate
    reallocations = []

    def tight(*args, **kwargs):  # the set-up's list: exactly full, no room to move
        if "capacity" not in kwargs:
            _, full = real_allocate(*args, **kwargs)
            kwargs["capacity"] = int(full.count)
        return real_allocate(*args, **kwargs)

    def counted(*args, **kwargs):
        reallocations.append(kwargs["flags"])
        return real_reallocate(*args, **kwargs)

    monkeypatch.setattr(nb, "allocate", tight)
    monkeypatch.setattr(nb, "reallocate", counted)
    sweep._prepare.cache_clear()
    listed = sweep.run_sweep(sweep_config("on"), workers=0)
    sweep._prepare.cache_clear()
    assert reallocations and all(f & nb.PAIR_OVERFLOW for f in reallocations)
    assert list(listed.status.ravel()) == ["bounded"] * 2
    np.testing.assert_allclose(listed.samples["final_energy"],
                               all_pairs_sweep.samples["final_energy"], rtol=1e-10)


HARMONIC = '''[[potential]]
kind = "harmonic-invariants"
stiffness = 0.5
r_cut = 1.5
'''
BAROSTAT = '''[barostat]
pressure = 0.1
tau = 2.0
compressibility = 1.0
temperature = 0.3
'''


def test_xla_gets_one_thread_only_where_the_host_kernels_do_all_the_parallel_work():
    """The rule of ``runner.host_kernels_do_the_threading``: a list and every pair term through
    the fused host kernel (config expressions and the Morse family); a pair term whose f XLA
    evaluates between two host calls (harmonic-invariants) or all pairs leave XLA its
    threads; a barostat does not (its virial pass runs the fused kernel too)."""
    from affinebody.runner import host_kernels_do_the_threading as decides

    config = lambda mode, text: check_config(parse_config(crystal(mode, text), "c.toml"))  # noqa: E731
    assert decides(config("on", CRYSTAL))  # morse and an expression
    assert not decides(config("on", CRYSTAL.replace("[initial]", HARMONIC + "[initial]")))
    assert not decides(config("off", CRYSTAL))  # all pairs, in XLA
    assert decides(config("on", CRYSTAL.replace("[initial]", BAROSTAT + "[initial]")))
    assert not decides(config("on", CRYSTAL.replace("[initial]", HARMONIC + BAROSTAT
                                                    + "[initial]")))


def test_prepare_process_gives_xla_one_thread_where_the_host_kernels_take_every_core(
        monkeypatch):
    """``runner.prepare_process`` sets PJRT_NPROC=1 for such a run when the host kernels'
    threads take every core the process may use (two here), not on a larger machine, where
    XLA's pool threads have cores of their own."""
    import os

    from affinebody import _host, runner

    config = check_config(parse_config(crystal("on"), "c.toml"))
    for name in ("PJRT_NPROC", "NPROC"):
        monkeypatch.setenv(name, "")  # unset for XLA; restored after the test
    monkeypatch.setattr(_host, "cores", lambda: 16)
    assert not runner.prepare_process(config)
    assert os.environ["PJRT_NPROC"] == ""
    monkeypatch.setattr(_host, "cores", lambda: _host.PARTS)
    assert runner.prepare_process(config)
    assert os.environ["PJRT_NPROC"] == "1"
