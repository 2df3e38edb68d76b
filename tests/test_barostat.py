"""Stochastic cell rescaling: an ideal gas follows the isobaric law <V> = (N + 1) kT / P of the
ensemble exp(-(H + P V)/kT) dV (isotropic, and the volume of the anisotropic orthorhombic
coupling); the Ito drift of the triclinic coupling is the divergence worked out by hand; a
run continued from its last frame repeats the uninterrupted one bit for bit."""

import textwrap
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import barostat
from affinebody.integrators import get_integrator
from affinebody.kinetic import DAlembert, DAlembertTranslational, KineticEnergy
from affinebody.space import orthorhombic, triclinic
from affinebody.state import State
from affinebody.system import HamiltonianSystem
from tracking import compilations

N, KT, P0, GAMMA = 4, 1.0, 1.0, 5.0


def langevin_momenta(system, state, key, dt):
    """Exact Ornstein-Uhlenbeck step of the centres' momenta (unit mass) at temperature KT."""
    c = jnp.exp(-GAMMA * dt)
    noise = jax.random.normal(key, state.p.shape)
    return state._replace(p=c * state.p + jnp.sqrt((1 - c * c) * KT) * noise)


def ideal_gas(n=2):
    system = HamiltonianSystem(KineticEnergy(DAlembertTranslational(1.0), DAlembert(jnp.eye(n))))
    rng = np.random.default_rng(0)
    state = State(jnp.asarray(rng.uniform(0, 2, (N, n))), jnp.broadcast_to(jnp.eye(n), (N, n, n)),
                  jnp.asarray(rng.normal(size=(N, n))), jnp.zeros((N, n, n)))
    return system, state, orthorhombic((2.0, 2.5, 2.2)[:n])


@pytest.mark.parametrize("coupling,interval", [("isotropic", 1), ("anisotropic", 1),
                                               ("isotropic", 4)])
