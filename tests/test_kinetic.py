"""Kinetic energies (6)-(10), (63)-(74) and their Legendre transforms (76a)-(86).

Closed forms are checked against autodiff and against independent Legendre transforms built
from the Hessian (the metric) of the Lagrangian; drift flows against a high-accuracy numerical
integration of Hamilton's equations derived by autodiff of ``term.hamiltonian``.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.flatten_util import ravel_pytree
from scipy.integrate import solve_ivp

from affinebody import kinetic as K
from affinebody.state import State, VelocityState
from samples import BODIES, TRANSLATIONAL, bitensor, kinetic_sample, spd


def tr(a):
    return jnp.trace(a, axis1=-2, axis2=-1)


def t(a):
    return jnp.swapaxes(a, -1, -2)


def internal_model(name, n, rng):
    """The registered model ``name`` with per-body parameters (``samples.kinetic_sample``)."""
    if name == "af-J-spherical":
        return K.AffineJ(1.3 * np.eye(n))
    return kinetic_sample(K.MODELS[name], n, rng)


def translational_model(name, n=2, rng=None):
    return kinetic_sample(TRANSLATIONAL[name], n, rng)


# the batteries below run over the registries: a registered model gets them all
INTERNAL = [*K.MODELS, "af-J-spherical"]
EXACT = [name for name, cls in K.MODELS.items() if cls.exact_flow]
SPLIT = [name for name, cls in K.MODELS.items() if not cls.exact_flow]


def random_state(rng, n, scale=0.5):
    return State(
        x=jnp.asarray(rng.standard_normal((BODIES, n))),
        phi=jnp.asarray(np.eye(n) + 0.3 * rng.standard_normal((BODIES, n, n))),
        p=jnp.asarray(scale * rng.standard_normal((BODIES, n))),
        pi=jnp.asarray(scale * rng.standard_normal((BODIES, n, n))),
    )


def close(a, b, tol=1e-10):
    a, b = np.asarray(a), np.asarray(b)
    scale = max(1.0, float(np.max(np.abs(b))))
    return np.max(np.abs(a - b)) <= tol * scale


# ------------------------------------------------------------------------------------------
# Legendre transforms: autodiff, round trips, and an independent transform via the metric
# ------------------------------------------------------------------------------------------


def metric_hamiltonian(lagrangian, phi, mom_conj):
    """1/2 m^T G^-1 m with G the Hessian of the (quadratic) Lagrangian in the velocities.

    ``mom_conj`` is dT/dvel (the array with the shape of the velocity); the Lagrangian is summed
    over bodies, so G is block-diagonal and this is the total Hamiltonian.
    """
    zero = jnp.zeros_like(mom_conj)
    g = jax.hessian(lambda v: jnp.sum(lagrangian(phi, v)))(zero)
    size = mom_conj.size
    m = mom_conj.reshape(size)
    return 0.5 * m @ jnp.linalg.solve(g.reshape(size, size), m)


@settings(max_examples=2, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("name", INTERNAL)
def test_internal_legendre_is_autodiff_and_invertible(name, n, seed):
    rng = np.random.default_rng(seed)
    model = internal_model(name, n, rng)
    model.check(n)
    s = random_state(rng, n)
    xi = jnp.asarray(rng.standard_normal((BODIES, n, n)))
    for a, b in internal_legendre_pairs(model, s.phi, xi, s.pi):
        assert a.shape == b.shape
        assert close(a, b)


@jax.jit
def internal_legendre_pairs(model, phi, xi, pi_any):
    """Pairs that must agree; one compilation per model type and n (hypothesis reuses it)."""
    pi = model.legendre(phi, xi)
    # (50): pi^A_i = dT/dxi^i_A, i.e. pi = (dT/dxi)^T in array form.
    grad = jax.grad(lambda v: jnp.sum(model.lagrangian(phi, v)))(xi)
    # The closed-form Hamiltonian equals the Legendre transform computed from the metric,
    # and (dH/dpi)^T is the velocity (Hamilton's first equation).
    h_metric = metric_hamiltonian(model.lagrangian, phi, t(pi_any))
    dh = jax.grad(lambda q: jnp.sum(model.hamiltonian(phi, q)))(pi_any)
    return [
        (pi, t(grad)),
        (model.hamiltonian(phi, pi), model.lagrangian(phi, xi)),
        (model.inverse_legendre(phi, pi), xi),
        (model.legendre(phi, model.inverse_legendre(phi, pi_any)), pi_any),
        (jnp.sum(model.hamiltonian(phi, pi_any)), h_metric),
        (t(dh), model.inverse_legendre(phi, pi_any)),
        (model.hamiltonian(phi, pi_any).shape[0] * jnp.ones(()), BODIES * jnp.ones(())),
    ]


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("name", sorted(TRANSLATIONAL))
def test_translational_legendre_is_autodiff_and_invertible(name, n):
    rng = np.random.default_rng(7 + n)
    model = translational_model(name, n, rng)
    model.check(n)
    s = random_state(rng, n)
    v = jnp.asarray(rng.standard_normal((BODIES, n)))
    for a, b in translational_legendre_pairs(model, s.phi, v, s.p):
        assert close(a, b)


@jax.jit
def translational_legendre_pairs(model, phi, v, p_any):
    p = model.legendre(phi, v)
    return [
        (p, jax.grad(lambda w: jnp.sum(model.lagrangian(phi, w)))(v)),
        (model.hamiltonian(phi, p), model.lagrangian(phi, v)),
        (model.inverse_legendre(phi, p), v),
        (jnp.sum(model.hamiltonian(phi, p_any)), metric_hamiltonian(model.lagrangian, phi, p_any)),
    ]


# ------------------------------------------------------------------------------------------
# The paper's printed forms
# ------------------------------------------------------------------------------------------


def inv(a):
    return jnp.linalg.inv(a)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_printed_forms(n):
    rng = np.random.default_rng(100 + n)
    s = random_state(rng, n)
    phi, pi, p = s.phi, s.pi, s.p
    xi = jnp.asarray(rng.standard_normal((BODIES, n, n)))
    v = jnp.asarray(rng.standard_normal((BODIES, n)))
    green, cauchy = t(phi) @ phi, t(inv(phi)) @ inv(phi)  # (11)
    om, om_hat = xi @ inv(phi), inv(phi) @ xi  # (34)
    sig, sig_hat = phi @ pi, pi @ phi  # (45)
    v_hat = jnp.einsum("...ij,...j->...i", inv(phi), v)  # (38)
    p_hat = jnp.einsum("...ia,...i->...a", phi, p)  # (43)

    def quad(vec, mat):
        return jnp.einsum("...i,...ij,...j->...", vec, mat, vec)

    m = 1.7
    # (63), (77a): d'Alembert / is-af translational energy, written with G[phi].
    tr_da = K.DAlembertTranslational(m)
    assert close(tr_da.lagrangian(phi, v), m / 2 * quad(v_hat, green))
    assert close(tr_da.hamiltonian(phi, p), quad(p_hat, inv(green)) / (2 * m))
    # (64), (78a): af-is translational energy, the Cauchy tensor as metric.
    tr_af = K.AffineTranslational(m)
    assert close(tr_af.lagrangian(phi, v), m / 2 * quad(v, cauchy))
    assert close(tr_af.lagrangian(phi, v), m / 2 * jnp.sum(v_hat**2, -1))
    assert close(tr_af.hamiltonian(phi, p), quad(p, inv(cauchy)) / (2 * m))

    j = jnp.asarray(spd(rng, n))
    # (6), (52)/(76a): d'Alembert internal.
    da = K.DAlembert(j)
    assert close(da.lagrangian(phi, xi), 0.5 * tr(xi @ j @ t(xi)))
    assert close(da.hamiltonian(phi, pi), 0.5 * tr(t(pi) @ inv(j) @ pi))
    # (65), (79a): af-J.
    afj = K.AffineJ(j)
    assert close(afj.lagrangian(phi, xi), 0.5 * tr(cauchy @ xi @ j @ t(xi)))
    assert close(afj.lagrangian(phi, xi), 0.5 * tr(om_hat @ j @ t(om_hat)))
    assert close(afj.hamiltonian(phi, pi), 0.5 * tr(inv(cauchy) @ t(pi) @ inv(j) @ pi))
    assert close(afj.hamiltonian(phi, pi), 0.5 * tr(t(sig_hat) @ inv(j) @ sig_hat))
    # (66), (80a): af-J with spherical J is af-is with A = B = 0.
    i0 = 1.3
    afis0 = K.AffineIsotropic(i0, 0.0, 0.0)
    for model in (K.AffineJ(i0 * jnp.eye(n)), afis0):
        assert close(model.lagrangian(phi, xi), i0 / 2 * tr(cauchy @ xi @ t(xi)))
        assert close(model.hamiltonian(phi, pi), tr(inv(cauchy) @ t(pi) @ pi) / (2 * i0))
        assert close(model.hamiltonian(phi, pi), tr(t(sig_hat) @ sig_hat) / (2 * i0))
    # (67), (68), (81a): H-af.
    hm = jnp.asarray(spd(rng, n))
    h_phi = inv(phi) @ hm @ t(inv(phi))
    haf = K.HAffine(hm)
    assert close(haf.lagrangian(phi, xi), 0.5 * tr(om @ hm @ t(om)))
    assert close(haf.lagrangian(phi, xi), 0.5 * tr(xi @ h_phi @ t(xi)))
    assert close(haf.hamiltonian(phi, pi), 0.5 * tr(t(sig) @ inv(hm) @ sig))
    assert close(haf.hamiltonian(phi, pi), 0.5 * tr(t(pi) @ inv(h_phi) @ pi))
    # (70)/(82a), (71)/(83a) with the reciprocal bi-tensor
    # L~[A,B,C,D] L[C,D,E,F] = delta_AE delta_BF, contracted as L~ Sigma^B_A Sigma^D_C.
    for cls, vel, spin in ((K.LeftInvariant, om_hat, sig_hat), (K.RightInvariant, om, sig)):
        bi = jnp.asarray(bitensor(rng, n))
        recip = inv(bi.reshape(n * n, n * n)).reshape(n, n, n, n)
        model = cls(bi)
        assert close(model.lagrangian(phi, xi), 0.5 * jnp.einsum("abcd,...ab,...cd->...", bi,
                                                                 vel, vel))
        assert close(model.hamiltonian(phi, pi), 0.5 * jnp.einsum("abcd,...ba,...dc->...", recip,
                                                                  spin, spin))
    # (72) and (84a)/(85) with the constants (86).
    a_, b_ = 0.7, -0.2
    afaf = K.AffineAffine(a_, b_)
    for vel in (om, om_hat):
        assert close(afaf.lagrangian(phi, xi), a_ / 2 * tr(vel @ vel) + b_ / 2 * tr(vel) ** 2)
    for spin in (sig, sig_hat):
        h_afaf = tr(spin @ spin) / (2 * a_) - b_ * tr(spin) ** 2 / (2 * a_ * (a_ + n * b_))
        assert close(afaf.hamiltonian(phi, pi), h_afaf)
    i_, a_, b_ = 1.2, 0.4, -0.15
    i_t = (i_**2 - a_**2) / i_
    a_t = (a_**2 - i_**2) / a_
    b_t = -(i_ + a_) * (i_ + a_ + n * b_) / b_
    for cls, vel, spin in ((K.IsotropicAffine, om, sig), (K.AffineIsotropic, om_hat, sig_hat)):
        model = cls(i_, a_, b_)
        t73 = i_ / 2 * tr(t(vel) @ vel) + a_ / 2 * tr(vel @ vel) + b_ / 2 * tr(vel) ** 2
        assert close(model.lagrangian(phi, xi), t73)
        h86 = (tr(t(spin) @ spin) / (2 * i_t) + tr(spin @ spin) / (2 * a_t)
               + tr(spin) ** 2 / (2 * b_t))
        assert close(model.hamiltonian(phi, pi), h86)


# ------------------------------------------------------------------------------------------
# Positive definiteness: (73)/(74) are positive definite iff I + A > 0, I - A > 0, I + A + nB > 0
# ------------------------------------------------------------------------------------------


def metric_eigenvalues(model, n):
    """Eigenvalues of the Hessian of T in xi at a generic phi (signature = that of the metric)."""
    phi = jnp.asarray(np.eye(n) + 0.3 * np.random.default_rng(3).standard_normal((1, n, n)))
    g = _metric(model, phi)
    return np.linalg.eigvalsh(np.asarray(g).reshape(n * n, n * n))


@jax.jit
def _metric(model, phi):
    return jax.hessian(lambda v: jnp.sum(model.lagrangian(phi, v)))(jnp.zeros_like(phi))


EPS = 0.05


def region_cases(n):
    """(boundary message, (I, A, B) just inside, (I, A, B) just outside) for each boundary."""
    return [
        ("I \\+ kinetic.A must be > 0", (1.0, -1.0 + EPS, 1.0), (1.0, -1.0 - EPS, 1.0)),
        ("kinetic.I must be > kinetic.A", (1.0, 1.0 - EPS, 0.0), (1.0, 1.0 + EPS, 0.0)),
        ("n kinetic.B must be > 0", (1.0, 0.0, -1.0 / n + EPS), (1.0, 0.0, -1.0 / n - EPS)),
    ]


@pytest.mark.parametrize("cls", [K.IsotropicAffine, K.AffineIsotropic])
@pytest.mark.parametrize("n", [2, 3])
def test_positive_definite_region_of_73_74(cls, n):
    for message, inside, outside in region_cases(n):
        assert metric_eigenvalues(cls(*inside), n).min() > 0
        cls(*inside).check(n)
        assert metric_eigenvalues(cls(*outside), n).min() < 0
        with pytest.raises(ValueError, match=message):
            cls(*outside).check(n)
    # The region is a cone: the same answers at 1e308 times the values, where I + A, I - A
    # and I + A + nB overflow float64 (the check scales them; no overflow warning either)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for message, inside, outside in region_cases(n):
            cls(*(1e308 * v for v in inside)).check(n)
            with pytest.raises(ValueError, match=message):
                cls(*(1e308 * v for v in outside)).check(n)
    # On the three subspaces the metric is I + A (sym. traceless), I - A (skew), I + A + nB.
    i_, a_, b_ = 1.0, 0.3, 0.2
    phi = jnp.eye(n)[None]
    model = cls(i_, a_, b_)
    sym = jnp.zeros((n, n)).at[0, 1].set(1.0).at[1, 0].set(1.0)[None]
    skw = jnp.zeros((n, n)).at[0, 1].set(1.0).at[1, 0].set(-1.0)[None]
    dil = jnp.eye(n)[None]
    for vel, coefficient in ((sym, i_ + a_), (skw, i_ - a_), (dil, i_ + a_ + n * b_)):
        t_expected = 0.5 * coefficient * jnp.sum(vel * vel)
        assert close(model.lagrangian(phi, vel)[0], t_expected)


@pytest.mark.parametrize("cls", [K.IsotropicAffine, K.AffineIsotropic])
def test_positive_definite_region_n1_is_trace_only(cls):
    # n = 1: T = (I + A + B)/2 xi^2 / phi^2; I - A < 0 does not matter.
    assert metric_eigenvalues(cls(1.0, 1.5, 0.0), 1).min() > 0
    cls(1.0, 1.5, 0.0).check(1)
    assert metric_eigenvalues(cls(1.0, 0.0, -1.0 - EPS), 1).min() < 0
    with pytest.raises(ValueError, match="kinetic.I \\+ kinetic.A \\+ kinetic.B must be > 0"):
        cls(1.0, 0.0, -1.0 - EPS).check(1)
    with pytest.raises(ValueError, match="kinetic.I must be > kinetic.A"):
        cls(1.0, 1.5, 0.0).check(2)


@pytest.mark.parametrize("n", [2, 3])
def test_af_af_is_indefinite_but_regular(n):
    model = K.AffineAffine(0.7, 0.4)
    eig = metric_eigenvalues(model, n)
    assert eig.min() < 0 < eig.max()
    model.check(n)  # indefinite by design: accepted
    assert np.min(np.abs(metric_eigenvalues(K.AffineAffine(0.0, 0.4), n))) < 1e-12
    with pytest.raises(ValueError, match="kinetic.A must be nonzero"):
        K.AffineAffine(0.0, 0.4).check(n)
    assert np.min(np.abs(metric_eigenvalues(K.AffineAffine(0.6, -0.6 / n), n))) < 1e-12
    with pytest.raises(ValueError, match="kinetic.A \\+ n kinetic.B must be nonzero"):
        K.AffineAffine(0.6, -0.6 / n).check(n)


def test_check_rejects_degenerate_inertia():
    bad = np.diag([1.0, -0.5])
    for model in (K.DAlembert(bad), K.AffineJ(bad)):
        with pytest.raises(ValueError, match="kinetic.J must be positive definite"):
            model.check(2)
    with pytest.raises(ValueError, match="kinetic.H must be symmetric"):
        K.HAffine(np.array([[1.0, 0.5], [0.0, 1.0]])).check(2)
    with pytest.raises(ValueError, match="kinetic.mass must be > 0 \\(got mass=-1 for body 1\\)"):
        K.DAlembertTranslational(np.array([1.0, -1.0])).check(2)
    with pytest.raises(ValueError, match="kinetic.mass must be > 0"):
        K.AffineTranslational(0.0).check(2)
    nonsym = bitensor(np.random.default_rng(0), 2)
    nonsym[0, 1, 1, 0] += 0.3
    with pytest.raises(ValueError, match="kinetic.L .* must be symmetric"):
        K.LeftInvariant(nonsym).check(2)
    with pytest.raises(ValueError, match="kinetic.R .* must be positive definite"):
        K.RightInvariant(-bitensor(np.random.default_rng(0), 2)).check(2)
    with pytest.raises(ValueError, match="float64"):
        K.AffineIsotropic(np.float32(1.0)).check(2)


# ------------------------------------------------------------------------------------------
# Drift flows
# ------------------------------------------------------------------------------------------


def total_hamiltonian(term, state):
    """Total energy of a translational (p) or internal (pi) term, summed over bodies."""
    if type(term) in K.TRANSLATIONAL_MODELS.values():
        return jnp.sum(term.hamiltonian(state.phi, state.p))
    if isinstance(term, K.KineticEnergy):
        return term.hamiltonian(state)
    return jnp.sum(term.hamiltonian(state.phi, state.pi))


def hamilton_vector_field(term, state):
    """Hamilton's equations by autodiff: dphi/dt = (dH/dpi)^T, dpi/dt = -(dH/dphi)^T."""
    g = jax.grad(lambda s: total_hamiltonian(term, s))(state)
    return State(x=g.p, phi=t(g.pi), p=-g.x, pi=-t(g.phi))


