"""Thermostats: Langevin (an exact Ornstein-Uhlenbeck step) and stochastic velocity rescaling
(Bussi, Donadio, Parrinello 2007) for every kinetic model and configuration group;
docs/thermostats.md explains the choices.

Momentum coordinates with constant coefficients. At fixed configuration every kinetic model is
a quadratic form in the momenta whose coefficients depend on phi; in the coordinates z of
``thermal_coordinates`` (declared by each kinetic term, ``kinetic.AbstractKineticTerm``) they
are constant, T(phi, momentum) = T(Id, z):

- ``"canonical"``: z = p or z = pi (d'Alembert (6), (52), (76a), (77a));
- ``"material"``: z = p_hat = phi^T p (43) (the af-is translational energy (64), (78a));
- ``"left"``: z = Sigma_hat = pi phi (45) (af-is, af-J, l-af: H depends on Sigma_hat only);
- ``"right"``: z = Sigma = phi pi (45) (is-af, H-af, r-af).

The map momentum -> z is linear at fixed phi, so the Gaussian exp(-T / kT) in the momenta is
the Gaussian N(0, kT M0) in z, with M0 the inverse of the (constant) Hessian of T(Id, z). The
Langevin step O(h) is the exact solution of dz = -gamma z dt + sqrt(2 gamma kT) M0^(1/2) dW:

    z' = c z + sqrt((1 - c^2) kT) M0^(1/2) xi,   c = exp(-gamma h),   xi ~ N(0, Id),

(M0^(1/2): any F with F F^T = M0; here F = L^-T, L the Cholesky factor of M0^-1), mapped
back to the momenta and projected with ``HamiltonianSystem.constrain`` (the Frobenius
projection that keeps the covector class on SL, UL, SO, O, R+SO, R+O, the kinetic-metric
projection onto admissible momenta under a rotationless constraint): the restriction of the
Gaussian covector to the constrained velocities is the Gaussian of the restricted metric, so
the noise stays in the constrained momentum space with the right law.

The Bussi step rescales every momentum by alpha = sqrt(K'/K), K the kinetic energy and K' drawn
from the exact solution of dK = (K_bar - K) dt/tau + 2 sqrt(K K_bar / N_f) dW/sqrt(tau),
K_bar = N_f kT / 2 (Bussi, Donadio, Parrinello 2007, eq. (A7)); T is quadratic in the momenta,
also on the subgroups, so it scales by alpha^2.

Both keep the canonical density exp(-H/kT) dx dphi dp dpi (Liouville measure), whose marginal
in phi is exp(-V/kT) times sqrt(det) of the kinetic metric: Lebesgue for d'Alembert, Haar
|det phi|^-n (91) for the spatially or materially affine models. af-af (72) is indefinite and
has no canonical ensemble: refused.

Random numbers: the step with global index k (k = 1, 2, ...) draws from
``fold_in(PRNGKey(seed), k)``, so a resumed run repeats the noise of an uninterrupted one.
The heat, the kinetic energy the thermostat put in, is accumulated; H - heat is the
"effective energy", conserved by the thermostatted dynamics up to the integrator's error.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from affinebody import _linalg as linalg
from affinebody._checks import transpose
from affinebody.constraints import CONSTRAINED_GROUPS, algebra_basis
from affinebody.nonholonomic import constraint_count
from affinebody.state import State

#: Thermostat kinds by config name (``[thermostat] kind``).
THERMOSTAT_KINDS = ("langevin", "bussi")

#: Where the O step goes in a step (``[thermostat] splitting``, the first is the default):
#: "obabo", after the whole step, K D K O(h) (OBABO with its adjacent half O steps merged);
#: "baoab", in the middle of the middle drift, K D(h/2) O(h) D(h/2) K
#: (``integrators.Thermostatted``, docs/thermostats.md).
SPLITTINGS = ("obabo", "baoab")


@dataclasses.dataclass(frozen=True)
class Langevin:
    """Langevin thermostat: the exact Ornstein-Uhlenbeck step (module docstring).

    temperature: kT (k_B = 1); friction: gamma, 1/time; seed: the random stream;
    splitting: one of :data:`SPLITTINGS`."""

    temperature: float
    friction: float
    seed: int = 0
    splitting: str = SPLITTINGS[0]
    kind = "langevin"

    def __post_init__(self):
        _check_positive("thermostat.temperature", self.temperature)
        _check_positive("thermostat.friction", self.friction)
        _check_splitting(self.splitting)


@dataclasses.dataclass(frozen=True)
class Bussi:
    """Stochastic velocity rescaling (Bussi, Donadio, Parrinello 2007).

    temperature: kT (k_B = 1); tau: the relaxation time of the kinetic energy; seed;
    splitting: one of :data:`SPLITTINGS`."""

    temperature: float
    tau: float
    seed: int = 0
    splitting: str = SPLITTINGS[0]
    kind = "bussi"

    def __post_init__(self):
        _check_positive("thermostat.temperature", self.temperature)
        _check_positive("thermostat.tau", self.tau)
        _check_splitting(self.splitting)


def _check_positive(name: str, value) -> None:
    if isinstance(value, jax.core.Tracer):  # traced in an ensemble (sweep samples)
        return
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0 (got {value!r})")


def _check_splitting(value) -> None:
    if value not in SPLITTINGS:
        raise ValueError(f"thermostat.splitting must be one of {', '.join(SPLITTINGS)} "
                         f"(got {value!r})")


class ThermostatCarry(NamedTuple):
    """What a thermostatted step carries besides the state: the forces (first same as last),
    the index of the last step done, the accumulated heat, and the factors M0^(1/2) of the
    translational and internal momentum coordinates ([N, n, n] and [N, n^2, n^2])."""

    forces: tuple
    step: jax.Array
    heat: jax.Array
    factors: tuple


# ------------------------------------------------------------------ momentum coordinates
def to_coordinates(term, phi, momentum):
    """z of ``term.thermal_coordinates`` from p [..., n] or pi [..., n, n] at fixed phi."""
    frame = term.thermal_coordinates
    if frame == "canonical":
        return momentum
    if frame == "material":
        return jnp.einsum("...ia,...i->...a", phi, momentum)
    if frame == "left":
        return momentum @ phi
    return phi @ momentum  # "right"


def from_coordinates(term, phi, z):
    """The momentum whose coordinates (:func:`to_coordinates`) are z."""
    frame = term.thermal_coordinates
    if frame == "canonical":
        return z
    if frame == "material":
        return linalg.solve(transpose(phi), z[..., None])[..., 0]
    if frame == "left":
        return transpose(linalg.solve(transpose(phi), transpose(z)))
    return linalg.solve(phi, z)  # "right"


def coordinate_hessian(term, bodies: int, shape: tuple[int, ...]) -> jax.Array:
    """The constant Hessian K of T(Id, z) in the flattened z, [bodies, d, d] (d = prod(shape)):
    T is quadratic, so column k is the gradient at the unit vector e_k. The d columns are
    taken one after the other (``lax.map``): differentiated all at once, as a [d, bodies, d]
    batch, the gradient's intermediates needed 2-5 kB per body (3D), which a thermostatted
    run's compiled loop kept on top of its own (1.4-2.2x the memory of an NVE run)."""
    d = math.prod(shape)
    n = shape[0]
    eye = jnp.eye(n)
    gradient = jax.grad(lambda z: jnp.sum(term.hamiltonian(eye, z)))

    def column(unit):
        return gradient(jnp.broadcast_to(unit.reshape(shape), (bodies,) + shape)).reshape(
            bodies, d)

    columns = jax.lax.map(column, jnp.eye(d))  # [d (col), bodies, d (row)]
    return jnp.moveaxis(columns, 0, -1)  # [bodies, d (row), d (col)]


