"""Thermostats (issue 15): each test compares with a closed form or an independent method.

- the O step draws the Maxwell distribution of every kinetic model on GL+ and on subgroups
  (chi^2 law of the per-body kinetic energy with d degrees of freedom);
- in a harmonic trap BAOAB's translational temperature has the exact bias 1 - (h w/2)^2 and
  OBABO's positions the exact bias 1/(1 - (h w/2)^2); both vanish as dt -> 0;
- the configurational marginal of one body: ln det phi and the singular values of phi have the
  moments of exp(-V/kT) times the volume element of the kinetic metric (Lebesgue for
  d'Alembert, Haar |det phi|^-n (91) for af-is, times the |det phi|^-1 of the af-is translational
  energy), computed by quadrature in two-polar coordinates (polar.py's densities), and
  equipartition holds; the af-is energy agrees with quantum/thermal.py's classical Z;
- Bussi: the kinetic energy of free bodies has the gamma law with N_f/2 degrees;
- a resumed thermostatted run reproduces the uninterrupted one bit for bit;
- af-af is refused in one line.
"""

import math
import re
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import kinetic as K
from affinebody import thermostats as th
from affinebody.config import ConfigError, parse_config
from affinebody.config import check_config as check
from affinebody.groups import expm, project_algebra
from affinebody.polar import two_polar_haar_density, two_polar_lebesgue_density
from affinebody.quantum.thermal import classical_partition_function_affine2
from affinebody.simulate import run
from affinebody.state import State
from affinebody.system import HamiltonianSystem

KT = 0.5
STIFFNESS = 4.0  # V = STIFFNESS/2 (q1^2 + q2^2) + |x|^2/2, q = ln of the singular values


class Trap:
    """V = |x|^2/2 + k/2 sum_a q_a^2, q_a = ln s_a (s_a the singular values of phi)."""

    def energy(self, x, phi):
        lam = jnp.linalg.eigvalsh(jnp.swapaxes(phi, -1, -2) @ phi)
        return jnp.sum(0.5 * jnp.sum(x * x, -1)
                       + STIFFNESS / 8 * jnp.sum(jnp.log(lam) ** 2, -1), -1)

    def __hash__(self):
        return 17

    def __eq__(self, other):
        return isinstance(other, Trap)


class XTrap:
    """V = |x|^2/2: a harmonic trap of the centres only (w = 1 for unit mass)."""

    def energy(self, x, phi):
        return 0.5 * jnp.sum(x * x, (-2, -1))

    def __hash__(self):
        return 18

    def __eq__(self, other):
        return isinstance(other, XTrap)


def rest(bodies, n=2):
    return State(jnp.zeros((bodies, n)), jnp.broadcast_to(jnp.eye(n), (bodies, n, n)),
                 jnp.zeros((bodies, n)), jnp.zeros((bodies, n, n)))


SPD = jnp.array([[1.0, 0.3], [0.3, 0.6]])
L4 = np.eye(4) + 0.2 * np.ones((4, 4))
INTERNAL = {
    "dalembert": K.DAlembert(SPD),
    "af-is": K.AffineIsotropic(1.0, 0.3, 0.2),
    "is-af": K.IsotropicAffine(1.2, -0.4, 0.1),
    "af-J": K.AffineJ(SPD),
    "H-af": K.HAffine(SPD),
    "l-af": K.LeftInvariant(jnp.asarray(L4.reshape(2, 2, 2, 2))),
    "r-af": K.RightInvariant(jnp.asarray(L4.reshape(2, 2, 2, 2))),
}
CASES = [(m, "GL+") for m in INTERNAL] + [("is-af", "SO"), ("is-af", "R+SO"), ("af-is", "SL"),
                                          ("af-J", "GL+ spatial")]