def integrate(term, state, time):
    """Reference solution: DOP853 with rtol = atol = 1e-13."""
    flat, unravel = ravel_pytree(state)
    field = jax.jit(lambda y: ravel_pytree(hamilton_vector_field(term, unravel(y)))[0])

    def rhs(_, y):
        return np.asarray(field(y))

    sol = solve_ivp(rhs, (0.0, time), np.asarray(flat), method="DOP853", rtol=1e-13, atol=1e-13)
    assert sol.success
    return unravel(jnp.asarray(sol.y[:, -1]))


@jax.jit
def flow(term, state, h):
    return term.flow(state, h)


def states_close(a, b, tol):
    return all(close(u, v, tol) for u, v in zip(a, b, strict=True))


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("name", EXACT + [f"tr-{name}" for name in TRANSLATIONAL])
def test_exact_flow_solves_hamilton_equations(name, n):
    rng = np.random.default_rng(200 + n)
    if name.startswith("tr-"):
        term = translational_model(name[3:], n, rng)
    else:
        term = internal_model(name, n, rng)
    assert term.exact_flow
    s0 = random_state(rng, n)
    time = 0.6
    assert states_close(flow(term, s0, time), integrate(term, s0, time), 1e-9)
    # Exact at any step size: the flow is a one-parameter group.
    h = 0.9
    twice = flow(term, flow(term, s0, h), h)
    assert states_close(twice, flow(term, s0, 2 * h), 1e-10)
    assert close(total_hamiltonian(term, twice), total_hamiltonian(term, s0), 1e-11)