def noise_factor(term, bodies: int, shape: tuple[int, ...]) -> jax.Array:
    """F with F F^T = K^-1 = M0 (the covariance of z per unit kT), [bodies, d, d]; NaN where K
    is not positive definite (the caller refuses such models first)."""
    k = coordinate_hessian(term, bodies, shape)
    return linalg.inverse_cholesky_factor(0.5 * (k + transpose(k)))  # F = L^-T, no LAPACK


def check_positive_kinetic(system, n: int) -> None:
    """ValueError (one line) unless every kinetic term is positive definite: af-af (72) is
    indefinite and has no canonical ensemble."""
    kinetic = system.kinetic
    for term, shape in ((kinetic.translational, (n,)), (kinetic.internal, (n, n))):
        k = coordinate_hessian(term, 1, shape)[0]
        if not bool(jnp.all(jnp.linalg.eigvalsh(0.5 * (k + k.T)) > 0)):
            raise ValueError(
                f"thermostat: the kinetic energy {type(term).__name__} is not positive definite "
                f"(af-af (72) is indefinite), so there is no canonical ensemble: use a positive "
                f"definite model (dalembert, af-is, is-af, af-J, H-af, l-af, r-af)")


# ------------------------------------------------------------------ degrees of freedom
def internal_degrees_of_freedom(system, n: int) -> int:
    """d: internal momentum degrees of freedom per body: n^2 on GL+, GL, L; dim g on a
    subgroup; n^2 minus the constraint count under a rotationless constraint."""
    if system.rotationless is not None:
        return n * n - constraint_count(n, system.group)
    if system.group in CONSTRAINED_GROUPS:
        return int(algebra_basis(system.group, n).shape[0])
    return n * n


