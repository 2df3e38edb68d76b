"""The paper's qualitative claims about affine dynamics (text around (78)-(81)), reproduced.

1. Geodesic af-af motion on SL(2): bounded (oscillatory) trajectories form an open set of initial
   data, and so do unbounded ones.
2. Geodesic affine motion on GL(n): the dilatation is unbounded; a potential V(det phi) (80), (81)
   makes it bounded.
3. A binary affine potential (78) bounds the relative volumes det Gamma[phi_K, phi_L] (79) but not
   the single volumes det phi_K.

Every trajectory comes from the library's integrator (``simulate.run``); the expectations come
from closed forms derived independently (docs/theory/exact-flows.md, "Closed-form facts used by
the tests").
"""

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from affinebody import kinetic as kin
from affinebody import potentials as pot
from affinebody.groups import expm
from affinebody.simulate import run
from affinebody.state import State
from affinebody.system import HamiltonianSystem

AF_AF_SL2 = HamiltonianSystem(
    kin.KineticEnergy(kin.DAlembertTranslational(1.0), kin.AffineAffine(A=1.0, B=0.5)),
    None, group="SL")


def phi_of(state: State) -> jnp.ndarray:
    return state.phi


def sl2_state(phi0, omega_hat) -> State:
    """One body at phi0 in SL(2) with co-moving velocity Omega_hat (traceless), at rest in x."""
    internal = AF_AF_SL2.kinetic.internal
    pi = internal.legendre(phi0[None], (phi0 @ omega_hat)[None])
    return State(jnp.zeros((1, 2)), phi0[None], jnp.zeros((1, 2)), pi)


def traceless(a, b, c):
    return jnp.asarray([[a, b], [c, -a]])


small = st.floats(-0.2, 0.2)
rotation_angle = st.floats(-1.0, 1.0)


def random_sl2(angle, shear):
    return expm(traceless(0.3 * shear, angle, -0.5 * angle + 0.2 * shear))


@settings(max_examples=6, deadline=None)
@given(small, small, small, rotation_angle, small)
def test_af_af_on_sl2_bounded_motions_form_an_open_set(da, db, dc, angle, shear):
    """Near Omega_hat = [[0,1],[-1,0]] (det > 0): phi0 (cos wt + sin wt / w X) oscillates."""
    x = traceless(da, 1.0 + db, -1.0 + dc)  # det x >= 0.6 on this whole box
    w = float(jnp.sqrt(jnp.linalg.det(x)))
    phi0 = random_sl2(angle, shear)
    period = 2 * np.pi / w
    steps = 400
    trajectory = run(AF_AF_SL2, sl2_state(phi0, x), 40 * period / steps, steps, every=4,
                     observers={"phi": phi_of})
    phis = trajectory.observables["phi"][:, 0]
    bound = float(jnp.linalg.norm(phi0)) * (1.0 + float(jnp.linalg.norm(x, 2)) / w)
    assert np.max(np.abs(phis)) <= bound * (1 + 1e-9)
    # periodic with the period 2 pi / w of the closed form: back to phi0 after 40 periods
    np.testing.assert_allclose(phis[-1], phi0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(phis), 1.0, atol=1e-11)


@settings(max_examples=6, deadline=None)
@given(small, small, small, rotation_angle, small)
def test_af_af_on_sl2_unbounded_motions_form_an_open_set(da, db, dc, angle, shear):
    """Near Omega_hat = diag(1, -1) (det < 0): phi(t) = phi0 (cosh wt + sinh wt / w X) grows."""
    x = traceless(1.0 + da, db, dc)  # det x <= -0.6 on this whole box
    w = float(jnp.sqrt(-jnp.linalg.det(x)))
    phi0 = random_sl2(angle, shear)
    # up to w t = 7: phi and pi then differ by e^14 in scale, and Sigma_hat = pi phi (from
    # which each step takes its velocity) loses log10(e^14) = 6 of its 16 digits
    t_end = 7.0 / w
    trajectory = run(AF_AF_SL2, sl2_state(phi0, x), t_end / 400, 400, every=400,
                     observers={"phi": phi_of})
    final = trajectory.observables["phi"][-1, 0]
    expected = phi0 @ (np.cosh(w * t_end) * np.eye(2) + np.sinh(w * t_end) / w * np.asarray(x))
    np.testing.assert_allclose(final, expected, rtol=1e-7, atol=1e-7 * np.abs(expected).max())
    assert np.abs(final).max() > 100 * np.abs(phi0).max()
    assert abs(np.linalg.det(final) - 1.0) < 1e-9


GL_MODELS = {
    "af-is": (kin.AffineIsotropic(I=2.0, A=0.5, B=0.3), 2.0 + 0.5),
    "af-af": (kin.AffineAffine(A=1.2, B=0.4), 1.2),
}