def conserved_quantities(term, state):
    """The momentum maps of the symmetries ``term.symmetry`` claims (per body)."""
    sig, sig_hat = state.phi @ state.pi, state.pi @ state.phi
    out = {}
    if "spatial-affine" in term.symmetry:
        out["Sigma"] = sig
    if "material-affine" in term.symmetry:
        out["Sigma_hat"] = sig_hat
    if term.exact_flow:  # rank-one splittings conserve only the affine spins
        if "spatial-euclidean" in term.symmetry:
            out["spin"] = sig - t(sig)  # (49)
        if "material-euclidean" in term.symmetry:
            out["vorticity"] = sig_hat - t(sig_hat)  # (49)
        if hasattr(term, "J"):  # material O(n, J) generator: skew(J^-1 Sigma_hat)
            jinv_s = jnp.linalg.solve(jnp.asarray(term.J), sig_hat)
            out["J-vorticity"] = jinv_s - t(jinv_s)
    return out


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("name", INTERNAL)
def test_flows_conserve_the_momentum_maps_of_their_symmetries(name, n):
    rng = np.random.default_rng(300 + n)
    term = internal_model(name, n, rng)
    s0 = random_state(rng, n)
    s1 = flow(term, s0, 0.7)
    before, after = conserved_quantities(term, s0), conserved_quantities(term, s1)
    expected = {"dalembert": {"spin", "J-vorticity"}, "af-af": {"Sigma", "Sigma_hat", "spin",
                "vorticity"}, "is-af": {"Sigma_hat", "spin", "vorticity"},
                "af-is": {"Sigma", "spin", "vorticity"}, "af-J": {"Sigma"},
                "af-J-spherical": {"Sigma"}, "l-af": {"Sigma"}, "H-af": {"Sigma_hat"},
                "r-af": {"Sigma_hat"}}[name]
    assert set(before) == expected
    for key in before:
        assert close(after[key], before[key], 1e-10), key