@pytest.mark.parametrize("model,group", CASES)
def test_the_o_step_draws_the_maxwell_law_of_every_model_and_group(model, group):
    """c = 0: fresh momenta at random phi in G; per body 2 T / kT is chi^2 with n + d degrees
    (translational af-is or d'Alembert, and the restricted internal metric on G; "GL+ spatial":
    the admissible velocities of the rotationless constraint (40), Omega symmetric)."""
    bodies, n = 2000, 2
    group, rotationless = (group.split() + [None])[:2]
    rng = np.random.default_rng(1)
    algebra = "GL" if group == "GL+" else group
    phi = expm(project_algebra(jnp.asarray(0.4 * rng.standard_normal((bodies, 1, n, n))),
                               algebra))
    translational = K.AffineTranslational(1.3) if model == "af-is" else \
        K.DAlembertTranslational(0.7)
    system = HamiltonianSystem(K.KineticEnergy(translational, INTERNAL[model]), None, group,
                               rotationless=rotationless)
    state = State(jnp.zeros((bodies, 1, n)), phi, jnp.zeros((bodies, 1, n)),
                  jnp.zeros((bodies, 1, n, n)))
    langevin = th.Langevin(KT, 1.0)

    def fresh(state):
        factors = th.factors(system, rest(1))
        state = th.ornstein_uhlenbeck(system, langevin, state, 0.1, jax.random.PRNGKey(3),
                                      factors, damping=0.0)
        t_tr = th.translational_kinetic_energy(system, state)
        xi = system.kinetic.internal.inverse_legendre(state.phi, state.pi)
        return system.kinetic_energy(state) - t_tr, t_tr, state.pi @ state.phi, \
            xi @ jnp.linalg.inv(state.phi)

    t_int, t_tr, sigma_hat, omega = (np.asarray(a) for a in fresh(state))
    d = th.internal_degrees_of_freedom(system, n)
    assert d == {"GL+": 4, "SL": 3, "SO": 1, "R+SO": 2}[group] - (rotationless is not None)
    for energy, dof in ((t_int, d), (t_tr, n)):
        chi2 = 2 * energy / KT
        assert abs(chi2.mean() - dof) < 4 * math.sqrt(2 * dof / bodies)
        # the chi^2 variance 2 dof: a Gaussian of the wrong covariance fails here
        assert abs(chi2.var() / (2 * dof) - 1) < 4 * math.sqrt(8 / bodies + 12 / (dof * bodies))
    if rotationless:  # admissible: Omega = xi phi^-1 symmetric
        np.testing.assert_allclose(omega, np.swapaxes(omega, -1, -2), atol=1e-10)
    # the momenta are constrained ones (the projection keeps pi phi in the algebra)
    np.testing.assert_allclose(sigma_hat, np.asarray(project_algebra(sigma_hat, algebra)),
                               atol=1e-12)


def test_the_harmonic_biases_of_both_splittings_vanish_as_dt_goes_to_zero():
    """Harmonic trap V = |x|^2/2 (w = 1), exact closed forms of the stationary law:
    BAOAB's positions are exact and its momenta after a step have <p^2>/m = kT (1 - (h w/2)^2)
    (Leimkuhler and Matthews 2013); OBABO's momenta are exact and its positions have
    w^2 <x^2> = kT / (1 - (h w/2)^2) (velocity Verlet keeps the Gaussian of
    p^2/2 + w^2 (1 - (h w/2)^2) x^2/2, the O step keeps p ~ N(0, kT)). Each bias shrinks as
    h^2; the exact coordinate of each stays exact."""
    system = HamiltonianSystem(K.KineticEnergy(K.DAlembertTranslational(1.0),
                                               K.DAlembert(jnp.eye(2))), XTrap(), "L")
    for splitting in th.SPLITTINGS:
        measured = []
        for dt in (1.0, 0.5):
            traj = run(system, rest(200), dt, 800, every=10,
                       observers=("translational_temperature",),
                       thermostat=th.Langevin(KT, 1.0, seed=2, splitting=splitting))
            t = traj.observables["translational_temperature"][10:]
            x2 = np.mean(np.asarray(traj.states.x[10:]) ** 2)  # kT per coordinate if exact
            biased, exact = (x2, t.mean()) if splitting == "obabo" else (t.mean(), x2)
            factor = 1 / (1 - (dt / 2) ** 2) if splitting == "obabo" else 1 - (dt / 2) ** 2
            assert abs(biased / (KT * factor) - 1) < 0.03, splitting
            assert abs(exact / KT - 1) < 0.03, splitting
            measured.append(abs(biased / KT - 1))
        assert measured[1] < measured[0] / 2.5  # bias ~ h^2: 1/4 vs 1/16 (1/3 vs 1/15)