def gl_state(seed, n=2, dilatation_rate=0.1, mu=1.0):
    """A state whose Tr Sigma_hat gives d/dt ln det phi = dilatation_rate (inertia mu on Tr)."""
    rng = np.random.default_rng(seed)
    phi = jnp.asarray(np.eye(n) + 0.2 * rng.normal(size=(1, n, n)))
    sigma_hat = jnp.asarray(0.3 * rng.normal(size=(1, n, n)))
    sigma_hat = sigma_hat - (jnp.trace(sigma_hat[0]) / n - dilatation_rate * mu / n) * jnp.eye(n)
    return State(jnp.zeros((1, n)), phi, jnp.zeros((1, n)), sigma_hat @ jnp.linalg.inv(phi))


@pytest.mark.parametrize("model", list(GL_MODELS))
def test_geodesic_dilatation_is_unbounded_and_a_volume_potential_bounds_it(model):
    """ln det phi moves with constant speed Tr S / (I + A + nB); with V = k/2 (ln det)^2 (81) it
    oscillates with w^2 = k n / (I + A + nB) (the decoupled dilatation of
    docs/theory/exact-flows.md)."""
    internal, i_plus_a = GL_MODELS[model]
    n, rate = 2, 0.1
    mu = i_plus_a + n * internal.B
    kinetic = kin.KineticEnergy(kin.DAlembertTranslational(1.0), internal)
    state = gl_state(1, n, rate, mu)
    log_det0 = float(jnp.log(jnp.linalg.det(state.phi[0])))

    free = run(HamiltonianSystem(kinetic), state, 0.5, 400, every=8, observers=("volumes",))
    log_det = np.log(free.observables["volumes"][:, 0])
    np.testing.assert_allclose(log_det, log_det0 + rate * free.times, rtol=1e-10, atol=1e-10)
    assert log_det[-1] > 15.0  # det phi(200) > e^15: unlimited expansion

    k = 0.8
    confined = HamiltonianSystem(kinetic, pot.Dilatation(k))
    dt, steps = 0.02, 10_000
    trajectory = run(confined, state, dt, steps, every=20, observers=("volumes",))
    log_det = np.log(trajectory.observables["volumes"][:, 0])
    w = np.sqrt(k * n / mu)
    amplitude = np.hypot(log_det0, rate / w)
    assert np.max(np.abs(log_det)) < 1.01 * amplitude
    assert np.max(np.abs(log_det)) > 0.99 * amplitude  # and it does oscillate
    expected = log_det0 * np.cos(w * trajectory.times) + rate / w * np.sin(w * trajectory.times)
    np.testing.assert_allclose(log_det, expected, atol=2e-2 * amplitude)


def test_binary_affine_potential_bounds_relative_but_not_single_volumes():
    """(79)-(81): with V = sum_{K<L} k/2 sum_a (M_a - n)^2, det Gamma stays within the energy bound
    while sum_K ln det phi_K grows linearly (global scaling is a symmetry: Tr Sigma conserved)."""
    n, k = 2, 0.5
    internal = kin.AffineIsotropic(I=2.0, A=0.5, B=0.3)
    mu = 2.0 + 0.5 + n * 0.3
    system = HamiltonianSystem(kin.KineticEnergy(kin.DAlembertTranslational(1.0), internal),
                               pot.HarmonicInvariants(k))
    rng = np.random.default_rng(7)
    phi = jnp.asarray(np.eye(n) + 0.2 * rng.normal(size=(2, n, n)))
    sigma_hat = jnp.asarray(0.3 * rng.normal(size=(2, n, n))) + 0.1 * jnp.eye(n)
    state = State(jnp.zeros((2, n)), phi, jnp.zeros((2, n)), sigma_hat @ jnp.linalg.inv(phi))
    trace_sigma = float(jnp.trace(jnp.sum(sigma_hat, axis=0)))
    trajectory = run(system, state, 0.02, 10_000, every=20, observers=("volumes", "energy"))
    volumes = trajectory.observables["volumes"]
    energy = float(trajectory.observables["energy"][0])
    # single volumes: sum_K ln det phi_K = const + t Tr(Sigma_total) / (I + A + nB), unbounded
    total = np.sum(np.log(volumes), axis=1)
    np.testing.assert_allclose(total, total[0] + trace_sigma / mu * trajectory.times,
                               rtol=1e-9, atol=1e-9)
    # relative volume: for n = 2, det X = (M1^2 - M2)/2 and each |M_a - 2| <= 2 sqrt(E/k)
    r = 2.0 * np.sqrt(energy / k)
    log_bound = np.log(((2.0 + r) ** 2 - (2.0 - r)) / 2.0)
    log_relative = np.log(volumes[:, 1] / volumes[:, 0])
    assert np.max(np.abs(log_relative)) <= log_bound
    assert np.min(np.log(volumes[-1])) > 3.0 * log_bound  # both bodies grew past the bound