def degrees_of_freedom(system, n: int, bodies: int) -> int:
    """N_f = N (n + d), all momentum degrees of freedom (total momentum not removed)."""
    return bodies * (n + internal_degrees_of_freedom(system, n))


def translational_kinetic_energy(system, state: State) -> jax.Array:
    """T_tr, the translational kinetic energy summed over bodies."""
    return jnp.sum(system.kinetic.translational.hamiltonian(state.phi, state.p), axis=-1)


def translational_temperature(system, state: State) -> jax.Array:
    """2 T_tr / (N n): kT at equipartition of the translational energy."""
    return 2.0 * translational_kinetic_energy(system, state) / (state.bodies * state.n)


def internal_temperature(system, state: State) -> jax.Array:
    """2 T_int / (N d), T_int = T - T_tr (the restricted energy on a subgroup), d as in
    :func:`internal_degrees_of_freedom`."""
    t_int = system.kinetic_energy(state) - translational_kinetic_energy(system, state)
    return 2.0 * t_int / (state.bodies * internal_degrees_of_freedom(system, state.n))


# ------------------------------------------------------------------ the steps
def factors(system, state: State) -> tuple[jax.Array, jax.Array]:
    """(F_tr [N, n, n], F_int [N, n^2, n^2]) of :func:`noise_factor` for the system's terms.

    No LAPACK kernel: the factors were two batched eigendecompositions, which XLA ran at once
    and which then deadlocked its CPU pool of two threads (README, "Notes and known limits";
    an NPT run of 97 336 bodies from Python hung in its first call; an optimisation barrier
    between them in the jaxpr was gone from the compiled program)."""
    n, bodies = state.n, state.bodies
    kinetic = system.kinetic
    return (noise_factor(kinetic.translational, bodies, (n,)),
            noise_factor(kinetic.internal, bodies, (n, n)))


def ornstein_uhlenbeck(system, thermostat, state: State, h, key, noise_factors,
                       damping=None) -> State:
    """O(h): the exact Ornstein-Uhlenbeck step of the momenta at fixed x, phi (module
    docstring), then the constraint projection. ``damping`` overrides c = exp(-gamma h)
    (c = 0 draws fresh momenta from the Maxwell distribution of the momentum coordinates)."""
    return _ornstein_uhlenbeck(system, thermostat, state, h, key, noise_factors, damping)[0]


def _ornstein_uhlenbeck(system, thermostat, state: State, h, key, noise_factors, damping=None):
    """:func:`ornstein_uhlenbeck` and the kinetic energy it put in."""
    c = jnp.exp(-thermostat.friction * h) if damping is None else jnp.asarray(damping)
    scale = jnp.sqrt((1.0 - c * c) * thermostat.temperature)
    kinetic = system.kinetic
    f_tr, f_int = noise_factors
    z = to_coordinates(kinetic.translational, state.phi, state.p)
    w = to_coordinates(kinetic.internal, state.phi, state.pi)
    flat = w.reshape(w.shape[:-2] + (-1,))
    # one draw for both parts: [..., n] for z, [..., n^2] for the internal coordinates
    xi = jax.random.normal(key, z.shape[:-1] + (z.shape[-1] + flat.shape[-1],), z.dtype)
    z = c * z + scale * jnp.einsum("...ij,...j->...i", f_tr, xi[..., :z.shape[-1]])
    p = from_coordinates(kinetic.translational, state.phi, z)
    flat = c * flat + scale * jnp.einsum("...ij,...j->...i", f_int, xi[..., z.shape[-1]:])
    pi = from_coordinates(kinetic.internal, state.phi, flat.reshape(w.shape))
    new = system.constrain(state._replace(p=p, pi=pi))
    if system.constrained or system.nonholonomic:
        return new, system.kinetic_energy(new) - system.kinetic_energy(state)
    # on GL+, GL, L: T = T(Id, z), the constant-coefficient form (no inverse of phi)
    eye = jnp.eye(state.n, dtype=z.dtype)
    energy = (kinetic.translational.hamiltonian(eye, z) - kinetic.translational.hamiltonian(
        eye, to_coordinates(kinetic.translational, state.phi, state.p))
        + kinetic.internal.hamiltonian(eye, flat.reshape(w.shape))
        - kinetic.internal.hamiltonian(eye, w))
    return new, jnp.sum(energy, axis=-1)


