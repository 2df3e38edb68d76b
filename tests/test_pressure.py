"""The pressure tensor: its virial is -dV/d(eps) of a finite strain of the centres and the box
at fixed phi (central differences of the potential energy), orthorhombic and triclinic boxes,
n = 2 and 3, a pair potential of r, of the affine distance D (75) and of K1; the same over a
neighbour list; its kinetic part is -dT/d(eps) of the momenta's dual strain."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from affinebody import neighbors as nb
from affinebody import pressure
from affinebody.kinetic import AffineIsotropic, AffineTranslational, KineticEnergy
from affinebody.potentials import Cutoff, Dilatation, PairPotential, total_potential
from affinebody.space import triclinic
from affinebody.state import State
from affinebody.system import HamiltonianSystem

CELLS = {
    (2, "orthorhombic"): [[4.2, 0.0], [0.0, 3.9]],
    (2, "triclinic"): [[4.2, 1.1], [0.0, 3.9]],
    (3, "orthorhombic"): [[4.2, 0.0, 0.0], [0.0, 3.9, 0.0], [0.0, 0.0, 4.4]],
    (3, "triclinic"): [[4.2, 0.9, -0.6], [0.0, 3.9, 0.7], [0.0, 0.0, 4.4]],
}
R_CUT = 1.6
BODIES = 12


def pair_function(r, D, K1):
    """Depends on u through r and D, and on the shapes through K1 and D."""
    return jnp.exp(-D * D) * (1.0 + 0.3 * K1) + 0.5 / r**2


def setup(n, kind, seed=0):
    rng = np.random.default_rng(seed)
    space = triclinic(CELLS[(n, kind)])
    while True:  # spread over neighbouring images (wrapping is exercised), no pair too close
        s = rng.uniform(-0.5, 1.5, size=(BODIES, n))
        x = s @ space.matrix.T
        d = np.asarray(space.distance(jnp.asarray(x)[:, None], jnp.asarray(x)[None]))
        if np.min(d + 10 * np.eye(BODIES)) > 0.6:
            break
    phi = np.eye(n) + 0.2 * rng.normal(size=(BODIES, n, n))
    phi[np.linalg.det(phi) < 0, 0] *= -1
    pair = PairPotential(pair_function, ("r", "D", "K1"), Cutoff(R_CUT, 1.1), space)
    potential = total_potential([pair, Dilatation(0.7)])
    kinetic = KineticEnergy(AffineTranslational(1.3), AffineIsotropic(0.8))
    system = HamiltonianSystem(kinetic, potential)
    p = rng.normal(size=(BODIES, n))
    pi = rng.normal(size=(BODIES, n, n))
    state = State(*(jnp.asarray(a) for a in (x, phi, p, pi)))
    return system, state, space, pair


virial = jax.jit(pressure.virial, static_argnums=(2,))


@jax.jit
def energy(potential, x, phi):
    return potential.energy(x, phi)


@jax.jit
def strained_energy(system, state, cell, eps):
    """V of x -> F x, H -> F H, phi fixed, F = (Id + eps)^T (the box a traced cell)."""
    f = jnp.eye(eps.shape[0]) + eps.T
    return system.replace(cell=f @ cell).potential_energy(state._replace(x=state.x @ f.T))


@pytest.mark.parametrize("n, kind", [(2, "orthorhombic"), (3, "triclinic")])
def test_virial_is_minus_the_strain_derivative_of_the_potential_energy(n, kind):
    system, state, space, pair = setup(n, kind)
    w = np.asarray(virial(system, state, space))
    assert np.max(np.abs(w)) > 0.1  # pairs in range: a non-trivial virial
    cell = jnp.asarray(space.matrix)
    # the strained box as a traced cell is the box F H itself (static, a new potential)
    rng = np.random.default_rng(1)
    eps = 0.03 * rng.normal(size=(n, n))
    f = np.eye(n) + eps.T
    terms = [dataclasses.replace(t, box=triclinic(f @ space.matrix)) if t is pair else t
             for t in system.potential.terms]
    direct = energy(total_potential(terms), state.x @ f.T, state.phi)
    np.testing.assert_allclose(float(strained_energy(system, state, cell, jnp.asarray(eps))),
                               float(direct), rtol=1e-13)
    h = 1e-5
    fd = np.zeros((n, n))
    for a in range(n):
        for b in range(n):
            e = np.zeros((n, n))
            e[a, b] = h
            fd[a, b] = -(float(strained_energy(system, state, cell, jnp.asarray(e)))
                         - float(strained_energy(system, state, cell, jnp.asarray(-e)))) / (2 * h)
    np.testing.assert_allclose(w, fd, rtol=1e-7, atol=1e-7 * np.max(np.abs(fd)))
    # the D-dependence makes the virial non-symmetric (phi is held fixed under the strain)
    assert np.max(np.abs(w - w.T)) > 1e-3
    # over a neighbour list (as a neighbour-list run), and with the box as a traced cell
    _, lst = nb.allocate(space, state.x, state.phi, R_CUT, "r", 0.1)
    scale = 1e-12 * np.max(np.abs(w))
    np.testing.assert_allclose(np.asarray(virial(system, state, space, lst)), w,
                               rtol=1e-12, atol=scale)
    np.testing.assert_allclose(np.asarray(virial(system.replace(cell=cell), state, space)), w,
                               rtol=1e-12, atol=scale)


def test_kinetic_part_is_minus_the_strain_derivative_of_the_kinetic_energy():
    """-dT/d(eps) for p -> (Id + eps)^-1 p (phi fixed), af-is translational model whose
    velocity phi phi^T p / M depends on the shape: sum_K v_K p_K^T."""
    system, state, _, _ = setup(2, "triclinic")
    k = np.asarray(pressure.kinetic_tensor(system, state))

    @jax.jit
    def strained(eps):
        p = jnp.einsum("ab,kb->ka", jnp.linalg.inv(jnp.eye(2) + eps), state.p)
        return system.kinetic_energy(state._replace(p=p))

    energy = lambda eps: float(strained(jnp.asarray(eps)))  # noqa: E731

    h = 1e-5
    fd = np.array([[-(energy(h * np.eye(2)[a][:, None] * np.eye(2)[b][None])
                      - energy(-h * np.eye(2)[a][:, None] * np.eye(2)[b][None])) / (2 * h)
                    for b in range(2)] for a in range(2)])
    np.testing.assert_allclose(k, fd, rtol=1e-7)
    velocity = jnp.einsum("kab,kcb,kc->ka", state.phi, state.phi, state.p) / 1.3
    np.testing.assert_allclose(k, np.einsum("ka,kb->ab", velocity, state.p), rtol=1e-12)


def test_pressure_refuses_free_space_and_a_foreign_box():
    system, state, space, pair = setup(2, "orthorhombic")
    with pytest.raises(ValueError, match="periodic box"):
        pressure.pressure_tensor(system, state, None)
    with pytest.raises(ValueError, match="not in the box"):
        pressure.virial(system, state, triclinic([[5.0, 0.0], [0.0, 5.0]]))
    assert float(pressure.scalar_pressure(jnp.diag(jnp.asarray([1.0, 2.0])))) == 1.5


def test_the_virial_pass_also_gives_the_potential_energy():
    """pair_virial(..., energy=True): the energy of the same pass over the pairs is the pair
    energy (what the barostat books its work with). The JAX kernel here (a GPU's); the host
    kernel's is exercised by the NPT effective-energy test (tests/test_barostat.py)."""
    from affinebody import pair_kernels

    _, state, space, pair = setup(2, "triclinic")
    i, j = (jnp.asarray(a, dtype=jnp.int32) for a in np.triu_indices(BODIES, 1))
    e, _ = pair_kernels.pair_virial(pair, space, state.x, state.phi, i, j, i.shape[0],
                                    chunk=7, energy=True)
    np.testing.assert_allclose(float(e), float(pair.energy(state.x, state.phi)), rtol=1e-12)


@pytest.mark.parametrize("kernel", ["host", "jax"])
@pytest.mark.parametrize("form", ["python", "expression"])
def test_forces_and_virial_from_one_pass_equal_those_of_their_own_passes(monkeypatch, kernel,
                                                                         form):
    """pressure.energy_forces_virial (what an NPT step's last force evaluation computes, so
    that the barostat's move needs no pass of its own) gives the energy and forces of
    system.energy_and_forces and the virial of pressure.virial, over a list in a traced cell,
    with the host kernel (a Python f: two callbacks; a config expression: the fused kernel)
    and the JAX one; and a barostat move fed these (V, W) is the move that measures them."""
    from affinebody import pair_kernels
    from affinebody.barostat import StochasticCellRescaling

    if kernel == "jax":
        monkeypatch.setattr(pair_kernels, "host_kernel_in_use", lambda: False)
    system, state, space, pair = setup(3, "triclinic", seed=4)
    if form == "expression":
        pair = PairPotential.from_expression("exp(-D**2)*(1 + 0.3*K1) + 0.5/r**2", 3,
                                             cutoff=Cutoff(R_CUT, 1.1), box=space)
        system = system.replace(potential=total_potential([pair, Dilatation(0.7)]))
    cell = jnp.asarray(space.matrix) * 1.02  # a barostat's box, as a traced cell
    boxed = system.replace(cell=cell)
    _, lst = nb.allocate(space, state.x, state.phi, R_CUT, "r", 0.1, cell=cell)

    @jax.jit
    def both(boxed, state, lst):
        return (pressure.energy_forces_virial(boxed, state, space, lst),
                boxed.energy_and_forces(state, lst), pressure.virial(boxed, state, space, lst))

    (e, (gx, gphi), w), (e_ref, (gx_ref, gphi_ref)), w_ref = both(boxed, state, lst)
    assert np.max(np.abs(np.asarray(w_ref))) > 0.1 and np.max(np.abs(gx_ref)) > 0.1
    np.testing.assert_allclose(float(e), float(e_ref), rtol=1e-13)
    for a, b in ((gx, gx_ref), (gphi, gphi_ref), (w, w_ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0,
                                   atol=1e-12 * np.max(np.abs(np.asarray(b))))
    barostat = StochasticCellRescaling(tuple(map(tuple, 0.3 * np.eye(3))), tau=1.0,
                                       compressibility=0.5,
                                       temperature=0.2)
    key = jax.random.key(5)
    fed = barostat.propose(boxed, state, cell, space, key, 0.01, lst, measured=(e, w))
    own = barostat.propose(boxed, state, cell, space, key, 0.01, lst)
    for a, b in zip(jax.tree.leaves(fed), jax.tree.leaves(own), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-13)
    assert float(jnp.linalg.det(fed[1])) != float(jnp.linalg.det(cell))  # the box moved