def test_ideal_gas_follows_the_isobaric_law(coupling, interval):
    """With a move every ``interval`` steps, dt / interval keeps the moves' length (the
    barostat's discretisation error; docs/pressure.md) and the time span those of interval 1."""
    system, state, space = ideal_gas()
    baro = barostat.StochasticCellRescaling(((P0, 0.0), (0.0, P0)), tau=0.5,
                                            compressibility=1.0, temperature=KT,
                                            coupling=coupling, interval=interval)
    trajectory = barostat.run(system, state, space, baro, 0.01 / interval, 40_000 * interval,
                              seed=3, every=10 * interval, thermostat=langevin_momenta)
    volume = trajectory.observables["volume"][400:]
    blocks = volume[: len(volume) // 20 * 20].reshape(20, -1).mean(axis=1)
    error = blocks.std(ddof=1) / np.sqrt(len(blocks))
    expected = (N + 1) * KT / P0
    assert abs(volume.mean() - expected) < 4 * error + 0.01 * expected, (volume.mean(), error)
    # the test can tell N kT / P = 4 from (N + 1) kT / P = 5: its tolerance is below kT / P
    assert 4 * error + 0.01 * expected < 0.8 * KT / P0, error
    np.testing.assert_allclose(trajectory.observables["volume"],
                               np.linalg.det(trajectory.cells), rtol=1e-12)
    # positions moved with the box: the fractional coordinates stay in range of the cell
    if coupling == "anisotropic":  # an orthorhombic box stays orthorhombic
        assert np.all(trajectory.cells[:, 0, 1] == 0) and np.all(trajectory.cells[:, 1, 0] == 0)


@pytest.mark.parametrize("coupling,dt", [("isotropic", 0.1), ("anisotropic", 0.04)])
def test_the_metropolis_test_makes_coarse_moves_sample_the_isobaric_law(coupling, dt):
    """Moves of 10x (isotropic) and 4x the length of the test above, rate * dt = 0.2 and 0.08:
    the plain Euler-Maruyama move leaves the isobaric law (the isotropic box blows up once,
    the anisotropic one collapses an edge and the run stops), while with the
    Metropolis-Hastings test the ideal gas has <V> = (N + 1) kT / P0 within the statistical
    error alone (the particle part is exact here: free drift, exact Ornstein-Uhlenbeck
    momenta). The same seed and the compiled loop of the test above for the plain move."""
    system, state, space = ideal_gas()
    expected = (N + 1) * KT / P0
    runs = {}
    for metropolis in (False, True):
        baro = barostat.StochasticCellRescaling(((P0, 0.0), (0.0, P0)), tau=0.5,
                                                compressibility=1.0, temperature=KT,
                                                coupling=coupling, metropolis=metropolis)
        runs[metropolis] = barostat.run(system, state, space, baro, dt, 40_000, seed=3,
                                        every=10, thermostat=langevin_momenta)
    tested = runs[True]
    assert tested.failed_step is None
    volume = tested.observables["volume"][400:]
    blocks = volume[: len(volume) // 20 * 20].reshape(20, -1).mean(axis=1)
    error = blocks.std(ddof=1) / np.sqrt(len(blocks))
    assert abs(volume.mean() - expected) < 4 * error, (volume.mean(), error)
    assert 4 * error < 0.2 * KT / P0, error
    rejected = tested.observables["rejected_moves"]
    assert rejected[0] == 0 and np.all(rejected <= 10)  # counted over each frame's 10 moves
    assert 0.02 < rejected.sum() / 40_000 < 0.3
    plain = runs[False]
    assert "rejected_moves" not in plain.observables
    plain_volume = plain.observables["volume"][400:]
    assert plain.failed_step is not None or abs(plain_volume.mean() - expected) > 40 * error


def test_log_proposal_is_the_density_of_the_drawn_move():
    """``propose`` draws the new cell from a Gaussian whose log density ``log_proposal``
    gives: for the triclinic coupling, in the cell's moving entries q = (h11, h12, h22) the
    move is q + (d delta H)[q] with d delta = drift + noise, so q' ~ N(mean, s^2 J J^T), J the
    linear map noise -> (noise H)[q] (written out here, scipy's normal density; the drift
    with the Ito drift of the test below); isotropic:
    eps' - eps = ln det mu ~ N((beta_T/tau)(P - P0) dt, 2 kT beta_T dt / (V tau)), P of the
    free bodies (unit masses) sum p p^T / V. A wrong Jacobian or variance would bias the
    Metropolis test."""
    from scipy.stats import multivariate_normal, norm

    system, state, _ = ideal_gas()
    h = np.array([[2.1, 0.4], [0.0, 1.7]])
    space = triclinic(h)
    rows, cols = np.nonzero(np.triu(np.ones((2, 2))))
    unit = np.zeros((3, 2, 2))
    unit[np.arange(3), rows, cols] = 1.0
    jac = np.stack([(e @ h)[rows, cols] for e in unit], axis=1)  # noise entries -> q
    p_inst = np.asarray(state.p).T @ np.asarray(state.p) / np.linalg.det(h)
    dt, rate, kt = 0.03, 1.3 / 0.7, 0.9
    s = np.sqrt(2 * kt * rate / np.linalg.det(h) * dt)
    for coupling in ("anisotropic", "isotropic"):
        baro = barostat.StochasticCellRescaling(((0.4, 0.1), (0.1, 0.6)), tau=0.7,
                                                compressibility=1.3, temperature=kt,
                                                coupling=coupling, metropolis=True)

        @jax.jit  # op by op, the Ito drift's nested jacfwd takes seconds
        def draw(key, baro=baro):
            moved, new_cell, _, logq = baro.propose(system, state, jnp.asarray(h), space, key,
                                                    dt)
            mu = new_cell @ jnp.linalg.inv(h)
            return moved.x, new_cell, logq, baro.log_proposal(h, p_inst, mu, space, dt)

        for seed in range(3):
            x, new_cell, logq, again = map(np.asarray, draw(jax.random.PRNGKey(seed)))
            mu = new_cell @ np.linalg.inv(h)
            np.testing.assert_allclose(x, state.x @ mu.T, rtol=1e-12)
            np.testing.assert_allclose(logq, again, rtol=1e-12)
            if coupling == "isotropic":
                mean = rate * (np.trace(p_inst) - 1.0) / 2 * dt
                exact = norm.logpdf(np.log(np.linalg.det(mu)), mean, s)
            else:  # the strain's drift: stress, and the Ito drift worked out by hand (below)
                c = kt * rate
                ito = np.array([[2 * c / h[1, 1], 2 * c * h[0, 1] / (h[0, 0] * h[1, 1])],
                                [0.0, c / h[0, 0]]]) @ np.linalg.inv(h)
                stress = np.triu(rate * (p_inst - np.array([[0.4, 0.1], [0.1, 0.6]])).T)
                mean = h[rows, cols] + (((stress + ito) * dt) @ h)[rows, cols]
                exact = multivariate_normal.logpdf(new_cell[rows, cols], mean,
                                                   s * s * jac @ jac.T)
            np.testing.assert_allclose(logq, exact, rtol=1e-10)


def test_move_size_is_the_mean_and_spread_of_the_drawn_moves():
    """``move_size`` (what a stopped run's advice quotes) against the moves ``propose`` draws:
    ln det mu over 4000 isotropic draws has mean ``drift`` and standard deviation ``noise``
    (moves every 3 steps: of length 3 dt); short moves give no advice, long ones name the
    parameters with their values."""
    system, state, space = ideal_gas()
    h = jnp.asarray(space.matrix)
    dt = 0.02
    baro = barostat.StochasticCellRescaling(((0.4, 0.0), (0.0, 0.4)), tau=0.7,
                                            compressibility=1.3, temperature=0.9, interval=3)
    p_inst = np.asarray(state.p).T @ np.asarray(state.p) / np.linalg.det(space.matrix)
    drift, noise = baro.move_size(h, p_inst, space, dt)

    @jax.jit
    @jax.vmap
    def log_volume_change(key):
        _, cell, _, _ = baro.propose(system, state, h, space, key, baro.interval * dt)
        return jnp.log(jnp.linalg.det(cell) / jnp.linalg.det(h))

    draws = np.asarray(log_volume_change(jax.random.split(jax.random.PRNGKey(5), 4000)))
    assert abs(draws.mean() - drift) < 4 * noise / np.sqrt(len(draws))
    assert abs(draws.std() / noise - 1) < 4 / np.sqrt(2 * len(draws))
    assert abs(drift) > 0.01 and 0.05 < noise < barostat.LARGE_MOVE  # a real test of both
    assert barostat.stop_advice(baro, h, p_inst, space, dt) is None
    wild = barostat.StochasticCellRescaling(((0.4, 0.0), (0.0, 0.4)), tau=0.7,
                                            compressibility=1e6, temperature=0.9)
    advice = barostat.stop_advice(wild, h, p_inst, space, dt)
    assert "barostat.compressibility 1e+06" in advice and "from the noise" in advice


def test_an_npt_run_stopped_by_its_barostat_names_the_parameter_at_fault(tmp_path):
    """A compressibility of 1e20 throws the box to infinity at the first move: the run stops
    (frames before it kept) and says which parameter, with its value, instead of only the
    general advice (found by fuzzing the CLI)."""
    from affinebody.config import check_config, parse_config
    from affinebody.h5md import read_trajectory
    from affinebody.runner import SimulationStopped, run_simulation

    text = NPT_CONFIG.replace("compressibility = 1.0", "compressibility = 1e20")
    with pytest.raises(SimulationStopped, match=r"barostat.compressibility 1e\+20 / tau 2 x "
                                                r"\(P - P0\)") as stopped:
        run_simulation(check_config(parse_config(text)), tmp_path / "npt.h5")
    assert "body" not in str(stopped.value)  # the box's stop, no one body's (said "body 0")
    assert read_trajectory(tmp_path / "npt.h5").frames >= 1


def test_a_move_every_interval_steps_spans_interval_dt():
    """Bodies at rest and no forces: P = 0, so each move is the deterministic
    d eps = -(beta_T / tau) P0 (its length) up to a noise of kT = 1e-30. With interval = 4
    the box moves only after the steps k (counted from first_step) with (k + 1) % 4 == 0,
    no work is booked in between, and after 40 steps ln V has moved as far as with a move
    every step: -(beta_T / tau) P0 * 40 dt. A move of length dt would get a quarter of it."""
    system, state, space = ideal_gas()
    state = state._replace(p=jnp.zeros_like(state.p))
    dt, rate = 0.01, 1.3 / 0.5
    volumes = {}
    for interval in (1, 4):
        baro = barostat.c_rescale(P0, 2, tau=0.5, compressibility=1.3, temperature=1e-30,
                                  interval=interval)
        trajectory = barostat.run(system, state, space, baro, dt, 40, seed=1, first_step=6,
                                  every=1)
        volumes[interval] = volume = trajectory.observables["volume"]
        moved = np.flatnonzero(np.diff(volume)) + 1  # frames after a move
        steps = 6 + moved  # the global step count after the frame's last step
        expected = np.arange(1, 41) if interval == 1 else np.arange(8, 47, 4) - 6
        np.testing.assert_array_equal(moved, expected)
        assert np.all(steps % interval == 0)
        still = np.setdiff1d(np.arange(1, 41), moved)
        np.testing.assert_array_equal(np.diff(trajectory.observables["work"])[still - 1], 0.0)
        # bodies at rest stay at rest in fractional coordinates
        fractional = np.einsum("fab,fkb->fka", np.linalg.inv(trajectory.cells),
                               trajectory.states.x)
        np.testing.assert_allclose(fractional, np.broadcast_to(fractional[0], fractional.shape),
                                   rtol=1e-12)
    # ln V falls by rate P0 dt a step, or by 4 rate P0 dt at each move of interval 4: frame f
    # (global step count 6 + f) follows (6 + f) // 4 - 1 moves
    exact = np.log(volumes[1][0]) - rate * P0 * dt * np.arange(41)
    np.testing.assert_allclose(np.log(volumes[1]), exact, rtol=0, atol=1e-12)
    moves = (6 + np.arange(41)) // 4 - 1
    np.testing.assert_allclose(np.log(volumes[4]), exact[4 * moves], rtol=0, atol=1e-12)
    assert moves[-1] == 10


def test_ensembles_of_npt_runs_move_their_boxes_as_single_runs_do():
    """``barostat.advance`` vmapped over seeds (the samples of ``affinebody sweep``) with a move
    every 3 steps ends where each seed's ``barostat.run`` ends."""
    system, state, space = ideal_gas()
    baro = barostat.c_rescale(P0, 2, tau=0.5, compressibility=1.0, temperature=KT, interval=3)
    cell = jnp.asarray(space.matrix)
    method = get_integrator("strang")

    def sample(seed):
        return barostat.advance(system, state, cell, jnp.asarray(2), seed, 0.01, steps=13,
                                method=method, barostat=baro, space=space,
                                thermostat=langevin_momenta)

    seeds = jnp.asarray([3, 8])
    ends, cells, *_ = jax.jit(jax.vmap(sample))(seeds)
    for k, seed in enumerate((3, 8)):
        single = barostat.run(system, state, space, baro, 0.01, 13, seed=seed, first_step=2,
                              thermostat=langevin_momenta)
        np.testing.assert_allclose(cells[k], single.cells[-1], rtol=1e-13)
        np.testing.assert_allclose(ends.x[k], single.final_state.x, rtol=1e-13)
    assert abs(np.linalg.det(cells[0]) - np.linalg.det(cells[1])) > 1e-3  # the seeds differ


def test_triclinic_ito_drift_is_the_divergence_of_the_mobility():
    """n = 2, q = (h11, h12, h22), M = c/V J J^T: div M = (2c/h22, 2c h12/(h11 h22), c/h11)
    (worked by hand), as a strain increment dh H^-1."""
    baro = barostat.StochasticCellRescaling(((P0, 0.0), (0.0, P0)), tau=0.7,
                                            compressibility=1.3, temperature=0.9,
                                            coupling="anisotropic")
    h = jnp.asarray([[2.1, 0.4], [0.0, 1.7]])
    c = 0.9 * 1.3 / 0.7
    dh = np.array([[2 * c / 1.7, 2 * c * 0.4 / (2.1 * 1.7)], [0.0, c / 2.1]])
    got = np.asarray(jax.jit(lambda a: baro._ito_drift(a, np.triu(np.ones((2, 2)))))(h))
    np.testing.assert_allclose(got, dh @ np.linalg.inv(np.asarray(h)), rtol=1e-12, atol=1e-14)


def test_one_line_errors():
    with pytest.raises(ValueError, match="barostat.tau must be > 0"):
        barostat.StochasticCellRescaling(((1.0,),), tau=0.0, compressibility=1.0,
                                         temperature=1.0)
    with pytest.raises(ValueError, match="barostat.coupling must be one of"):
        barostat.StochasticCellRescaling(((1.0,),), tau=1.0, compressibility=1.0,
                                         temperature=1.0, coupling="semi")


NPT_CONFIG = """
[system]
n = 2
bodies = 4
box = [4.0, 4.2]
[body]
mass = 1.0
inertia = 0.5
[kinetic]
translational = "dalembert"
internal = "dalembert"
[[potential]]
kind = "pair"
expr = "exp(-D**2) + 0.5 * exp(-r**2)"
r_cut = 1.0
[[potential]]
kind = "one-body"
expr = "2*(det - 1)**2 + 0.5*(trG - 2)**2"
[initial]
x = [[0.2, 0.3], [2.2, 0.2], [0.4, 2.3], [2.4, 2.1]]
momentum = [[0.5, 0.0], [0.0, -0.5], [-0.5, 0.5], [0.0, 0.0]]
[run]
dt = 0.01
steps = 400
every = 50
checkpoint = 200
seed = 11
[barostat]
pressure = 0.1
tau = 2.0
compressibility = 1.0
temperature = 0.3
coupling = "anisotropic"
"""


def test_npt_run_writes_the_box_pressure_and_volume_and_resumes_bit_for_bit(tmp_path):
    from affinebody.config import check_config, parse_config
    from affinebody.h5md import read_trajectory
    from affinebody.runner import run_simulation

    # NPT as users run it: a [thermostat] for the bodies, whose kT the barostat takes
    text = NPT_CONFIG.replace("temperature = 0.3\n", "") + (
        '[thermostat]\nkind = "langevin"\ntemperature = 0.3\nfriction = 1.0\nseed = 5\n')
    config = check_config(parse_config(text))
    summary = run_simulation(config, tmp_path / "whole.h5")
    run_simulation(config, tmp_path / "resumed.h5", steps=200)
    run_simulation(config, tmp_path / "resumed.h5", resume=True)
    whole, resumed = (read_trajectory(tmp_path / f"{k}.h5") for k in ("whole", "resumed"))
    assert whole.frames == 9
    for name in ("x", "phi", "p", "pi", "boxes", "step", "time"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name))
    for name, value in whole.observables.items():
        np.testing.assert_array_equal(resumed.observables[name], value)
    # the box moves with the barostat (each edge on its own), volume = det of the cell
    assert np.all(np.ptp(whole.boxes, axis=0) > 1e-4)
    assert np.ptp(whole.boxes[:, 0] / whole.boxes[:, 1]) > 1e-4  # anisotropic: not one scale
    np.testing.assert_allclose(whole.observables["volume"], np.prod(whole.boxes, axis=1),
                               rtol=1e-12)
    assert whole.observables["pressure"].shape == (9, 2, 2)
    # the summary's energies are the conserved effective energy's, and it says so (it said
    # "energy", the word for H in a run without a bath)
    effective = whole.observables["effective_energy"]
    assert (summary.initial_energy, summary.final_energy) == (effective[0], effective[-1])
    assert summary.lines()[2].startswith("effective energy ")
    from affinebody.plotting import plot_all

    written = plot_all(whole, tmp_path / "plots")
    assert (tmp_path / "plots" / "pressure.png") in written
    assert (tmp_path / "plots" / "pressure.png").stat().st_size > 10_000


def test_barostat_config_errors_are_one_line():
    from affinebody.config import ConfigError, check_config, parse_config

    cases = {
        "tau = 2.0": ("tau = -1.0", "barostat.tau must be > 0"),
        "pressure = 0.1": ("pressure = [[1.0, 0.0]]", "barostat.pressure"),
        # P0 V beyond float64: validate passed it, the run stopped at once (fuzzing the CLI)
        "pressure = 0.1\n": ("pressure = -1e308\n", "barostat.pressure = -1e\\+308 times the "
                                                   "box volume 16.8 is beyond float64"),
        "box = [4.0, 4.2]\n": ("", "barostat needs a periodic box"),
        'coupling = "anisotropic"': ('coupling = "sheared"', "barostat.coupling"),
        "temperature = 0.3\n": ("", "barostat.temperature is required without a"),
        "tau = 2.0\n": ("tau = 2.0\ninterval = 0\n", "barostat.interval"),
        "tau = 2.0\ncompressibility": ("tau = 0.05\ninterval = 10\ncompressibility",
                                       "barostat.interval \\* run.dt must not exceed "
                                       "barostat.tau"),
        'coupling = "anisotropic"\n': ('coupling = "anisotropic"\n[thermostat]\nkind = '
                                       '"bussi"\ntemperature = 0.5\ntau = 1.0\n',
                                       "barostat.temperature must equal thermostat.temperature"),
    }
    for old, (new, message) in cases.items():
        with pytest.raises(ConfigError, match=message) as err:
            check_config(parse_config(NPT_CONFIG.replace(old, new)))
        assert "\n" not in str(err.value)
    from affinebody.sweep import SweepSpec

    with pytest.raises(ConfigError, match="a \\[barostat\\] needs a \\[thermostat\\]"):
        SweepSpec.from_config(check_config(parse_config(NPT_CONFIG)))


#: 16 bodies in 2D squeezed from spacing 1.2 to about 0.9 by the barostat: the neighbour list's
#: cells outgrow the box in the first steps and are reallocated (a coarser grid)
SQUEEZED_CRYSTAL = """
[system]
n = 2
bodies = 16
box = [4.8, 4.8]
[body]
mass = 1.0
inertia = [[1.0, 0.0], [0.0, 1.0]]
[kinetic]
translational = "dalembert"
internal = "dalembert"
[[potential]]
kind = "pair"
expr = "(1 - exp(-3*(r - 1)))**2 - 1"
r_cut = 1.3
[[potential]]
kind = "one-body"
expr = "5*(det - 1)**2 + 0.5*(trG - 2)**2"
[initial]
generator = "lattice"
spacing = 1.2
phi_noise = 0.02
[run]
dt = 0.005
steps = 200
every = 10
checkpoint = 50
seed = 1
neighbor_list = "on"
neighbor_skin = 0.1
[thermostat]
kind = "langevin"
temperature = 0.1
friction = 1.0
seed = 2
[barostat]
pressure = 2.0
tau = 0.2
compressibility = 0.2
interval = 3
"""


def test_npt_run_with_a_neighbour_list_resumes_bit_for_bit(tmp_path):
    """The list follows the box and is rebuilt from the state and the cell at checkpoints, so
    a resumed run repeats the uninterrupted one (its agreement with all pairs:
    tests/test_npt_neighbors.py). The box moves every 3 steps, counted from the start of the
    run: the cut at step 100 falls between two moves. The list was reallocated for the
    shrinking box in the middle of the first chunk of steps, before the cut: the rest of the
    chunk runs through the chunk's program, and the list's sizes go through the checkpoints
    (and into the resumed run), so neither run compiles its loop for other sizes or lengths
    again: twice in all, the first list and the reallocated one (three when the rest of the
    chunk had a program of its own, more when every checkpoint took the config's list's
    sizes). The moves pass a Metropolis test (``metropolis = true``): a move whose list
    overflowed is kept unjudged, reallocated and judged when run again, and the file counts
    the rejected moves, as many in the resumed run as in the whole one."""
    from affinebody.checkpoint import checkpoint_path, load_checkpoint
    from affinebody.config import build, check_config, parse_config, uses_neighbor_list
    from affinebody.h5md import read_trajectory
    from affinebody.neighbors import sizes
    from affinebody.runner import run_simulation

    config = check_config(parse_config(SQUEEZED_CRYSTAL + "metropolis = true\n"))
    assert uses_neighbor_list(config)
    first_sizes = sizes(build(config).neighbors[0])
    with compilations("_npt") as compiled, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        whole_run = run_simulation(config, tmp_path / "whole.h5")
        assert len(compiled) <= 2
        first_part = run_simulation(config, tmp_path / "resumed.h5", steps=100)
        kept = load_checkpoint(checkpoint_path(tmp_path / "resumed.h5")).neighbor_sizes
        assert tuple(kept["grid"]) != first_sizes["grid"]  # reallocated before the cut
        second_part = run_simulation(config, tmp_path / "resumed.h5", resume=True)
    assert len(compiled) <= 2  # the whole run's programs
    # its moves are as long as the plain test's below, but tested: no warning about them
    assert not [w for w in caught if "barostat moves" in str(w.message)]
    # moves after steps 3, 6, ..., 198: 66, of which 33 before the cut at step 100
    rejected, moves = whole_run.barostat_moves
    assert moves == 66 and (first_part.barostat_moves[1], second_part.barostat_moves[1]) == (
        33, 33)
    assert first_part.barostat_moves[0] + second_part.barostat_moves[0] == rejected
    assert any(line.startswith(f"barostat: {rejected} of 66 moves rejected")
               for line in whole_run.lines())
    whole, resumed = (read_trajectory(tmp_path / f"{k}.h5") for k in ("whole", "resumed"))
    assert whole.frames == 21 and whole.boxes[-1, 0] < 0.8 * whole.boxes[0, 0]  # squeezed
    for name in ("x", "phi", "p", "pi", "boxes"):
        np.testing.assert_array_equal(getattr(resumed, name), getattr(whole, name))
    for name, value in whole.observables.items():
        np.testing.assert_array_equal(resumed.observables[name], value)
    assert whole.observables["rejected_moves"].sum() == rejected


def pressure_along_the_move(system, state, cell, mass=1.0):
    """P(eps) = (2 T_c / n - dU/d eps) / V after the isotropic move by eps in ln V, from
    autodiff of the all-pairs energy in the scaled cell (not the virial's code): the
    independent reference of barostat.move_modulus (T_c the centres' kinetic energy)."""
    n = cell.shape[-1]
    cell = jnp.asarray(cell)

    def energy(eps):
        mu = jnp.exp(eps / n)
        return system.potential.energy(state.x * mu, state.phi, None, cell * mu)

    def p_of(eps):
        kinetic = jnp.sum(state.p**2) / mass * jnp.exp(-2 * eps / n)  # 2 T_c
        return (kinetic / n - jax.grad(energy)(eps)) / (jnp.linalg.det(cell) * jnp.exp(eps))

    return p_of


def test_move_modulus_of_an_ideal_gas_is_one_plus_two_over_n_times_its_pressure():
    """K = -dP/d ln V along the move x -> mu x, p -> p / mu, H -> mu H: P = 2 T / (n V) goes
    as V^-(1 + 2/n). (A crystal's, against autodiff: the run test below.)"""
    for n in (2, 3):
        system, state, space = ideal_gas(n)
        p = float(jnp.sum(state.p**2)) / (n * float(np.prod(np.diag(space.matrix))))
        k = barostat.move_modulus(system, state, None, space)
        assert k == pytest.approx((1 + 2 / n) * p, rel=1e-8)


@pytest.mark.parametrize("length", [0.1, 0.25, 1.0, 1.25, 1.9])
def test_variance_factor_is_that_of_euler_maruyama_steps_of_an_ou_process(length):
    """The warnings' var(V) factor: Euler-Maruyama steps of length h (relaxation times) of
    dx = -x dt + sqrt(2) dW, simulated (numpy, 2e5 chains), against the exact variance 1."""
    rng = np.random.default_rng(7)
    x = rng.normal(size=200_000)  # the exact law; its variance relaxes as (1 - h)^(2k)
    for _ in range(int(10 / (length * (2 - length))) + 5):
        x = (1 - length) * x + np.sqrt(2 * length) * rng.normal(size=x.size)
    factor = barostat.variance_factor(length)
    assert np.var(x) == pytest.approx(factor, rel=5 * np.sqrt(2 / x.size))  # 5 sigma
    assert barostat.variance_factor(2.0) == np.inf  # |1 - h| >= 1: no stationary law


def test_long_plain_moves_get_a_warning_and_tested_ones_none():
    baro = barostat.c_rescale(1.0, 2, tau=1.0, compressibility=0.1, temperature=1.0,
                              interval=10)
    assert barostat.move_length(baro, 20.0, 0.01) == pytest.approx(0.2)
    assert barostat.long_move_warning(baro, 20.0, 0.01) is None  # below LONG_MOVE
    message = barostat.long_move_warning(baro, 30.0, 0.01)
    assert "about 0.3 of the volume's relaxation time" in message and "K = 30" in message
    assert "var(V) about 1.2x" in message and "\n" not in message
    assert "unstable" in barostat.long_move_warning(baro, 300.0, 0.01)
    assert barostat.long_move_warning(baro, -5.0, 0.01) is None
    tested = barostat.c_rescale(1.0, 2, tau=1.0, compressibility=0.1, temperature=1.0,
                                interval=10, metropolis=True)
    assert barostat.long_move_warning(tested, 300.0, 0.01) is None


def test_a_run_with_long_plain_moves_warns_with_the_modulus_of_its_last_state(tmp_path):
    """The squeezed crystal's moves of 3 dt are nearly two relaxation times long (K about
    120 at P0 = 2): affinebody run says so once, after the run, with K of the last frame
    (its state, box and list), which must be the modulus of the all-pairs autodiff pressure
    of that frame read back from the file."""
    import re

    from affinebody.config import build, check_config, parse_config
    from affinebody.h5md import read_trajectory
    from affinebody.runner import run_simulation

    config = check_config(parse_config(SQUEEZED_CRYSTAL.replace("steps = 200", "steps = 60")))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_simulation(config, tmp_path / "plain.h5")
    said = [str(w.message) for w in caught if "barostat moves" in str(w.message)]
    assert len(said) == 1
    length, modulus = map(float, re.search(r"about ([\d.]+) of .* K = ([\d.]+)", said[0]).groups())
    traj = read_trajectory(tmp_path / "plain.h5")
    last = State(*(jnp.asarray(a[-1]) for a in traj.state))
    system, cell = build(config).system, np.diag(traj.boxes[-1])
    p_of = pressure_along_the_move(system, last, cell)
    reference = -float(jax.jit(jax.grad(p_of))(0.0))
    assert modulus == pytest.approx(reference, rel=5e-3)  # the message's 3 digits
    space = system.potential.terms[0].space
    assert barostat.move_modulus(system, last, cell, space) == pytest.approx(reference,
                                                                             rel=1e-6)
    assert length == pytest.approx(reference * 0.2 * 3 * 0.005 / 0.2, rel=0.05)
    assert length > 1.0


def test_npt_effective_energy_drifts_by_the_integrator_error_only():
    """H + P0 V - heat - work (Bernetti and Bussi 2020: the thermostat's heat and the
    barostat's work booked step by step) is conserved up to the error of the Strang steps at
    fixed cell: over 400 steps its largest deviation shrinks at least 3x per halving of dt
    (h^2 and a time span halved with it), while the energy exchanged with the baths is
    O(1). A work or heat booked wrongly (a move's kinetic change, the P0 V term) would leave
    a random walk of O(sqrt(dt)) per step that does not shrink like that."""
    from affinebody import thermostats as th
    from affinebody.config import build, check_config, parse_config

    text = (NPT_CONFIG.replace("r_cut = 1.0", "r_cut = 1.2\nr_on = 0.8")  # smooth at the cut
            .replace('coupling = "anisotropic"', 'coupling = "isotropic"'))
    built = build(check_config(parse_config(text)))
    baro = barostat.c_rescale(0.1, 2, tau=2.0, compressibility=1.0, temperature=0.3)
    langevin = th.Langevin(0.3, 1.0, seed=5)

    def hook(system, state, key, dt):
        return th.thermostat_step(system, langevin, state, dt, key,
                                  th.factors(system, state))[0]

    drifts = []
    for dt in (0.02, 0.01, 0.005):
        trajectory = barostat.run(built.system, built.state, orthorhombic((4.0, 4.2)), baro,
                                  dt, 400, seed=3, every=10, thermostat=hook)
        assert trajectory.failed_step is None
        values = trajectory.observables
        effective = values["effective_energy"]
        assert np.ptp(values["heat"]) > 1.0 and np.ptp(values["work"]) > 0.1
        assert np.ptp(values["volume"]) > 1.0  # the box moved
        drifts.append(np.max(np.abs(effective - effective[0])))
    assert drifts[1] < drifts[0] / 3 and drifts[2] < drifts[1] / 3, drifts
    assert drifts[2] < 1e-3


@pytest.mark.parametrize("metropolis,dt", [(False, 0.05), (True, 0.2)])
def test_a_bound_pair_samples_the_exact_isobaric_volume_law(metropolis, dt):
    """NPT and NVT agree, in exact form: the barostat samples p(V) ~ exp(-P0 V/kT) Q(V), Q the
    NVT partition function of the same system in the box of volume V (the NVT pressure is
    kT d ln Q/dV), so <V>_NPT is a ratio of integrals of Q. For two bodies with a pair
    potential u(r), Q(V) ~ V * integral of exp(-u(r)/kT) over the minimum-image cell of the
    box (a 2D quadrature per V; the box may be narrower than 2 r_cut: both sides use the
    minimum image). A deep well binds the pair (<V> = 7.41 here, 10 = 3 kT/P0 for the ideal
    gas that a missing virial would sample). The long NPT-then-NVT comparison of an
    interacting crystal is benchmarks/npt_consistency.py (minutes). With the Metropolis test
    the same law holds at moves four times as long, where the plain move's box runs away."""
    from affinebody import thermostats as th
    from affinebody.potentials import Cutoff, PairPotential, StVenantKirchhoff, total_potential

    kt, p0, depth, r_cut, r_on, edges = 1.0, 0.3, 4.0, 1.5, 1.2, (3.0, 3.3)
    space = orthorhombic(edges)
    pair = PairPotential(lambda r: -depth * jnp.exp(-r * r), ("r",), Cutoff(r_cut, r_on), space)
    system = HamiltonianSystem(KineticEnergy(DAlembertTranslational(1.0), DAlembert(jnp.eye(2))),
                               total_potential([pair, StVenantKirchhoff(1.0, 1.0)]))
    state = State(jnp.asarray([[0.5, 0.5], [2.0, 2.2]]), jnp.broadcast_to(jnp.eye(2), (2, 2, 2)),
                  jnp.zeros((2, 2)), jnp.zeros((2, 2, 2)))
    langevin = th.Langevin(kt, 1.0, seed=1)

    def hook(system, state, key, dt):
        return th.thermostat_step(system, langevin, state, dt, key,
                                  th.factors(system, state))[0]

    baro = barostat.c_rescale(p0, 2, tau=0.5, compressibility=1.0, temperature=kt,
                              metropolis=metropolis)
    steps = int(round(600 / dt))  # the same span of time (the statistical error's measure)
    trajectory = barostat.run(system, state, space, baro, dt, steps, seed=1,
                              every=int(round(0.5 / dt)), thermostat=hook)
    assert trajectory.failed_step is None
    volume = trajectory.observables["volume"][60:]
    blocks = volume[: len(volume) // 20 * 20].reshape(20, -1).mean(axis=1)
    error = blocks.std(ddof=1) / np.sqrt(len(blocks))

    def cell_integral(v, m=100):  # over the minimum-image cell, u with its quintic switch
        half = np.sqrt(v / (edges[0] * edges[1])) * np.asarray(edges) / 2
        x, y = ((np.arange(m) + 0.5) / m * h for h in half)
        r = np.hypot(x[:, None], y[None])
        t = np.clip((r - r_on) / (r_cut - r_on), 0.0, 1.0)
        u = -depth * np.exp(-r * r) * (1 - t**3 * (10 - 15 * t + 6 * t * t))
        return 4 * np.exp(-u / kt).sum() * half[0] * half[1] / m**2

    v = np.linspace(1e-3, 80.0, 400)  # exp(-P0 V/kT) < 1e-10 beyond
    weight = np.exp(-p0 * v / kt) * v * np.array([cell_integral(a) for a in v])
    exact = (weight * v).sum() / weight.sum()
    assert abs(volume.mean() - exact) < 4 * error, (volume.mean(), error, exact)
    assert 3 * kt / p0 - exact > 5 * error  # the ideal-gas law would fail


def test_a_box_that_blows_up_stops_the_run_before_its_volume_overflows(tmp_path):
    """Sixty-four bodies 1e-9 apart under a barostat (found by fuzzing the CLI): the Morse
    repulsion's pressure throws the box open by hundreds of orders of magnitude in a few steps.
    The edges stayed finite while the volume overflowed, and the run ended with exit 0 and an
    infinite volume, nan effective energy in its file: now the step is not kept and the run
    stops (SimulationStopped, what the CLI reports with exit 3), every kept frame finite."""
    from affinebody.config import check_config, parse_config
    from affinebody.h5md import read_trajectory
    from affinebody.runner import SimulationStopped, run_simulation

    text = textwrap.dedent("""
        [system]
        n = 2
        bodies = 64
        box = [8.0, 8.0]
        [kinetic]
        internal = "af-is"
        I = 1.0
        A = 0.2
        B = 0.1
        [[potential]]
        kind = "pair"
        expr = "(1 - exp(-3*(r - 1)))**2 - 1 + 0.5*exp(-D**2/4)*(M1 - 2)**2"
        r_cut = 2.5
        [[potential]]
        kind = "one-body"
        expr = "5*(det - 1)**2 + 0.5*(trG - 2)**2"
        [initial]
        generator = "lattice"
        spacing = 1e-9
        phi_noise = 0.02
        [run]
        dt = 0.005
        steps = 40
        every = 10
        seed = 1
        neighbor_list = "on"
        [thermostat]
        kind = "langevin"
        temperature = 0.1
        friction = 1.0
        [barostat]
        pressure = 0.5
        tau = 1.0
        compressibility = 1.0
        interval = 10
    """)
    with pytest.raises(SimulationStopped, match="non-finite state or box"):
        run_simulation(check_config(parse_config(text)), tmp_path / "npt.h5")
    kept = read_trajectory(tmp_path / "npt.h5")
    assert kept.frames >= 1
    for name in ("volume", "effective_energy", "total_energy"):
        assert np.all(np.isfinite(kept.observables[name])), name
    assert np.all(np.isfinite(kept.boxes))


def test_the_thermostat_hook_prepared_once_is_the_hook_of_every_step():
    """barostat.run computes the thermostat's noise factors once per compiled call
    (ThermostatHook.prepare; they depend on the kinetic model and the number of bodies only),
    not in every step: the prepared hook gives the same bits as the hook that computes them."""
    from affinebody.config import build, check_config, parse_config
    from affinebody.runner import ThermostatHook

    text = NPT_CONFIG.replace("temperature = 0.3\n", "") + (
        '[thermostat]\nkind = "langevin"\ntemperature = 0.3\nfriction = 1.0\nseed = 5\n')
    built = build(check_config(parse_config(text)))
    hook, key = ThermostatHook(built.thermostat), jax.random.PRNGKey(3)
    state = built.state
    for _ in range(2):  # the second from momenta the first drew
        every = jax.jit(hook, static_argnums=3)(built.system, state, key, 0.01)
        once = jax.jit(lambda s, k: hook.prepare(built.system, s)(built.system, s, k, 0.01))(
            state, key)
        for a, b in zip(jax.tree.leaves(every), jax.tree.leaves(once), strict=True):
            np.testing.assert_array_equal(a, b)
        assert np.any(np.asarray(every.p) != np.asarray(state.p))
        state, key = every, jax.random.split(key)[0]


def test_the_compiled_thermostatted_npt_loop_calls_no_lapack_kernel():
    """The NPT loop with the runner's Langevin hook (its noise factors computed inside the
    program, ``ThermostatHook.prepare``), af-is bodies, compiled: no LAPACK custom call. Two
    batched LAPACK kernels ready at once deadlock XLA's CPU pool of two threads, which the
    thermostat's two eigendecompositions did (a 97 336-body run hung in its first call)."""
    import re

    from affinebody import thermostats as th
    from affinebody.config import build, check_config, parse_config
    from affinebody.runner import ThermostatHook

    text = NPT_CONFIG.replace('internal = "dalembert"', 'internal = "af-is"\nI = 1.0\n'
                              'A = 0.2\nB = 0.1')
    built = build(check_config(parse_config(text)))
    space = orthorhombic((4.0, 4.2))
    baro = barostat.c_rescale(0.1, 2, tau=2.0, compressibility=1.0, temperature=0.3)
    hook = ThermostatHook(th.Langevin(0.3, 1.0, seed=5))

    def npt(seed):
        return barostat.advance(built.system, built.state, jnp.asarray(space.matrix),
                                jnp.asarray(0), seed, 0.01, steps=3,
                                method=get_integrator("strang"), barostat=baro, space=space,
                                thermostat=hook)

    compiled = jax.jit(npt).lower(jnp.asarray(1)).compile().as_text()
    targets = re.findall(r'custom_call_target="([^"]*)"', compiled)
    assert not [t for t in targets if "lapack" in t.lower()], targets
    state, cell, *_ = jax.jit(npt)(jnp.asarray(1))
    assert np.all(np.isfinite(np.asarray(state.pi))) and np.all(np.isfinite(np.asarray(cell)))