@pytest.mark.parametrize("n", [2, 3])
@pytest.mark.parametrize("name", SPLIT + ["system-af-is"])
def test_splitting_flows_converge_at_second_order(name, n):
    rng = np.random.default_rng(400 + n)
    if name == "system-af-is":
        term = K.KineticEnergy(K.AffineTranslational(1.2), K.AffineIsotropic(1.0, 0.2, 0.3))
    else:
        term = internal_model(name, n, rng)
    assert not term.exact_flow
    s0 = random_state(rng, n, scale=0.4)
    time = 0.5
    reference = integrate(term, s0, time)
    errors = []
    for steps in (4, 8, 16):
        s = s0
        for _ in range(steps):
            s = flow(term, s, time / steps)
        errors.append(max(np.max(np.abs(np.asarray(u - v))) for u, v in zip(s, reference,
                                                                          strict=True)))
    assert np.all(np.isfinite(errors)) and errors[-1] < 0.05, errors
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders > 1.8) & (orders < 2.3)), (errors, orders)
    # Symplectic splittings keep the energy error O(h^2) and the affine spins exact.
    assert close(total_hamiltonian(term, s), total_hamiltonian(term, s0), 1e-2)


def canonical(n):
    """(z -> State, State -> z) with z = (x, phi, p, P = pi^T): P is conjugate to phi (42)."""

    def to_state(z):
        k = n * n
        return State(z[:n][None], z[n:n + k].reshape(1, n, n), z[n + k:2 * n + k][None],
                     t(z[2 * n + k:].reshape(n, n))[None])

    def to_z(s):
        return jnp.concatenate([s.x[0], s.phi[0].ravel(), s.p[0], t(s.pi[0]).ravel()])

    return to_state, to_z