def _two_polar_moments(lebesgue: bool, translational_weight: float):
    """<ln det phi>, <(ln det)^2> and <s_max> under exp(-V/kT) x the measure, by quadrature on
    a grid of q1 > q2 (the densities of polar.py; Lebesgue in Q = e^q needs dQ = Q dq)."""
    q = np.linspace(-4, 4, 801)
    q1, q2 = np.meshgrid(q, q, indexing="ij")
    upper = q1 > q2
    qs = np.stack([q1, q2], -1)
    if lebesgue:
        Q = np.exp(qs)
        density = np.asarray(two_polar_lebesgue_density(jnp.asarray(Q))) * Q[..., 0] * Q[..., 1]
    else:
        density = np.asarray(two_polar_haar_density(jnp.asarray(qs)))
    s = q1 + q2
    weight = density * np.exp(-STIFFNESS / 2 * (q1**2 + q2**2) / KT
                              + translational_weight * s) * upper
    z = weight.sum()
    return (weight * s).sum() / z, (weight * s**2).sum() / z, (weight * np.exp(q1)).sum() / z


def _sample(internal, translational, seed):
    system = HamiltonianSystem(K.KineticEnergy(translational, internal), Trap())
    traj = run(system, rest(300), 0.05, 2000, every=20,
               observers=("energy", "translational_temperature", "internal_temperature"),
               thermostat=th.Langevin(KT, 2.0, seed=seed))
    keep = slice(20, None)
    phi = np.asarray(traj.states.phi[keep])
    logdet = np.log(np.abs(np.linalg.det(phi))).ravel()
    top = np.linalg.svd(phi, compute_uv=False)[..., 0].ravel()
    return system, traj, keep, logdet, top


@pytest.mark.parametrize("model", ["dalembert", "af-is"])
def test_the_configurational_marginal_is_boltzmann_times_the_kinetic_volume(model):
    """d'Alembert (T independent of phi): Lebesgue measure; af-is: Haar |det phi|^-2 times
    |det phi|^-1 from the af-is translational energy |phi^T p|^2/2M. The two differ by
    |det phi|^3 (<ln det phi> = 0.75 apart here), so the wrong measure fails."""
    if model == "dalembert":
        internal, translational, lebesgue, extra = K.DAlembert(0.7 * jnp.eye(2)), \
            K.DAlembertTranslational(1.0), True, 0.0
    else:
        internal, translational, lebesgue, extra = K.AffineIsotropic(1.0, 0.2, 0.1), \
            K.AffineTranslational(1.0), False, -1.0
    system, traj, keep, logdet, top = _sample(internal, translational, seed=5)
    mean, second, s_max = _two_polar_moments(lebesgue, extra)
    # independent samples: 300 bodies x ~10 decorrelated frames
    err = math.sqrt((second - mean**2) / 3000)
    assert abs(logdet.mean() - mean) < 5 * err
    assert abs(logdet.var() / (second - mean**2) - 1) < 0.1
    assert abs(top.mean() - s_max) < 0.03 * s_max
    # equipartition of both parts
    for name in ("translational_temperature", "internal_temperature"):
        assert abs(traj.observables[name][keep].mean() / KT - 1) < 0.03
    if model == "af-is":
        # quantum/thermal.py: <T_int + V_int> = -d ln Z_cl / d beta of the internal motion
        def log_z(beta):
            return math.log(classical_partition_function_affine2(
                "af-is", lambda Q: STIFFNESS / 2 * np.sum(np.log(Q) ** 2, -1), 1.0, beta,
                I=1.0, A=0.2, B=0.1, points=200))

        beta, h = 1 / KT, 1e-4
        exact = -(log_z(beta + h) - log_z(beta - h)) / (2 * h)
        # the af-is translational factor |det phi|^-1 shifts the measure: undo it by weights
        states = jax.tree.map(lambda a: a[keep], traj.states)
        lam = np.linalg.eigvalsh(np.swapaxes(states.phi, -1, -2) @ states.phi)
        v_int = STIFFNESS / 8 * np.sum(np.log(lam) ** 2, -1)
        t_int = 2.0 * KT  # equipartition, checked above: d/2 kT with d = 4
        w = np.abs(np.linalg.det(np.asarray(states.phi)))
        sampled = t_int + np.sum(w * v_int) / np.sum(w)
        assert abs(sampled / exact - 1) < 0.03


def test_bussi_kinetic_energy_has_the_gamma_law():
    """Free d'Alembert bodies on L (V = 0): the exact drift keeps T, the rescaling samples
    K ~ Gamma(N_f/2, kT) with N_f = N (n + n^2)."""
    system = HamiltonianSystem(K.KineticEnergy(K.DAlembertTranslational(1.0),
                                               K.DAlembert(SPD)), None, "L")
    bodies = 2
    traj = run(system, rest(bodies), 0.1, 4000, every=2, observers=("kinetic_energy",),
               thermostat=th.Bussi(KT, 0.1, seed=4))
    k = traj.observables["kinetic_energy"][50:]
    dof = th.degrees_of_freedom(system, 2, bodies)
    assert dof == 12
    shape = dof / 2
    assert abs(k.mean() / (shape * KT) - 1) < 0.03
    assert abs(k.var() / (shape * KT**2) - 1) < 0.15
    # effective energy: H minus the heat stays constant (exact drift of free bodies)
    e = traj.observables["effective_energy"]
    assert np.max(np.abs(e - e[0])) < 1e-9


