"""Contracts every registered model honours, and the pytree convention the run driver needs.

The batteries are parametrized over the registries (``kinetic.MODELS``,
``kinetic.TRANSLATIONAL_MODELS``, ``potentials.POTENTIALS``): a model gets every check by being
registered (instances come from ``samples``). ``test_kinetic`` runs its Legendre and flow
batteries over the same registries; ``test_potentials`` its catalogue of options.
"""

from __future__ import annotations

import dataclasses
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import config, constraints, runner, simulate
from affinebody import kinetic as K
from affinebody._pytree import is_array_pytree
from affinebody.groups import expm, is_member, project_algebra
from affinebody.potentials import (
    POTENTIALS,
    Cutoff,
    LennardJones,
    PairTerm,
    build_potential,
    generalized_forces,
)
from affinebody.state import State
from samples import (
    BODIES,
    POTENTIAL_EXAMPLES,
    TRANSLATIONAL,
    configuration,
    kinetic_sample,
    kinetic_zero,
    random_linear,
    random_rotation,
    spd,
    transform,
)

# --------------------------------------------------------------------------------------------
# One compiled loop per system structure


@pytest.fixture(scope="module")
def demo():
    return config.build(config.parse_config(runner.demo_config_text()))


def test_demo_system_is_an_array_pytree_and_two_runs_compile_once(demo):
    """The run driver passes the system as a traced argument of one cached jit only when it is
    an array pytree (hashable treedef: the potential is static; array leaves: the inertia)."""
    system, state = demo.system, demo.state
    assert is_array_pytree(system)
    assert system.potential is not None
    assert len(jax.tree.leaves(system)) == len(jax.tree.leaves(system.kinetic)) > 0
    before = simulate._simulate_jit._cache_size()
    first = simulate.run(system, state, 0.01, 2)
    after_first = simulate._simulate_jit._cache_size()
    # the same structure with other kinetic parameters (leaves) reuses the compiled loop
    scaled = system.replace(kinetic=jax.tree.map(lambda a: 1.5 * a, system.kinetic))
    second = simulate.run(scaled, state, 0.01, 2)
    assert after_first - before in (0, 1)  # 0 if an earlier test compiled this structure
    assert simulate._simulate_jit._cache_size() == after_first
    # ... and really uses the new parameters: heavier bodies move less in the same time
    moved = [np.abs(np.asarray(t.final_state.x - state.x)).sum() for t in (first, second)]
    assert moved[1] < moved[0]


def test_mismatched_state_arrays_and_an_empty_state_are_one_line_errors(demo):
    """H of a state whose arrays disagree on N (x of 2 bodies, phi of 3) raised a JAX
    broadcasting TypeError; run of a state with no bodies failed inside NumPy (an argmax of
    an empty sequence). Both are one ValueError naming the state, also under jit for H (the
    shapes are static). Found by an audit of the API."""
    system, state = demo.system, demo.state
    short = State(state.x[:2], state.phi[:3], state.p[:2], state.pi[:3])
    for energy in (system.hamiltonian, jax.jit(system.hamiltonian)):
        with pytest.raises(ValueError, match="state shapes disagree"):
            energy(short)
    empty = State(*(a[:0] for a in state))
    with pytest.raises(ValueError, match="at least one body"):
        simulate.run(system, empty, 0.01, 2)
    assert np.isfinite(float(system.hamiltonian(state)))  # the good state still passes


def _registered_models(n: int = 2) -> list:
    """One instance of every registered kinetic model and potential family."""
    rng = np.random.default_rng(0)
    models = [kinetic_sample(cls, n, rng) for cls in dict.fromkeys(K.MODELS.values())]
    models += [kinetic_sample(cls, n, rng) for cls in TRANSLATIONAL.values()]
    models += [build_potential(name, POTENTIAL_EXAMPLES[name](n), n=n, field="potential.0")
               for name in POTENTIALS]
    return models