def bussi_kinetic_energy(kinetic_energy, thermostat: Bussi, dof: int, h, key) -> jax.Array:
    """K' of the stochastic velocity rescaling after time h from K (Bussi et al. 2007, (A7)):
    K' = c K + (1 - c) K_bar (R1^2 + S)/N_f + 2 R1 sqrt(c (1 - c) K K_bar / N_f),
    c = exp(-h/tau), K_bar = N_f kT/2, R1 ~ N(0, 1), S ~ chi^2 with N_f - 1 degrees, drawn
    as 2 Gamma((N_f - 1)/2) (one draw, whatever N_f)."""
    c = jnp.exp(-h / thermostat.tau)
    target = 0.5 * dof * thermostat.temperature
    key_r, key_s = jax.random.split(key)
    r1 = jax.random.normal(key_r, (), kinetic_energy.dtype)
    s = (2.0 * jax.random.gamma(key_s, 0.5 * (dof - 1), (), kinetic_energy.dtype) if dof > 1
         else jnp.zeros((), kinetic_energy.dtype))
    return (c * kinetic_energy + (1.0 - c) * target * (r1 * r1 + s) / dof
            + 2.0 * r1 * jnp.sqrt(c * (1.0 - c) * kinetic_energy * target / dof))


def velocity_rescaling(system, thermostat: Bussi, state: State, h, key,
                       noise_factors) -> tuple[State, jax.Array]:
    """The Bussi step: every momentum times sqrt(K'/K) (:func:`bussi_kinetic_energy`);
    returns the new state and K' - K. From rest (K = 0) there is no direction to scale: the
    momenta are first drawn from the Maxwell distribution, then scaled to K'."""
    k = system.kinetic_energy(state)
    dof = degrees_of_freedom(system, state.n, state.bodies)
    key_k, key_direction = jax.random.split(key)
    k_new = bussi_kinetic_energy(k, thermostat, dof, h, key_k)
    at_rest = k <= 0.0
    state = jax.lax.cond(at_rest, lambda s: ornstein_uhlenbeck(
        system, thermostat, s, h, key_direction, noise_factors, damping=0.0), lambda s: s, state)
    scaled = jax.lax.cond(at_rest, lambda s: system.kinetic_energy(s), lambda s: k, state)
    alpha = jnp.sqrt(k_new / jnp.maximum(scaled, jnp.finfo(k.dtype).tiny))
    return state._replace(p=alpha * state.p, pi=alpha * state.pi), k_new - k


def thermostat_step(system, thermostat, state: State, h, key,
                    noise_factors) -> tuple[State, jax.Array]:
    """O(h) of ``thermostat`` (Langevin or Bussi) at fixed configuration: the new state and
    the kinetic energy it put in (the heat of this step)."""
    if thermostat.kind == "langevin":
        return _ornstein_uhlenbeck(system, thermostat, state, h, key, noise_factors)
    return velocity_rescaling(system, thermostat, state, h, key, noise_factors)


def step_key(thermostat, step) -> jax.Array:
    """The key of the step with global index ``step``: fold_in(PRNGKey(seed), step)."""
    return jax.random.fold_in(jax.random.PRNGKey(thermostat.seed), step)


def check(system, thermostat, n: int) -> None:
    """One-line ValueErrors before any compilation: positive definite kinetic energy."""
    if thermostat.kind not in THERMOSTAT_KINDS:
        raise ValueError(f"thermostat.kind must be one of {', '.join(THERMOSTAT_KINDS)}")
    check_positive_kinetic(system, n)


__all__ = [
    "SPLITTINGS", "THERMOSTAT_KINDS", "Bussi", "Langevin", "ThermostatCarry",
    "bussi_kinetic_energy", "check", "check_positive_kinetic", "coordinate_hessian",
    "degrees_of_freedom", "factors",
    "from_coordinates", "internal_degrees_of_freedom", "internal_temperature", "noise_factor",
    "ornstein_uhlenbeck", "step_key", "thermostat_step", "to_coordinates",
    "translational_kinetic_energy", "translational_temperature", "velocity_rescaling",
]