CONFIG = """
[system]
n = 2
bodies = 3
[body]
mass = 1.0
inertia = 0.5
[kinetic]
translational = "dalembert"
internal = "af-is"
I = 1.0
A = 0.2
[[potential]]
kind = "dilatation"
stiffness = 5.0
[initial]
x = [[0.0, 0.0], [1.1, 0.0], [0.0, 0.9]]
[run]
dt = 0.01
steps = 600
every = 100
checkpoint = 200
[thermostat]
kind = "{kind}"
temperature = 0.3
{parameter} = 0.5
seed = 7
"""


def test_a_resumed_thermostatted_run_is_bit_exact(tmp_path, kind="langevin",
                                                  parameter="friction"):
    import h5py

    from affinebody.runner import run_simulation

    config = check(parse_config(CONFIG.format(kind=kind, parameter=parameter)))
    run_simulation(config, tmp_path / "a.h5")
    run_simulation(config, tmp_path / "b.h5", steps=400)
    run_simulation(config, tmp_path / "b.h5", resume=True)
    with h5py.File(tmp_path / "a.h5") as a, h5py.File(tmp_path / "b.h5") as b:
        for key in ("particles/bodies/phi_momentum/value", "particles/bodies/momentum/value",
                    "observables/effective_energy/value",
                    "observables/internal_temperature/value"):
            assert np.array_equal(a[key][()], b[key][()]), key
        e = a["observables/effective_energy/value"][()]
        total = a["observables/total_energy/value"][()]
        assert np.ptp(total) > 100 * np.ptp(e)  # heat flowed, the effective energy stayed


def test_af_af_and_incomplete_thermostats_are_refused_in_one_line():
    base = CONFIG.format(kind="langevin", parameter="friction")
    for text, words in (
        (base.replace('internal = "af-is"\nI = 1.0\nA = 0.2', 'internal = "af-af"\nA = 1.0'),
         "indefinite"),
        (base.replace("friction = 0.5", "tau = 0.5"), "thermostat.friction is required"),
        (base.replace("temperature = 0.3", "temperature = -1.0"), "thermostat.temperature"),
        (base + 'splitting = "abab"\n', "thermostat.splitting"),
    ):
        with pytest.raises(ConfigError) as err:
            check(parse_config(text))
        assert words in str(err.value) and "\n" not in str(err.value)
    from affinebody.sweep import run_sweep

    with pytest.raises(ConfigError, match="sweep.equilibration must leave a measurement"):
        run_sweep(check(parse_config(base + "[sweep]\nequilibration = 100000\n")), workers=0)
    system = HamiltonianSystem(K.KineticEnergy(K.DAlembertTranslational(1.0),
                                               K.AffineAffine(1.0)))
    with pytest.raises(ValueError, match="no canonical ensemble"):
        run(system, rest(2), 0.01, 1, thermostat=th.Langevin(KT, 1.0))