def test_models_of_different_classes_never_share_a_treedef():
    """jax.jit reuses a compiled program for arguments of equal treedef, so two classes must
    never have equal treedefs (docs/architecture.md, "The pytree convention"): HAffine(H) and
    DAlembert(J) have one array field of the same shape each, and under jaxlib 0.10.1's
    register_dataclass their treedefs compared equal."""
    models = _registered_models()
    for a, b in ((a, b) for a in models for b in models if type(a) is not type(b)):
        assert jax.tree.structure(a) != jax.tree.structure(b), (type(a), type(b))
    # equal static values of one class: one treedef, the compiled program is shared
    lj = POTENTIAL_EXAMPLES["lennard-jones"](2)
    assert jax.tree.structure(build_potential("lennard-jones", lj, n=2, field="p")) == \
        jax.tree.structure(build_potential("lennard-jones", dict(lj), n=2, field="p"))


def test_one_jitted_function_runs_each_class_its_own_program():
    """A hundred classes with identical fields (one array, one static value) through one jit:
    each call computes with its own class's method. Under register_dataclass about one class
    in ten (400 classes: 44) got another class's program, depending on the hash seed."""
    from affinebody import _pytree

    classes = []
    for k in range(100):
        cls = type(f"Model{k}", (), {"__annotations__": {"a": "Any", "s": "float"},
                                     "s": _pytree.static_field(default=1.0),
                                     "energy": lambda self, k=k: (k + self.s) * self.a})
        classes.append(_pytree.dataclass(cls))
    energy = jax.jit(lambda model: model.energy())
    got = [float(energy(cls(jnp.ones(())))) for cls in classes]
    assert got == [k + 1.0 for k in range(100)]


# --------------------------------------------------------------------------------------------
# Kinetic models: declarations, symmetries, degenerate parameters, drifts on subgroups
# --------------------------------------------------------------------------------------------
# Kinetic models: declarations, symmetries, degenerate parameters, drifts on subgroups

KINETIC = [("internal", name, cls) for name, cls in K.MODELS.items()] + [
    ("translational", name, cls) for name, cls in TRANSLATIONAL.items()]


def kinetic_id(case):
    return f"{case[0]}-{case[1]}"


@pytest.mark.parametrize("case", KINETIC, ids=kinetic_id)
def test_kinetic_model_declares_its_interface(case):
    kind, name, cls = case
    assert issubclass(cls, K.AbstractKineticTerm) and not inspect.isabstract(cls)
    # its config parameters are its fields, and they are the pytree leaves (traced under jit)
    assert cls.parameters == tuple(f.name for f in dataclasses.fields(cls))
    term = kinetic_sample(cls, 3, np.random.default_rng(1))
    assert len(jax.tree.leaves(term)) == len(cls.parameters)
    if kind == "internal":
        assert config.INTERNAL_MODELS[name] == cls.parameters
    assert isinstance(cls.exact_flow, bool) and isinstance(cls.flow_moves_only_x, bool)
    assert cls.constrained_drift in constraints.DRIFT_MODES
    assert constraints.drift_mode(term) == cls.constrained_drift
    # a Lie-group drift needs the side of the invariance it declares
    side_label = {"left": "spatial-affine", "right": "material-affine"}
    if cls.constrained_drift == "lie-group":
        assert side_label[cls.invariance_side] in term.symmetry
    assert term.symmetry <= K.SYMMETRIES


def group_action(label, rng, n, term):
    """(g, side) for a random element of the group named by ``label`` (per body [N, n, n])."""
    if label == "spatial-affine":
        return np.stack([random_linear(rng, n) for _ in range(BODIES)]), "left"
    if label == "spatial-euclidean":
        return np.stack([random_rotation(rng, n) for _ in range(BODIES)]), "left"
    if label == "material-affine":
        return np.stack([random_linear(rng, n) for _ in range(BODIES)]), "right"
    if label == "material-euclidean":
        return np.stack([random_rotation(rng, n) for _ in range(BODIES)]), "right"
    if label == "material-J":  # O(n, J) = {B : B J B^T = J} = J^1/2 O(n) J^-1/2
        j = np.broadcast_to(np.asarray(getattr(term, "J", spd(rng, n, (BODIES,)))),
                            (BODIES, n, n))
        w, u = np.linalg.eigh(j)
        root = u * np.sqrt(w)[..., None, :] @ np.swapaxes(u, -1, -2)
        inv_root = u / np.sqrt(w)[..., None, :] @ np.swapaxes(u, -1, -2)
        rotations = np.stack([random_rotation(rng, n) for _ in range(BODIES)])
        return root @ rotations @ inv_root, "right"
    raise AssertionError(label)