@pytest.mark.parametrize(
    "term",
    [K.DAlembert(np.diag([1.0, 2.0])), K.AffineIsotropic(1.0, 0.3, 0.2),
     K.IsotropicAffine(1.0, -0.3, 0.2), K.AffineAffine(0.7, 0.4), K.AffineTranslational(1.3),
     K.LeftInvariant(bitensor(np.random.default_rng(1), 2))],
    ids=lambda term: type(term).__name__,
)
def test_flows_are_symplectic(term):
    n = 2
    to_state, to_z = canonical(n)
    z0 = to_z(random_state(np.random.default_rng(5), n))  # the first body
    jac = jax.jit(jax.jacfwd(lambda z: to_z(term.flow(to_state(z), 0.8))))(z0)
    half = z0.size // 2
    omega = jnp.block([[jnp.zeros((half, half)), jnp.eye(half)],
                       [-jnp.eye(half), jnp.zeros((half, half))]])
    assert close(jac.T @ omega @ jac, omega, 1e-11)
    assert not close(jac, jnp.eye(z0.size), 1e-3)  # the flow moves something


# ------------------------------------------------------------------------------------------
# Systems of bodies (10), (55), the d'Alembert model from its constituents, the registry
# ------------------------------------------------------------------------------------------


def test_dalembert_kinetic_energy_is_the_constituents_kinetic_energy():
    """(2) r_p = x + phi a_p with sum mu_p a_p = 0 gives (6) with M, J of (8)."""
    rng = np.random.default_rng(11)
    n, count = 3, 5
    mu = rng.uniform(0.5, 2.0, count)
    a = rng.standard_normal((count, n))
    a -= (mu @ a) / mu.sum()  # centre of mass at the origin of the material frame
    mass, j = mu.sum(), np.einsum("p,pk,pl->kl", mu, a, a)
    x, v = rng.standard_normal(n), rng.standard_normal(n)
    phi, xi = np.eye(n) + 0.2 * rng.standard_normal((n, n)), rng.standard_normal((n, n))
    velocities = v + a @ xi.T  # d/dt (x + phi a_p)
    t_constituents = 0.5 * np.sum(mu * np.sum(velocities**2, axis=-1))
    energy = K.KineticEnergy(K.DAlembertTranslational(mass), K.DAlembert(j))
    vs = VelocityState(jnp.asarray(x[None]), jnp.asarray(phi[None]), jnp.asarray(v[None]),
                       jnp.asarray(xi[None]))
    assert close(energy.lagrangian(vs), t_constituents, 1e-12)