def test_a_temperature_in_kelvin_given_as_kt_in_kj_per_mol_is_warned_of():
    """With system.units = "gromacs" a temperature is kT in kJ/mol (k_B = 1): 300 meant as
    kelvin is 300 / 0.0083144626 = 36 082 K, which is warned of in one line with the value for
    300 K (2.494 kJ/mol); kT = 2.494 and reduced units (no kelvin) are not."""
    base = CONFIG.format(kind="langevin", parameter="friction").replace(
        "n = 2\n", 'n = 2\nunits = "gromacs"\n', 1)
    with pytest.warns(UserWarning) as caught:
        check(parse_config(base.replace("temperature = 0.3", "temperature = 300")))
    text = str(caught[0].message)
    assert "36082 K" in text and "2.494" in text and "\n" not in text
    assert 300 / 0.0083144626181532 == pytest.approx(36082, abs=0.5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check(parse_config(base.replace("temperature = 0.3", "temperature = 2.494")))
        check(parse_config(CONFIG.format(kind="langevin", parameter="friction").replace(
            "temperature = 0.3", "temperature = 300")))


def test_the_noise_factors_are_each_bodys_hessian_without_a_batch_of_all_its_columns():
    """K of every body (its own J) is the Hessian of its T(Id, z), F F^T K = Id; and the
    compiled factors need temporaries of about their own size: the d columns of K are taken
    one after the other. (Differentiated as one [d, N, d] batch, the 3D d'Alembert factors
    needed 8.7 times their bytes in temporaries, which a thermostatted run's loop kept on top
    of its own: 2.1 GB against 0.9 GB for NVE at 10^5 bodies.)"""
    rng = np.random.default_rng(5)
    a = rng.standard_normal((3, 3, 3))
    inertia = jnp.asarray(a @ np.swapaxes(a, -1, -2) + np.eye(3))  # one SPD J per body
    term = K.DAlembert(inertia)
    k = np.asarray(th.coordinate_hessian(term, 3, (3, 3)))
    for body in range(3):
        one = K.DAlembert(inertia[body])
        hessian = jax.hessian(lambda z, t=one: t.hamiltonian(jnp.eye(3), z.reshape(3, 3)))(
            jnp.zeros(9))
        np.testing.assert_allclose(k[body], hessian, rtol=1e-13, atol=1e-14)
    f = np.asarray(th.noise_factor(term, 3, (3, 3)))
    np.testing.assert_allclose(f @ np.swapaxes(f, -1, -2) @ k, np.broadcast_to(np.eye(9), k.shape),
                               atol=1e-12)
    bodies = 4096
    many = K.DAlembert(jnp.broadcast_to(inertia[0], (bodies, 3, 3)))
    compiled = jax.jit(lambda t: th.noise_factor(t, bodies, (3, 3))).lower(many).compile()
    memory = compiled.memory_analysis()
    assert memory is not None  # XLA's CPU (and GPU) clients report it
    assert memory.temp_size_in_bytes <= 2.5 * memory.output_size_in_bytes


@pytest.mark.parametrize("n", [2, 3])
def test_the_compiled_noise_factors_call_no_lapack_kernel(n):
    """The factors of a thermostatted run are plain XLA arithmetic: no LAPACK custom call in
    the compiled program. Two batched LAPACK eigendecompositions (translational, internal)
    were ready at once in the compiled NPT loop and deadlocked XLA's pool of two threads (a
    run of 97 336 bodies hung, gdb: two dsyevd waiting on each other); the optimisation
    barrier meant to order them was gone from the optimised program."""
    system = HamiltonianSystem(K.KineticEnergy(K.DAlembertTranslational(1.0),
                                               K.AffineIsotropic(1.0, 0.2, 0.1)))
    state = rest(64, n=n)
    compiled = jax.jit(lambda s: th.factors(system, s)).lower(state).compile().as_text()
    targets = re.findall(r'custom_call_target="([^"]*)"', compiled)
    assert not [t for t in targets if "lapack" in t.lower()], targets
    f_tr, f_int = th.factors(system, state)
    for f, term, shape in ((f_tr, system.kinetic.translational, (n,)),
                           (f_int, system.kinetic.internal, (n, n))):
        k = np.asarray(th.coordinate_hessian(term, 64, shape))
        np.testing.assert_allclose(np.asarray(f) @ np.swapaxes(f, -1, -2) @ k,
                                   np.broadcast_to(np.eye(k.shape[-1]), k.shape), atol=1e-12)


def test_the_inverse_cholesky_factor_against_lapack_and_its_failure_as_nan():
    """F F^T = k^-1 to rounding for random SPD k of sizes 1..9 (against numpy's inverse), F
    upper triangular, and NaN (never a wrong finite factor) where k is not positive definite."""
    from affinebody import _linalg

    rng = np.random.default_rng(11)
    for d in (1, 2, 3, 4, 9):
        a = rng.standard_normal((6, d, d))
        k = a @ np.swapaxes(a, -1, -2) + 0.05 * np.eye(d)
        f = np.asarray(_linalg.inverse_cholesky_factor(k))
        np.testing.assert_allclose(f @ np.swapaxes(f, -1, -2), np.linalg.inv(k),
                                   rtol=1e-10, atol=1e-10 * np.abs(np.linalg.inv(k)).max())
        assert np.all(np.tril(f, -1) == 0.0)
    indefinite = np.asarray(_linalg.inverse_cholesky_factor(np.diag([1.0, -1.0, 2.0])))
    assert np.isnan(indefinite).any()
    singular = np.asarray(_linalg.inverse_cholesky_factor(np.zeros((3, 3))))
    assert np.isnan(singular).all()