def moved_energies(term, kind, g, side, phi, vel, mom):
    """(T, H) before and after acting with g: left phi -> g phi, xi -> g xi, v -> g v,
    pi -> pi g^-1, p -> g^-T p; right phi -> phi g, xi -> xi g, pi -> g^-1 pi (p, v fixed).
    The momenta move by the cotangent lift, so Tr(pi xi) and p . v are invariant."""
    g = jnp.asarray(g)
    g_inv = jnp.linalg.inv(g)
    if side == "left":
        phi2 = g @ phi
        if kind == "translational":
            vel2 = jnp.einsum("kij,kj->ki", g, vel)
            mom2 = jnp.einsum("kji,kj->ki", g_inv, mom)
        else:
            vel2, mom2 = g @ vel, mom @ g_inv
    else:
        phi2 = phi @ g
        vel2, mom2 = (vel, mom) if kind == "translational" else (vel @ g, g_inv @ mom)
    before = (term.lagrangian(phi, vel), term.hamiltonian(phi, mom))
    after = (term.lagrangian(phi2, vel2), term.hamiltonian(phi2, mom2))
    return before, after


@pytest.mark.parametrize("case", KINETIC, ids=kinetic_id)
def test_kinetic_declared_symmetries_hold_and_are_tight(case):
    """T and H are invariant under the groups the model declares, and change under the
    others (so the declaration is neither wrong nor weaker than the truth)."""
    kind, name, cls = case
    n = 3
    rng = np.random.default_rng(20)
    term = kinetic_sample(cls, n, rng)
    phi = jnp.asarray(np.eye(n) + 0.3 * rng.standard_normal((BODIES, n, n)))
    shape = (BODIES, n) if kind == "translational" else (BODIES, n, n)
    vel, mom = (jnp.asarray(rng.standard_normal(shape)) for _ in range(2))
    for label in sorted(K.SYMMETRIES):
        g, side = group_action(label, rng, n, term)
        (t0, h0), (t1, h1) = moved_energies(term, kind, g, side, phi, vel, mom)
        change = max(float(jnp.max(jnp.abs(t1 - t0) / (1 + jnp.abs(t0)))),
                     float(jnp.max(jnp.abs(h1 - h0) / (1 + jnp.abs(h0)))))
        if label in term.symmetry:
            assert change < 1e-10, (name, label, change)
        else:
            assert change > 1e-4, (name, label, change)


@pytest.mark.parametrize("n", [1, 2, 3])
@pytest.mark.parametrize("case", KINETIC, ids=kinetic_id)
def test_kinetic_check_accepts_samples_and_refuses_zero_parameters(case, n):
    kind, name, cls = case
    kinetic_sample(cls, n, np.random.default_rng(2)).check(n)
    with pytest.raises(ValueError) as info:
        kinetic_zero(cls, n).check(n)
    message = str(info.value)
    assert "\n" not in message
    assert any(f"kinetic.{p}" in message for p in cls.parameters), message


def group_probe(rng, n, group):
    """A state on ``group`` whose co-moving spin Sigma_hat = pi phi lies in its algebra g."""
    phi = expm(project_algebra(jnp.asarray(0.4 * rng.standard_normal((BODIES, n, n))), group))
    sigma_hat = project_algebra(jnp.asarray(rng.standard_normal((BODIES, n, n))), group)
    return State(jnp.asarray(rng.standard_normal((BODIES, n))), phi,
                 jnp.asarray(rng.standard_normal((BODIES, n))), sigma_hat @ jnp.linalg.inv(phi))