@pytest.mark.parametrize("translational", sorted(TRANSLATIONAL))
def test_system_energy_is_the_sum_over_bodies(translational):
    rng = np.random.default_rng(12)
    n = 2
    energy = K.KineticEnergy(translational_model(translational), internal_model("af-is", n, rng))
    energy.check(n)
    s = random_state(rng, n)
    vs = energy.inverse_legendre(s)
    tr_term, int_term = energy.pieces
    per_body = []
    for body in range(BODIES):
        single = K.KineticEnergy(
            type(tr_term)(tr_term.mass[body]),
            K.AffineIsotropic(int_term.I[body], int_term.A[body], int_term.B[body]),
        )
        sub = State(*(leaf[body:body + 1] for leaf in s))
        per_body.append(single.hamiltonian(sub))
        assert close(single.lagrangian(single.inverse_legendre(sub)), single.hamiltonian(sub))
    assert close(energy.hamiltonian(s), sum(per_body), 1e-12)
    assert close(energy.lagrangian(vs), energy.hamiltonian(s), 1e-12)
    assert states_close(energy.legendre(vs), s, 1e-12)
    # Identical bodies: scalar parameters equal per-body arrays holding equal values.
    same = K.KineticEnergy(type(tr_term)(2.0), K.AffineIsotropic(1.0, 0.2, 0.1))
    same_arrays = K.KineticEnergy(type(tr_term)(np.full(BODIES, 2.0)),
                                  K.AffineIsotropic(*(np.full(BODIES, c) for c in (1.0, 0.2, 0.1))))
    assert close(same.hamiltonian(s), same_arrays.hamiltonian(s), 1e-13)


