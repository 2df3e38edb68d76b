"""The host drift (kinetic.isotropic_flow_host, Numba kernel _host_kernels/drift.py): the exact
af-is / is-af flow that `affinebody run` runs on a CPU, against the JAX flow (the GPU path),
its independence of the thread count, and the momentum maps it must conserve."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import _host, _linalg
from affinebody import kinetic as K
from affinebody.state import State

BODIES = 64


def spinning_states(rng, n, left):
    """phi near Id and pi whose spin S (pi phi left, phi pi right) is a large rotation and
    dilatation rate plus a moderate shear: h X reaches 1-norms of ~10^2 (several squarings in
    expm) while C = expm(X_c) stays well conditioned, so both flows are accurate to round-off
    and must agree to it (an ill-conditioned C amplifies any rounding difference by cond C)."""
    phi = np.eye(n) + 0.3 * rng.standard_normal((BODIES, n, n))
    w = rng.standard_normal((BODIES, n, n)) * rng.uniform(0.1, 40.0, (BODIES, 1, 1))
    spin = (w - np.swapaxes(w, -1, -2)) + rng.uniform(-30, 30, (BODIES, 1, 1)) * np.eye(n)
    spin = spin + 0.3 * rng.standard_normal((BODIES, n, n))
    inv = np.linalg.inv(phi)
    pi = inv @ spin if not left else spin @ inv  # S = pi phi (left), phi pi (right)
    # h / I~ etc. over five decades: every Pade degree of the host expm is used
    coefs = rng.uniform(-1.0, 1.0, (BODIES, 3))
    coefs[BODIES // 4:] *= 10.0 ** rng.uniform(-5.0, 0.0, (BODIES - BODIES // 4, 1))
    coefs[:, 1] *= 0.05  # the trace part of X_c: exp(n c1 Tr S) stays finite
    return jnp.asarray(phi), jnp.asarray(pi), jnp.asarray(coefs)


def relative_error(a, b):
    """max over bodies of |a - b| / |b| (max norms per body)."""
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.max(np.abs(a - b), axis=(-2, -1)) / np.max(np.abs(b), axis=(-2, -1))))


host_flow = jax.jit(K.isotropic_flow_host, static_argnums=3)
jax_flow = jax.jit(K.isotropic_flow_jax, static_argnums=3)


@pytest.mark.parametrize("left", [True, False], ids=["af-is", "is-af"])
@pytest.mark.parametrize("n", [2, 3])
def test_host_drift_is_the_jax_flow(n, left):
    phi, pi, coefs = spinning_states(np.random.default_rng(10 * n + left), n, left)
    s = np.asarray(pi @ phi if left else phi @ pi)
    c = np.asarray(coefs)
    generators = [c[:, 0, None, None] * s + (c[:, 1] * np.trace(s, axis1=1, axis2=2))[:, None,
                  None] * np.eye(n), c[:, 2, None, None] * (np.swapaxes(s, -1, -2) - s)]
    norms = np.concatenate([np.max(np.abs(x).sum(-2), -1) for x in generators])
    # Pade degrees 3, 5 to 9, and 13 with squarings (three and more) are exercised
    assert np.min(norms) < 1.5e-2 and np.any((norms > 0.26) & (norms < 2.0))
    assert np.max(norms) > 8 * _linalg.THETA13
    host, reference = host_flow(phi, pi, coefs, left), jax_flow(phi, pi, coefs, left)
    assert relative_error(host[0], reference[0]) < 1e-12
    assert relative_error(host[1], reference[1]) < 1e-12
    # vmap: one callback over the stacked batch, the same bits as the unbatched call
    halves = jax.vmap(lambda *a: K.isotropic_flow_host(*a, left))(
        phi.reshape(2, -1, n, n), pi.reshape(2, -1, n, n), coefs.reshape(2, -1, 3))
    assert np.array_equal(np.asarray(halves[0]).reshape(phi.shape), np.asarray(host[0]))


def test_host_drift_bits_do_not_depend_on_the_thread_count(monkeypatch):
    phi, pi, coefs = spinning_states(np.random.default_rng(3), 3, True)
    monkeypatch.setattr(K, "HOST_DRIFT_THREAD_MIN_ROWS", 0)
    out = {}
    for threads in (1, 2):
        monkeypatch.setattr(K._host, "threads", lambda parts, threads=threads: threads)
        out[threads] = [np.asarray(a) for a in K.isotropic_flow_host(phi, pi, coefs, True)]
    assert all(np.array_equal(a, b) for a, b in zip(out[1], out[2], strict=True))


@pytest.mark.parametrize("model", [K.AffineIsotropic(1.0, 0.2, 0.1),
                                   K.IsotropicAffine(1.3, -0.4, 0.2)],
                         ids=["af-is", "is-af"])
def test_host_drift_conserves_the_momentum_maps(model, monkeypatch):
    """The product's drift (term.flow runs the callback on a CPU from HOST_DRIFT_MIN_BODIES
    bodies on, lowered here to this test's 64) conserves H, the spin and the vorticity (49)
    and the affine spin of the side its symmetry is affine on: Sigma = phi pi for af-is,
    Sigma_hat = pi phi for is-af."""
    monkeypatch.setattr(K, "HOST_DRIFT_MIN_BODIES", BODIES)
    rng = np.random.default_rng(7)
    n = 3
    phi, pi, _ = spinning_states(rng, n, isinstance(model, K.AffineIsotropic))
    pi = pi / 20.0
    state = State(jnp.zeros((BODIES, n)), phi, jnp.zeros((BODIES, n)), pi)
    flow = jax.jit(model.flow)
    assert _host.CALLBACK_NAME in str(jax.make_jaxpr(model.flow)(state, 0.9))
    after = flow(state, 0.9)
    assert relative_error(after.phi, state.phi) > 1e-2  # it moves
    sig, sig_hat = state.phi @ state.pi, state.pi @ state.phi
    sig1, sig_hat1 = after.phi @ after.pi, after.pi @ after.phi
    affine = (sig1, sig) if isinstance(model, K.AffineIsotropic) else (sig_hat1, sig_hat)
    t = lambda a: jnp.swapaxes(a, -1, -2)  # noqa: E731
    for new, old in (affine, (sig1 - t(sig1), sig - t(sig)),
                     (sig_hat1 - t(sig_hat1), sig_hat - t(sig_hat))):
        assert relative_error(new, old) < 1e-12
    energy = lambda s: np.asarray(model.hamiltonian(s.phi, s.pi))  # noqa: E731
    assert np.max(np.abs(energy(after) / energy(state) - 1.0)) < 1e-12


def test_the_set_up_compiles_the_drift_kernel_that_the_loop_calls():
    """kinetic.compile_host_drift (what config.build runs as its "drift kernel" stage) compiles
    the host drift for the argument types of the loop's callback, so the loop's first drift
    compiles nothing more (Numba compiles again for any other type: a writable operand, say);
    and it does nothing where the loop runs the JAX flow (n = 2, few bodies, no isotropic
    affine model, or no host kernels at all: a GPU, or no Numba)."""
    model = K.AffineIsotropic(1.0, 0.2, 0.1)
    bodies = K.HOST_DRIFT_MIN_BODIES
    rng = np.random.default_rng(3)
    assert not K.compile_host_drift(model, np.zeros((bodies, 2, 2)))
    assert not K.compile_host_drift(model, np.zeros((bodies - 1, 3, 3)))
    assert not K.compile_host_drift(K.DAlembert(np.eye(3)), np.zeros((bodies, 3, 3)))
    if not _host.in_use():  # the loop runs the JAX flow: nothing for the set-up to compile
        assert not K.compile_host_drift(model, np.zeros((bodies, 3, 3)))
        return
    K._drift_kernel.cache_clear()  # a new dispatcher: only what is compiled from here counts
    assert K.compile_host_drift(model, np.zeros((bodies, 3, 3)))
    kernel = K._drift_kernel(3)
    assert len(kernel.signatures) == 1
    phi = jnp.asarray(np.eye(3) + 0.1 * rng.standard_normal((bodies, 3, 3)))
    pi = jnp.asarray(rng.standard_normal((bodies, 3, 3)))
    coefs = jnp.asarray(rng.uniform(-0.1, 0.1, (bodies, 3)))
    for left in (True, False):  # af-is and is-af: the same types
        jax.block_until_ready(host_flow(phi, pi, coefs, left))
    assert len(kernel.signatures) == 1


def test_a_gradient_through_steps_of_the_host_drift_is_the_central_difference(monkeypatch):
    """What docs/tutorials/autodiff.md does, with the host drift in the loop (n = 3, the
    product's path at scale, forced here for 2 bodies): the gradient of <det phi> after 20
    Strang steps with respect to k, the stiffness of a Python-function one-body term (no pair
    term: the bodies' drift and kick are what is differentiated), and to A of af-is (74), a
    leaf of the kinetic model, by reverse mode through the callback's custom_jvp and a
    lax.scan; equal to central differences (whose error, ~h^2 f''' and round-off / h, is
    ~1e-9 here) and to the same gradient through the JAX flow."""
    from affinebody import potentials as pot
    from affinebody.integrators import get_integrator
    from affinebody.system import HamiltonianSystem

    rng = np.random.default_rng(4)
    state = State(x=jnp.zeros((2, 3)),
                  phi=jnp.asarray(np.eye(3) + 0.1 * rng.standard_normal((2, 3, 3))),
                  p=jnp.zeros((2, 3)), pi=jnp.asarray(0.3 * rng.standard_normal((2, 3, 3))))
    strang = get_integrator("strang")

    def mean_volume(k, A):
        volume = pot.OneBodyPotential(lambda det, trG: k * (det - 1.0) ** 2 + 0.1 * trG,
                                      ("det", "trG"))
        kinetic = K.KineticEnergy(K.DAlembertTranslational(1.0), K.AffineIsotropic(1.0, A, 0.1))
        system = HamiltonianSystem(kinetic, volume, group="GL+")
        end, _ = jax.lax.scan(lambda s, _: (strang.step(system, s, 0.02), None), state, None,
                              length=20)
        return jnp.mean(_linalg.det(end.phi))

    point, gradients = (3.0, 0.2), {}
    for fewest in (0, 10**9):  # host drift, then the JAX flow
        monkeypatch.setattr(K, "HOST_DRIFT_MIN_BODIES", fewest)
        assert K.host_drift_in_use(state.phi) == (fewest == 0 and _host.in_use())
        gradients[fewest] = np.array(jax.jit(jax.grad(mean_volume, argnums=(0, 1)))(*point))
    h, value = 1e-4, jax.jit(mean_volume)
    central = [(value(*(point + h * e)) - value(*(point - h * e))) / (2 * h)
               for e in np.eye(2)]
    assert np.all(np.abs(gradients[0]) > 1e-3)  # both act within 20 steps
    np.testing.assert_allclose(gradients[0], np.array(central, dtype=float), rtol=1e-6)
    np.testing.assert_allclose(gradients[0], gradients[10**9], rtol=1e-11)