def stays_on(group, start, out):
    """phi stays in G and Sigma_hat in g (or phi does not move at all)."""
    sigma_hat = out.pi @ out.phi
    in_algebra = float(jnp.max(jnp.abs(sigma_hat - project_algebra(sigma_hat, group)))) < 1e-9
    fixed = bool(jnp.all(out.phi == start.phi))
    return bool(jnp.all(is_member(out.phi, group, tol=1e-9))) and (in_algebra or fixed)


@pytest.mark.parametrize("case", KINETIC, ids=kinetic_id)
def test_kinetic_constrained_drift_declaration_is_true(case):
    """'exact': the model's own flow keeps the subgroups (phi in G, Sigma_hat in g); the other
    declarations are needed: the own flow leaves the rotations."""
    kind, name, cls = case
    n = 2
    rng = np.random.default_rng(30)
    term = kinetic_sample(cls, n, rng)
    exact = cls.constrained_drift == "exact"
    for group in ("SL", "SO") if exact else ("SO",):
        start = group_probe(rng, n, group)
        assert stays_on(group, start, term.flow(start, 0.37)) == exact, group


# --------------------------------------------------------------------------------------------
# Potential families of the config registry

POTENTIAL_BODIES = 4


def test_every_registered_family_has_an_example():
    assert set(POTENTIALS) == set(POTENTIAL_EXAMPLES)
    periodic = build_potential(
        "lennard-jones", POTENTIAL_EXAMPLES["lennard-jones"](2), n=2, box=[4.0, 4.0]
    )
    assert periodic == LennardJones(0.7, 0.6, cutoff=Cutoff(1.9, 1.5), box=(4.0, 4.0))


@pytest.mark.parametrize("name", POTENTIALS)
def test_potential_family_builds_and_has_gradient_symmetry_and_static_pytree(name):
    """The family builds from its documented parameters (the example), and its term has a
    finite nonzero energy, autodiff forces, its declared symmetries and a static pytree."""
    n, family, params = 2, POTENTIALS[name], POTENTIAL_EXAMPLES[name](2)
    assert set(family.required) <= set(params) <= set(family.parameters)
    pot = build_potential(name, params, n=n, field="potential.0")
    assert family.kind == ("pair" if isinstance(pot, PairTerm) else "one-body")
    rng = np.random.default_rng(70)
    x, phi = configuration(rng, POTENTIAL_BODIES, n)
    # a static pytree: no leaves, a hashable treedef that rebuilds an equal term
    leaves, treedef = jax.tree.flatten(pot)
    assert leaves == [] and hash(treedef) == hash(jax.tree.structure(pot))
    assert jax.tree.unflatten(treedef, []) == pot
    # autodiff gradient = central differences along three random directions
    fx, fphi = generalized_forces(pot, x, phi)
    h = 1e-5
    dx, dphi = rng.normal(size=(3, *x.shape)), rng.normal(size=(3, *phi.shape))
    e = np.asarray(pot.energy(jnp.concatenate([x + h * dx, x - h * dx]),
                              jnp.concatenate([phi + h * dphi, phi - h * dphi])))
    numeric = (e[:3] - e[3:]) / (2 * h)
    autodiff = -(np.einsum("kd,ekd->e", fx, dx) + np.einsum("kab,ekab->e", fphi, dphi))
    scale = max(1.0, float(np.max(np.abs(autodiff))))
    np.testing.assert_allclose(autodiff, numeric, atol=1e-7 * scale, rtol=1e-7)
    assert np.max(np.abs(autodiff)) > 1e-3
    # the declared symmetries hold; the undeclared ones do not
    labels = ("translation", "spatial-euclidean", "spatial-affine", "material-euclidean",
              "material-affine")
    moved = [transform(label, rng, x, phi) for label in labels]
    e0, *e1 = np.asarray(pot.energy(jnp.stack([x] + [m[0] for m in moved]),
                                    jnp.stack([phi] + [m[1] for m in moved])))
    assert np.isfinite(e0) and e0 != 0.0
    for label, energy in zip(labels, e1, strict=True):
        change = abs(energy - e0) / (1.0 + abs(e0))
        assert (change < 1e-9) if label in pot.symmetry else (change > 1e-7), (label, change)