def test_system_flow_exact_with_dalembert_translation():
    rng = np.random.default_rng(13)
    n = 3
    energy = K.KineticEnergy(translational_model("dalembert"), internal_model("af-is", n, rng))
    assert energy.exact_flow
    assert energy.symmetry == frozenset({"spatial-euclidean", "material-euclidean"})
    s0 = random_state(rng, n)
    assert states_close(flow(energy, s0, 0.6), integrate(energy, s0, 0.6), 1e-9)
    assert not K.KineticEnergy(translational_model("dalembert"), K.AffineJ(np.eye(n))).exact_flow


def test_af_is_with_spherical_inertia_is_af_J():
    """(66)/(80a) is both af-J with J = I Id and af-is (74) with A = B = 0."""
    rng = np.random.default_rng(14)
    n = 3
    s = random_state(rng, n)
    xi = jnp.asarray(rng.standard_normal((BODIES, n, n)))
    a, b = K.AffineJ(1.7 * np.eye(n)), K.AffineIsotropic(1.7)
    assert close(a.lagrangian(s.phi, xi), b.lagrangian(s.phi, xi))
    assert close(a.legendre(s.phi, xi), b.legendre(s.phi, xi))
    assert {"spatial-affine", "material-euclidean"} <= a.symmetry & b.symmetry


def test_registry():
    assert set(K.MODELS) == {"dalembert", "is-af", "af-is", "af-J", "H-af", "l-af", "r-af",
                             "af-af"}
    assert K.MODELS["af-is"] is K.AffineIsotropic and K.MODELS["is-af"] is K.IsotropicAffine
    assert K.MODELS["dalembert"] is K.DAlembert and K.MODELS["af-af"] is K.AffineAffine
    assert K.TRANSLATIONAL_MODELS["dalembert"] is K.DAlembertTranslational
    assert K.TRANSLATIONAL_MODELS["is-af"] is K.DAlembertTranslational
    assert K.TRANSLATIONAL_MODELS["af-is"] is K.AffineTranslational
    for cls in list(K.MODELS.values()) + list(K.TRANSLATIONAL_MODELS.values()):
        assert cls.__doc__ and "(" in cls.__doc__
