"""Kinetic energies of affine bodies: every model of the paper, its Legendre map and drift flow.

Each model is a small frozen dataclass (a JAX pytree) for the kinetic energy of *one* body,
evaluated for all bodies at once. Parameters are scalars (identical bodies) or arrays with a
leading body axis N (each body its own M, J, ...), broadcasting against the body axis of the
state ``[..., N, n]`` / ``[..., N, n, n]``. Every model offers

- ``lagrangian(phi, vel)``       kinetic energy T per body ``[..., N]``,
- ``hamiltonian(phi, mom)``      its Legendre transform (the kinetic Hamiltonian) per body,
- ``legendre(phi, vel)``         momentum p = dT/dv, or pi = (dT/dxi)^T (pi[a, i] = pi^a_i, (50)),
- ``inverse_legendre(phi, mom)`` velocity from momentum,
- ``flow(state, h)``             the drift: the flow of this Hamiltonian (summed over bodies)
                                  for time h, exact where ``exact_flow`` is True, otherwise an
                                  explicit symplectic palindromic splitting (2nd order),
- ``check(n=None)``              ValueError with the fix when the model is degenerate,
- ``symmetry``                   the invariance groups, as strings (see ``SYMMETRIES``),

and declares ``parameters``, ``exact_flow``, ``constrained_drift``, ``invariance_side`` and
``flow_moves_only_x`` (``AbstractKineticTerm``). ``MODELS`` and ``TRANSLATIONAL_MODELS`` are the
registries (config name -> class).

Conventions (docs/theory/conventions.md): ``xi = dphi/dt``; Omega = xi phi^-1,
Omega_hat = phi^-1 xi (34); Sigma = phi pi, Sigma_hat = pi phi (45);
Tr(Sigma Omega) = Tr(Sigma_hat Omega_hat) (46).
Hamilton's equations: dphi/dt = (dH/dpi)^T, dpi/dt = -(dH/dphi)^T.

Models (labels of the paper):

==========================  ============================  =====================================
class                       T (velocities)                T (momenta)
==========================  ============================  =====================================
DAlembertTranslational      (6), (63) [is-af]             (52), (77a)
AffineTranslational         (64) [af-is]                  (78a)
DAlembert                   (6), (6a), (10)               (52), (76a)
AffineJ                     (65); (66) for J = I Id        (79a); (80a)
HAffine                     (67), (68)                    (81a)
LeftInvariant               (70) [l-af]                   (82a)
RightInvariant              (71) [r-af]                   (83a)
AffineAffine                (72) [af-af]                  (84a)/(85) with I = 0
IsotropicAffine             (73) [is-af]                  (84a), constants (86)
AffineIsotropic             (74) [af-is]                  (85), constants (86)
==========================  ============================  =====================================

The kinetic energy of a system is the sum over bodies (10), (55): ``KineticEnergy``.

Drift flows. A left-invariant Hamiltonian h(Sigma_hat) with dh = Tr(W dSigma_hat) moves
phi' = phi W, pi' = -W pi; a right-invariant h(Sigma) with dh = Tr(W dSigma) moves
phi' = W phi, pi' = -pi W (W is the co-moving resp. spatial affine velocity). So
h = f(Tr(W Sigma_hat)) with constant W is a one-parameter subgroup:
phi -> phi expm(t f' W), pi -> expm(-t f' W) pi, and Tr(W Sigma_hat) is conserved.
Writing a quadratic h = 1/2 sum_k lam_k Tr(W_k Sigma_hat)^2 (W_k Frobenius-orthonormal
eigen-directions of the inverse inertia) and composing the rank-one flows palindromically
gives an explicit symplectic 2nd-order drift (McLachlan's Lie-Poisson splitting on gl(n)).
"""

from __future__ import annotations

import abc
import functools
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _host
from affinebody import _linalg as linalg
from affinebody import _pytree as pytree
from affinebody._checks import (
    as_float64,
    check_symmetric_positive_definite,
    eye_like,
    is_concrete,
    trace,
    transpose,
)
from affinebody.groups import expm
from affinebody.state import State, VelocityState

#: The invariance labels used by ``symmetry`` (shared with the potentials).
SYMMETRIES = frozenset(
    {"spatial-affine", "spatial-euclidean", "material-affine", "material-euclidean", "material-J"}
)


def _closed(labels: set[str]) -> frozenset[str]:
    """Close a set of symmetry labels under inclusion of groups.

    Affine invariance implies Euclidean invariance (O(n) < GL(n)); material affine invariance
    implies invariance under O(n, J) too. Closing the sets lets a caller intersect the labels of
    several terms (kinetic and potential) without knowing which groups contain which.
    """
    out = set(labels)
    if "spatial-affine" in out:
        out.add("spatial-euclidean")
    if "material-affine" in out:
        out |= {"material-euclidean", "material-J"}
    return frozenset(out)


def _is_spherical(a) -> bool:
    """True when the concrete matrix (batch) ``a`` is a multiple of the identity."""
    if not is_concrete(a):
        return False
    m = np.asarray(a, dtype=float)
    diag = np.einsum("...ii->...i", m)
    return bool(np.allclose(m, diag[..., :1, None] * np.eye(m.shape[-1]), rtol=1e-12, atol=0))


def _as_matrix_param(a, name: str) -> jax.Array:
    a = as_float64(a, name)
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise ValueError(f"{name} must have shape [n, n] or [N, n, n] (got {tuple(a.shape)})")
    return a


def _first_bad(ok: np.ndarray, **values) -> str:
    """'(got I=0.2, A=0.5)' for the first failing entry of a per-body parameter batch."""
    index = np.argwhere(~np.atleast_1d(ok))[0]
    items = []
    for name, value in values.items():
        v = np.broadcast_to(np.asarray(value, dtype=float), np.atleast_1d(ok).shape)
        items.append(f"{name}={float(v[tuple(index)]):.6g}")
    where = f" for body {int(index[0])}" if np.ndim(ok) else ""
    return f"(got {', '.join(items)}{where})"


def _bcast(c: jax.Array) -> jax.Array:
    """Per-body scalar [N] (or scalar) -> [N, 1, 1] to multiply matrices [..., N, n, n]."""
    return c[..., None, None]


def _frob(a: jax.Array, b: jax.Array) -> jax.Array:
    """Frobenius product Tr(a^T b) over the last two axes."""
    return jnp.sum(a * b, axis=(-2, -1))


# --------------------------------------------------------------------------------------------
# The interface of a kinetic term
# --------------------------------------------------------------------------------------------


class AbstractKineticTerm(abc.ABC):
    """The kinetic energy of one body, translational (acting on x, p) or internal (phi, pi).

    A model is a ``_pytree.dataclass`` whose fields are its inertial parameters (scalars or
    arrays with a leading body axis) and which declares, as class attributes, what the rest of
    the library needs to know about it (no caller decides by the model's type):

    - ``parameters``: the names of its fields, the parameters a config gives it;
    - ``exact_flow``: whether ``flow`` is the exact flow of ``hamiltonian``;
    - ``flow_moves_only_x``: whether ``flow`` moves the centre x only (then it commutes with
      every internal flow and the drift of ``KineticEnergy`` is their plain composition);
    - ``constrained_drift``: how it drifts on a constrained group (``affinebody.constraints``):
      ``"exact"`` (its own flow keeps the group: phi fixed, or g mapped into g), ``"lie-group"``
      (a left/right-invariant term restricted to G: rank-one splitting in g) or ``"rattle"``
      (d'Alembert's constant inertia);
    - ``thermal_coordinates``: the momentum coordinates z in which T has constant coefficients,
      T(phi, momentum) = T(Id, z) (``affinebody.thermostats``): ``"canonical"`` (z = p or pi),
      ``"material"`` (z = phi^T p), ``"left"`` (z = pi phi) or ``"right"`` (z = phi pi);
    - ``invariance_side``: ``"left"`` when T depends on xi through Omega_hat = phi^-1 xi (34)
      (spatially affine), ``"right"`` through Omega = xi phi^-1 (materially affine), else None;
    - ``symmetry``: its invariance groups, labels of ``SYMMETRIES`` closed under inclusion.

    The methods are per body: ``lagrangian``/``hamiltonian`` [..., N] and the Legendre map
    p = dT/dv (pi = (dT/dxi)^T, (50)) with its inverse, on the translational or the internal
    variables; ``flow(state, h)`` moves a whole ``State``; ``check(n)`` raises a one-line
    ValueError naming the parameter when the model is degenerate.
    """

    parameters: ClassVar[tuple[str, ...]]
    exact_flow: ClassVar[bool]
    flow_moves_only_x: ClassVar[bool] = False
    constrained_drift: ClassVar[str]
    invariance_side: ClassVar[str | None] = None
    thermal_coordinates: ClassVar[str] = "canonical"

    @property
    @abc.abstractmethod
    def symmetry(self) -> frozenset[str]:
        """The invariance groups (``SYMMETRIES`` labels, closed under inclusion)."""

    @abc.abstractmethod
    def lagrangian(self, q, velocity) -> jax.Array:
        """T per body [..., N] at configuration phi and velocity v (or xi)."""

    @abc.abstractmethod
    def hamiltonian(self, q, momentum) -> jax.Array:
        """The Legendre transform of T per body [..., N] at phi and momentum p (or pi)."""

    @abc.abstractmethod
    def legendre(self, q, velocity) -> jax.Array:
        """Momentum p = dT/dv, or pi = (dT/dxi)^T (50), from the velocity."""

    @abc.abstractmethod
    def inverse_legendre(self, q, momentum) -> jax.Array:
        """Velocity from momentum, the inverse of :meth:`legendre`."""

    @abc.abstractmethod
    def flow(self, state: State, h) -> State:
        """The drift: flow of this Hamiltonian (summed over bodies) for time h."""

    @abc.abstractmethod
    def check(self, n: int | None = None) -> None:
        """ValueError with the fix when the parameters are degenerate (in dimension n)."""


# --------------------------------------------------------------------------------------------
# Translational kinetic energies
# --------------------------------------------------------------------------------------------


@pytree.dataclass
class DAlembertTranslational(AbstractKineticTerm):
    """d'Alembert translational kinetic energy, also the is-af model (6), (63), (77a).

    T = M/2 v^T v = M/2 v_hat^T G[phi] v_hat,  p = M v,
    H = p^T p / (2M) = p_hat^T G[phi]^-1 p_hat / (2M),  p_hat = phi^T p (43).
    Drift (exact): x -> x + h p / M.
    """

    mass: Any

    parameters = ("mass",)
    exact_flow = True
    flow_moves_only_x = True
    constrained_drift = "exact"  # phi is fixed: the projected momentum change is exact
    symmetry = _closed({"spatial-euclidean", "material-affine"})

    def _m(self) -> jax.Array:
        return as_float64(self.mass, "kinetic.mass")

    def lagrangian(self, phi, v):
        return 0.5 * self._m() * jnp.sum(v * v, axis=-1)

    def hamiltonian(self, phi, p):
        return 0.5 * jnp.sum(p * p, axis=-1) / self._m()

    def legendre(self, phi, v):
        return self._m()[..., None] * v

    def inverse_legendre(self, phi, p):
        return p / self._m()[..., None]

    def flow(self, state: State, h) -> State:
        return state._replace(x=state.x + h * self.inverse_legendre(state.phi, state.p))

    def check(self, n: int | None = None) -> None:
        _check_mass(self.mass)


@pytree.dataclass
class AffineTranslational(AbstractKineticTerm):
    """Spatially affine, materially isotropic translational energy af-is (64), (78a).

    The Cauchy tensor C[phi] = phi^-T phi^-1 (11) is the metric of the physical space:
    T = M/2 v^T C[phi] v = M/2 |v_hat|^2, v_hat = phi^-1 v (38);  p = M C[phi] v;
    H = p^T C[phi]^-1 p / (2M) = |p_hat|^2 / (2M), p_hat = phi^T p (43).
    Drift (exact: phi and p stay constant): x -> x + h phi phi^T p / M,
    pi -> pi - h phi^T p p^T / M.
    """

    mass: Any

    parameters = ("mass",)
    exact_flow = True
    constrained_drift = "exact"  # phi is fixed: the projected momentum change is exact
    thermal_coordinates = "material"  # T = |phi^T p|^2 / (2M)
    symmetry = _closed({"spatial-affine", "material-euclidean"})

    def _m(self) -> jax.Array:
        return as_float64(self.mass, "kinetic.mass")

    def lagrangian(self, phi, v):
        v_hat = linalg.solve(phi, v[..., None])[..., 0]
        return 0.5 * self._m() * jnp.sum(v_hat * v_hat, axis=-1)

    def hamiltonian(self, phi, p):
        p_hat = jnp.einsum("...ia,...i->...a", phi, p)
        return 0.5 * jnp.sum(p_hat * p_hat, axis=-1) / self._m()

    def legendre(self, phi, v):
        inv = linalg.inv(phi)
        cauchy = transpose(inv) @ inv
        return self._m()[..., None] * jnp.einsum("...ij,...j->...i", cauchy, v)

    def inverse_legendre(self, phi, p):
        green_inv = phi @ transpose(phi)
        return jnp.einsum("...ij,...j->...i", green_inv, p) / self._m()[..., None]

    def flow(self, state: State, h) -> State:
        m = self._m()[..., None]
        p_hat = jnp.einsum("...ia,...i->...a", state.phi, state.p)
        x = state.x + h * jnp.einsum("...ia,...a->...i", state.phi, p_hat) / m
        pi = state.pi - h * (p_hat[..., :, None] * state.p[..., None, :]) / m[..., None]
        return state._replace(x=x, pi=pi)

    def check(self, n: int | None = None) -> None:
        _check_mass(self.mass)


def _check_mass(mass) -> None:
    m = as_float64(mass, "kinetic.mass")
    if is_concrete(m):
        ok = np.isfinite(np.asarray(m)) & (np.asarray(m) > 0)
        if not np.all(ok):
            raise ValueError(f"kinetic.mass must be > 0 {_first_bad(ok, mass=m)}")


# --------------------------------------------------------------------------------------------
# Internal kinetic energies: shared machinery
# --------------------------------------------------------------------------------------------


class _LeftInvariantModel(AbstractKineticTerm):
    """T depends on xi only through Omega_hat = phi^-1 xi; H only through Sigma_hat = pi phi.

    Subclasses give ``_energy_of_velocity(Omega_hat)``, ``_spin_of_velocity(Omega_hat)``
    (Sigma_hat = (dT/dOmega_hat)^T), ``_velocity_of_spin(Sigma_hat)`` (its inverse, = W with
    dH = Tr(W dSigma_hat)) and ``_energy_of_spin(Sigma_hat)``.
    """

    invariance_side = "left"
    thermal_coordinates = "left"

    def lagrangian(self, phi, xi):
        return self._energy_of_velocity(linalg.solve(phi, xi))

    def hamiltonian(self, phi, pi):
        return self._energy_of_spin(pi @ phi)

    def legendre(self, phi, xi):
        return self._spin_of_velocity(linalg.solve(phi, xi)) @ linalg.inv(phi)

    def inverse_legendre(self, phi, pi):
        return phi @ self._velocity_of_spin(pi @ phi)


class _RightInvariantModel(AbstractKineticTerm):
    """T depends on xi only through Omega = xi phi^-1; H only through Sigma = phi pi."""

    invariance_side = "right"
    thermal_coordinates = "right"

    def lagrangian(self, phi, xi):
        return self._energy_of_velocity(xi @ linalg.inv(phi))

    def hamiltonian(self, phi, pi):
        return self._energy_of_spin(phi @ pi)

    def legendre(self, phi, xi):
        return linalg.solve(phi, self._spin_of_velocity(xi @ linalg.inv(phi)))

    def inverse_legendre(self, phi, pi):
        return self._velocity_of_spin(phi @ pi) @ phi


def rank_one_splitting(state: State, directions, rates, h, side: str) -> State:
    """Palindromic composition of the exact flows of h_k = rates_k/2 * Tr(W_k S)^2.

    ``directions`` [..., m, n, n] are the W_k, ``rates`` [..., m] the lam_k; S = Sigma_hat
    (side 'left') or Sigma (side 'right'). Each flow is a one-parameter subgroup with the
    conserved c_k = Tr(W_k S): left phi -> phi expm(t lam c W), pi -> expm(-t lam c W) pi;
    right phi -> expm(t lam c W) phi, pi -> pi expm(-t lam c W). The symmetric sequence
    k = 0..m-2 (h/2), m-1 (h), m-2..0 (h/2) is a 2nd-order explicit symplectic integrator.
    """
    m = directions.shape[-3]
    order = jnp.array(list(range(m - 1)) + [m - 1] + list(reversed(range(m - 1))))
    fractions = jnp.array([0.5] * (m - 1) + [1.0] + [0.5] * (m - 1))

    def step(carry, kf):
        phi, pi = carry
        k, fraction = kf
        w = jnp.take(directions, k, axis=-3)
        spin = pi @ phi if side == "left" else phi @ pi
        c = trace(w @ spin)
        generator = _bcast(fraction * h * jnp.take(rates, k, axis=-1) * c) * w
        forward, backward = expm(generator), expm(-generator)
        if side == "left":
            return (phi @ forward, backward @ pi), None
        return (forward @ phi, pi @ backward), None

    (phi, pi), _ = jax.lax.scan(step, (state.phi, state.pi), (order, fractions))
    return state._replace(phi=phi, pi=pi)


def _principal_directions(metric: jax.Array):
    """Rank-one split of h(S) = 1/2 Tr(S^T metric^-1 S) for symmetric positive ``metric``.

    With metric = Q diag(d) Q^T: h = 1/2 sum_{k,i} (Q^T S)_{ki}^2 / d_k and
    (Q^T S)_{ki} = Tr(W_{ki} S), W_{ki} = e_i q_k^T (Frobenius-orthonormal).
    Returns W [..., n*n, n, n] and rates 1/d_k [..., n*n].
    """
    d, q = jnp.linalg.eigh(metric)
    n = metric.shape[-1]
    eye = jnp.eye(n, dtype=metric.dtype)
    # w[..., k, i, r, s] = delta_{ri} q_{sk}
    w = jnp.einsum("ri,...sk->...kirs", eye, q)
    w = w.reshape(w.shape[:-4] + (n * n, n, n))
    rates = jnp.repeat(1.0 / d, n, axis=-1)
    return w, rates


# --------------------------------------------------------------------------------------------
# Internal kinetic energies: the models
# --------------------------------------------------------------------------------------------


@pytree.dataclass
class DAlembert(AbstractKineticTerm):
    """d'Alembert internal kinetic energy with a general inertia J (6), (52), (76a).

    T = 1/2 Tr(xi J xi^T),  pi = J xi^T (51),  H = 1/2 Tr(pi^T J^-1 pi).
    J is the co-moving second moment of the mass distribution (8), symmetric positive definite.
    Drift (exact, linear): phi -> phi + h pi^T J^-1; pi constant. Unconfined, det phi is a
    polynomial in t and reaches 0 in finite time (phi may leave GL(n)).
    """

    J: Any

    parameters = ("J",)
    exact_flow = True
    constrained_drift = "rattle"  # its straight-line drift leaves every subgroup

    @property
    def symmetry(self) -> frozenset[str]:
        labels = {"spatial-euclidean", "material-J"}
        if _is_spherical(self.J):
            labels.add("material-euclidean")
        return _closed(labels)

    def _j(self):
        return _as_matrix_param(self.J, "kinetic.J")

    def lagrangian(self, phi, xi):
        return 0.5 * _frob(xi @ self._j(), xi)

    def hamiltonian(self, phi, pi):
        return 0.5 * _frob(pi, linalg.solve(self._j(), pi))

    def legendre(self, phi, xi):
        return self._j() @ transpose(xi)

    def inverse_legendre(self, phi, pi):
        return transpose(linalg.solve(self._j(), pi))

    def flow(self, state: State, h) -> State:
        return state._replace(phi=state.phi + h * self.inverse_legendre(state.phi, state.pi))

    def check(self, n: int | None = None) -> None:
        check_symmetric_positive_definite(self._j(), "kinetic.J")


@pytree.dataclass
class AffineJ(_LeftInvariantModel):
    """af-J: spatially affine internal energy with a material inertia J (65), (79a).

    T = 1/2 Tr(C[phi] xi J xi^T) = 1/2 Tr(Omega_hat J Omega_hat^T),
    Sigma_hat = J Omega_hat^T, H = 1/2 Tr(Sigma_hat^T J^-1 Sigma_hat) = 1/2 Tr(C^-1 pi^T J^-1 pi).
    J = I Id gives (66), (80a) (the same as ``AffineIsotropic(I, 0, 0)``).
    Drift: palindromic rank-one splitting in J's principal frame (``exact_flow`` False).
    Material symmetry: O(n, J) only when J is spherical (then O(n)); otherwise the subgroup
    the intersection of O(n, J) and O(n), which has no label (not all of O(n, J) as printed;
    see docs/theory/paper-typos.md).
    """

    J: Any

    parameters = ("J",)
    exact_flow = False
    constrained_drift = "lie-group"

    @property
    def symmetry(self) -> frozenset[str]:
        # phi -> phi B moves Omega_hat to B^-1 Omega_hat B: T is invariant when B J B^T = J
        # and B B^T = Id, i.e. on O(n, J) only for spherical J (docs/theory/paper-typos.md)
        labels = {"spatial-affine"}
        if _is_spherical(self.J):
            labels |= {"material-euclidean", "material-J"}
        return _closed(labels)

    def _j(self):
        return _as_matrix_param(self.J, "kinetic.J")

    def _energy_of_velocity(self, om):
        return 0.5 * _frob(om @ self._j(), om)

    def _spin_of_velocity(self, om):
        return self._j() @ transpose(om)

    def _velocity_of_spin(self, s):
        return transpose(linalg.solve(self._j(), s))

    def _energy_of_spin(self, s):
        return 0.5 * _frob(s, linalg.solve(self._j(), s))

    def flow(self, state: State, h) -> State:
        w, rates = _principal_directions(self._j())
        return rank_one_splitting(state, w, rates, h, "left")

    def check(self, n: int | None = None) -> None:
        check_symmetric_positive_definite(self._j(), "kinetic.J")


@pytree.dataclass
class HAffine(_RightInvariantModel):
    """H-af: materially affine energy with a constant spatial inertia H (67), (68), (81a).

    T = 1/2 Tr(Omega H Omega^T) = 1/2 Tr(xi H[phi] xi^T), H[phi] = phi^-1 H phi^-T (68);
    Sigma = H Omega^T, H = 1/2 Tr(Sigma^T H^-1 Sigma) = 1/2 Tr(pi^T H[phi]^-1 pi).
    Drift: palindromic rank-one splitting in H's principal frame (``exact_flow`` False).
    """

    H: Any

    parameters = ("H",)
    exact_flow = False
    constrained_drift = "lie-group"

    @property
    def symmetry(self) -> frozenset[str]:
        labels = {"material-affine"}
        if _is_spherical(self.H):
            labels.add("spatial-euclidean")
        return _closed(labels)

    def _h(self):
        return _as_matrix_param(self.H, "kinetic.H")

    def _energy_of_velocity(self, om):
        return 0.5 * _frob(om @ self._h(), om)

    def _spin_of_velocity(self, om):
        return self._h() @ transpose(om)

    def _velocity_of_spin(self, s):
        return transpose(linalg.solve(self._h(), s))

    def _energy_of_spin(self, s):
        return 0.5 * _frob(s, linalg.solve(self._h(), s))

    def flow(self, state: State, h) -> State:
        w, rates = _principal_directions(self._h())
        return rank_one_splitting(state, w, rates, h, "right")

    def check(self, n: int | None = None) -> None:
        check_symmetric_positive_definite(self._h(), "kinetic.H")


class _BiTensorModel:
    """Quadratic energy 1/2 L[A,B,C,D] X[A,B] X[C,D] with a constant symmetric bi-tensor L.

    ``L`` has shape [n, n, n, n] (or [N, n, n, n, n]); as an n^2 x n^2 matrix (row-major
    pairs (A, B)) it must be symmetric positive definite. The spin is S^T = dT/dX, i.e.
    vec(S^T) = L vec(X), and H = 1/2 vec(S^T)^T L^-1 vec(S^T) (the reciprocal bi-tensor).
    """

    _name = "L"

    def _matrix(self):
        t = as_float64(getattr(self, self._name), f"kinetic.{self._name}")
        n = t.shape[-1]
        if t.ndim < 4 or t.shape[-4:] != (n, n, n, n):
            raise ValueError(
                f"kinetic.{self._name} must have shape [n, n, n, n] or [N, n, n, n, n] "
                f"(got {tuple(t.shape)})"
            )
        return t.reshape(t.shape[:-4] + (n * n, n * n))

    def _energy_of_velocity(self, om):
        vec = om.reshape(om.shape[:-2] + (-1,))
        return 0.5 * jnp.einsum("...i,...ij,...j->...", vec, self._matrix(), vec)

    def _spin_of_velocity(self, om):
        vec = om.reshape(om.shape[:-2] + (-1,))
        return transpose(jnp.einsum("...ij,...j->...i", self._matrix(), vec).reshape(om.shape))

    def _velocity_of_spin(self, s):
        vec = transpose(s).reshape(s.shape[:-2] + (-1,))
        return linalg.solve(self._matrix(), vec[..., None])[..., 0].reshape(s.shape)

    def _energy_of_spin(self, s):
        vec = transpose(s).reshape(s.shape[:-2] + (-1,))
        return 0.5 * jnp.sum(vec * linalg.solve(self._matrix(), vec[..., None])[..., 0], -1)

    def _directions(self):
        mu, u = jnp.linalg.eigh(self._matrix())
        n = int(round(u.shape[-1] ** 0.5))
        w = jnp.swapaxes(u, -1, -2).reshape(u.shape[:-2] + (n * n, n, n))
        return w, 1.0 / mu

    def check(self, n: int | None = None) -> None:
        m = self._matrix()
        if is_concrete(m):
            size = m.shape[-1]
            if n is not None and size != n * n:
                raise ValueError(f"kinetic.{self._name} must be {n}x{n}x{n}x{n}")
        check_symmetric_positive_definite(
            m, f"kinetic.{self._name} (as an n^2 x n^2 matrix on pairs of indices)"
        )


@pytree.dataclass
class LeftInvariant(_BiTensorModel, _LeftInvariantModel):
    """l-af: the general spatially affine (left-invariant) energy (70), (82a).

    T = 1/2 L[A,B,C,D] Omega_hat[A,B] Omega_hat[C,D]; the paper's L^B_A^D_C is our
    L[A,B,C,D]. H = 1/2 L~ Sigma_hat Sigma_hat with L~ the reciprocal bi-tensor (82a).
    Drift: eigen-directions W_k of L (Frobenius-orthonormal), lam_k = 1/eigenvalue,
    H = 1/2 sum_k lam_k Tr(W_k Sigma_hat)^2, composed palindromically (``exact_flow`` False).
    """

    L: Any

    parameters = ("L",)
    exact_flow = False
    constrained_drift = "lie-group"
    _name = "L"
    symmetry = _closed({"spatial-affine"})

    def flow(self, state: State, h) -> State:
        w, rates = self._directions()
        return rank_one_splitting(state, w, rates, h, "left")


@pytree.dataclass
class RightInvariant(_BiTensorModel, _RightInvariantModel):
    """r-af: the general materially affine (right-invariant) energy (71), (83a).

    T = 1/2 R[i,j,k,l] Omega[i,j] Omega[k,l]; the paper's R^j_i^l_k is our R[i,j,k,l].
    H = 1/2 R~ Sigma Sigma (83a). Drift: palindromic rank-one splitting (``exact_flow`` False).
    """

    R: Any

    parameters = ("R",)
    exact_flow = False
    constrained_drift = "lie-group"
    _name = "R"
    symmetry = _closed({"material-affine"})

    def flow(self, state: State, h) -> State:
        w, rates = self._directions()
        return rank_one_splitting(state, w, rates, h, "right")


class _IsotropicAffineFamily:
    """T = I/2 Tr(X^T X) + A/2 Tr(X^2) + B/2 (Tr X)^2 with X = Omega_hat or Omega.

    Spin S^T = dT/dX: S = I X^T + A X + B Tr(X) Id. Inverse, with the constants of (86):
    X = S^T/I~ + S/A~ + Tr(S)/B~ Id and H = Tr(S^T S)/(2I~) + Tr(S^2)/(2A~) + (Tr S)^2/(2B~),
    1/I~ = I/(I^2 - A^2), 1/A~ = A/(A^2 - I^2), 1/B~ = -B/((I + A)(I + A + nB)).
    For n = 1 only the trace part exists: T = (I + A + B)/2 X^2, H = S^2 / (2(I + A + B)).

    Exact drift. Tr(S^T S) = Tr(S^2) - 2 Tr(skw(S)^2): H is a gl(n) Casimir part
    c(S) = Tr(S^2)(1/I~ + 1/A~)/2 + (Tr S)^2/(2B~) plus the so(n) Casimir -Tr(skw(S)^2)/I~;
    both flows commute and are one-parameter subgroups with the velocities
    X_c = (1/I~ + 1/A~) S + Tr(S)/B~ Id and X_r = (S^T - S)/I~ (constant along the flow).
    Left (af-is): phi -> phi E, pi -> E^-1 pi, E = expm(h X_c) expm(h X_r);
    right (is-af): phi -> E phi, pi -> pi E^-1, E = expm(h X_r) expm(h X_c).
    """

    def _constants(self, n: int):
        """(1/I~, 1/A~, 1/B~) of (86) for dimension n, each scalar or [N]."""
        i, a, b = self._iab()
        if n == 1:
            zero = jnp.zeros_like(i + a + b)
            return zero, zero, 1.0 / (i + a + b)
        return i / (i * i - a * a), a / (a * a - i * i), -b / ((i + a) * (i + a + n * b))

    def _energy_of_velocity(self, om):
        i, a, b = self._iab()
        return 0.5 * (i * _frob(om, om) + a * trace(om @ om) + b * trace(om) ** 2)

    def _spin_of_velocity(self, om):
        i, a, b = self._iab()
        return _bcast(i) * transpose(om) + _bcast(a) * om + _bcast(b * trace(om)) * eye_like(om)

    def _velocity_of_spin(self, s):
        ci, ca, cb = self._constants(s.shape[-1])
        return _bcast(ci) * transpose(s) + _bcast(ca) * s + _bcast(cb * trace(s)) * eye_like(s)

    def _energy_of_spin(self, s):
        ci, ca, cb = self._constants(s.shape[-1])
        return 0.5 * (ci * _frob(s, s) + ca * trace(s @ s) + cb * trace(s) ** 2)

    def _flow_coefficients(self, phi, h):
        """[..., 3] per body: (h (1/I~ + 1/A~), h / B~, h / I~), the coefficients of
        :func:`isotropic_flow` (batch of ``phi`` [..., n, n])."""
        ci, ca, cb = self._constants(phi.shape[-1])
        batch = phi.shape[:-2]
        return jnp.stack([jnp.broadcast_to(h * (ci + ca), batch),
                          jnp.broadcast_to(h * cb, batch), jnp.broadcast_to(h * ci, batch)], -1)

    def _flow_left(self, state: State, h) -> State:
        phi, pi = isotropic_flow(state.phi, state.pi, self._flow_coefficients(state.phi, h), True)
        return state._replace(phi=phi, pi=pi)

    def _flow_right(self, state: State, h) -> State:
        phi, pi = isotropic_flow(state.phi, state.pi, self._flow_coefficients(state.phi, h),
                                 False)
        return state._replace(phi=phi, pi=pi)

    def _check_region(self, model: str, n: int | None) -> None:
        if not all(is_concrete(v) for v in self._iab()):
            return
        i, a, b = (np.asarray(v) for v in self._iab())
        # the signs of the sums, computed on the values scaled by the largest of them (the
        # sums of values near the float64 limit would overflow to inf)
        scale = np.maximum(np.maximum(np.abs(i), np.abs(a)), np.abs(b))
        scale = np.where(scale > 0, scale, 1.0)
        si, sa, sb = i / scale, a / scale, b / scale
        if n == 1:
            ok = si + sa + sb > 0
            if not np.all(ok):
                raise ValueError(
                    f"kinetic.I + kinetic.A + kinetic.B must be > 0 for {model} to be positive "
                    f"definite in n = 1 {_first_bad(ok, I=i, A=a, B=b)}"
                )
            return
        for ok, what in (
            (si + sa > 0, "kinetic.I + kinetic.A must be > 0"),
            (si - sa > 0, "kinetic.I must be > kinetic.A"),
        ):
            if not np.all(ok):
                raise ValueError(
                    f"{what} for {model} to be positive definite {_first_bad(ok, I=i, A=a)}"
                )
        if n is not None:
            ok = si + sa + n * sb > 0
            if not np.all(ok):
                raise ValueError(
                    f"kinetic.I + kinetic.A + n kinetic.B must be > 0 (n = {n}) for {model} to be "
                    f"positive definite {_first_bad(ok, I=i, A=a, B=b)}"
                )


def isotropic_flow_jax(phi, pi, coefs, left: bool):
    """(phi, pi) after the exact drift of ``_IsotropicAffineFamily`` in JAX: S = pi phi (left)
    or phi pi (right), (c0, c1, c2) = ``coefs[..., :]``, X_c = c0 S + c1 Tr(S) Id,
    X_r = c2 (S^T - S), C = expm(X_c), R = expm(X_r); left: phi C R, R^T C^-1 pi;
    right: R C phi, pi C^-1 R^T."""
    mm = linalg.matmul
    s = mm(pi, phi) if left else mm(phi, pi)
    casimir = _bcast(coefs[..., 0]) * s + _bcast(coefs[..., 1] * trace(s)) * eye_like(s)
    c, r = expm(casimir), expm(_bcast(coefs[..., 2]) * (transpose(s) - s))
    # r is orthogonal (exponential of a skew matrix): r^-1 = r^T.
    if left:
        return mm(mm(phi, c), r), mm(transpose(r), linalg.solve(c, pi))
    return (mm(mm(r, c), phi),
            mm(transpose(linalg.solve(transpose(c), transpose(pi))), transpose(r)))


#: Fewest bodies worth handing to threads in the host drift (below, one thread).
HOST_DRIFT_THREAD_MIN_ROWS = 512
#: Fewest bodies (n = 3) for which the product runs the host drift: one core, medians, n = 3,
#: JAX flow / host kernel 171 / 181 us at 256 bodies, 633 / 435 us at 1024, 2.9 / 1.5 ms at
#: 4096 (for n = 2 the JAX flow: 0.79 / 1.27 ms at 4096).
HOST_DRIFT_MIN_BODIES = 512


#: Threads the host drift uses (:func:`affinebody._host.host_threads`, shared by every host
#: kernel).
host_drift_threads = _host.host_threads


@functools.cache
def _drift_kernel(n: int):
    return _host.specialized("drift", N=n, PADE13=linalg.PADE13, THETA13=linalg.THETA13,
                             MAX_SQUARINGS=linalg.MAX_SQUARINGS).isotropic_flow


def _host_isotropic_flow(left: bool, phi, pi, coefs, *, results=None):
    """The callback: the Numba kernel ``_host_kernels/drift.py`` over every body (leading axes
    flattened), in :data:`affinebody._host.PARTS` parts on up to
    :func:`affinebody._host.host_threads` threads, written into ``results`` (XLA's buffers
    for phi and pi, ``_host.callback``'s ``fills_results``; new arrays, returned, without
    them). Bodies are independent: the same bits on any number of threads."""
    shape = phi.shape
    n = shape[-1]
    kernel = _drift_kernel(n)
    phi = np.ascontiguousarray(np.asarray(phi).reshape(-1, n, n))
    pi = np.ascontiguousarray(np.asarray(pi).reshape(-1, n, n))
    coefs = np.ascontiguousarray(np.asarray(coefs).reshape(-1, 3))
    if results is None:
        results = np.empty_like(phi), np.empty_like(pi)
    phi_out, pi_out = (out.reshape(phi.shape) for out in results)  # views: C-contiguous
    rows = phi.shape[0]
    count = _host.thread_count(rows, HOST_DRIFT_THREAD_MIN_ROWS)
    _host.in_parts(lambda _, lo, hi: kernel(lo, hi, left, phi, pi, coefs, phi_out, pi_out),
                   rows, _host.PARTS, count)
    return tuple(out.reshape(shape) for out in results)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3,))
def isotropic_flow_host(phi, pi, coefs, left: bool):
    """:func:`isotropic_flow_jax` computed by the compiled host kernel (Numba, CPU), reached
    through ``_host.callback`` (vmap: one call over the whole batch). A callback has no
    derivative: jvp, grad and jacfwd differentiate :func:`isotropic_flow_jax` instead."""
    out = jax.ShapeDtypeStruct(jnp.shape(phi), jnp.result_type(phi))
    return _host.callback(functools.partial(_host_isotropic_flow, left), (out, out),
                          phi, pi, coefs, vmap_method="broadcast_all", fills_results=True)


@isotropic_flow_host.defjvp
def _isotropic_flow_host_jvp(left, primals, tangents):
    return jax.jvp(functools.partial(isotropic_flow_jax, left=left), primals, tangents)


def host_drift_in_use(phi) -> bool:
    """Whether :func:`isotropic_flow` of configurations shaped as ``phi`` runs the host
    kernel: a CPU with Numba, n = 3 and at least :data:`HOST_DRIFT_MIN_BODIES` bodies (a GPU:
    no host round trip; few bodies: a callback's fixed cost, ~0.1 ms, outweighs the work;
    n = 2: XLA's flow was the faster at every size measured, to 4096 bodies)."""
    bodies = int(np.prod(np.shape(phi)[:-2]))
    return _host.in_use() and np.shape(phi)[-1] == 3 and bodies >= HOST_DRIFT_MIN_BODIES


def isotropic_flow(phi, pi, coefs, left: bool):
    """The exact drift of af-is / af-af (``left``) and is-af: :func:`isotropic_flow_host`
    where :func:`host_drift_in_use`, :func:`isotropic_flow_jax` otherwise."""
    if host_drift_in_use(phi):
        return isotropic_flow_host(phi, pi, coefs, left)
    return isotropic_flow_jax(phi, pi, coefs, left)


def compile_host_drift(kinetic, phi) -> bool:
    """Compile (or load from the disk cache) the host drift kernel that a time loop of
    ``kinetic`` over configurations shaped as ``phi`` will call, so that a run's set-up pays
    for it rather than its first steps (where, compiled into an empty cache, it took ~4 s of
    the loop's time and of its steps/s). True where there was one to compile."""
    internal = getattr(kinetic, "internal", kinetic)
    if not (isinstance(internal, _IsotropicAffineFamily) and host_drift_in_use(phi)):
        return False
    n = np.shape(phi)[-1]
    # no bodies, given as the callback gives its operands (read-only views: a writable array
    # is another Numba type, which the loop would compile again)
    empty, coefs = np.zeros((0, n, n)), np.zeros((0, 3))
    empty.flags.writeable = coefs.flags.writeable = False
    _host_isotropic_flow(True, empty, empty, coefs)
    return True


_REGION_DOC = """
    Positive definite exactly when I + A > 0, I - A > 0 and I + A + nB > 0 (n >= 2): the
    metric acts as I + A on symmetric traceless, I - A on skew and I + A + nB on pure-trace
    velocities. For n = 1 only the trace part exists and the condition is I + A + B > 0.
    ``check(n)`` enforces this region (without n, the n-independent part).
"""


@pytree.dataclass
class AffineIsotropic(_IsotropicAffineFamily, _LeftInvariantModel):
    """af-is: spatially affine, materially isotropic internal energy (74), (85), (86).

    T = I/2 Tr(Omega_hat^T Omega_hat) + A/2 Tr(Omega_hat^2) + B/2 (Tr Omega_hat)^2,
    H = Tr(S^T S)/(2I~) + Tr(S^2)/(2A~) + (Tr S)^2/(2B~), S = Sigma_hat, constants (86).
    A = B = 0 gives (66), (80a). Exact drift: see ``_IsotropicAffineFamily``.
    """

    I: Any
    A: Any = 0.0
    B: Any = 0.0

    parameters = ("I", "A", "B")
    exact_flow = True
    constrained_drift = "exact"  # the inertia maps every subalgebra g into itself
    symmetry = _closed({"spatial-affine", "material-euclidean"})

    def _iab(self):
        return tuple(as_float64(getattr(self, k), f"kinetic.{k}") for k in "IAB")

    def flow(self, state: State, h) -> State:
        return self._flow_left(state, h)

    def check(self, n: int | None = None) -> None:
        self._check_region("af-is", n)


@pytree.dataclass
class IsotropicAffine(_IsotropicAffineFamily, _RightInvariantModel):
    """is-af: spatially isotropic, materially affine internal energy (73), (84a), (86).

    T = I/2 Tr(Omega^T Omega) + A/2 Tr(Omega^2) + B/2 (Tr Omega)^2,
    H = Tr(S^T S)/(2I~) + Tr(S^2)/(2A~) + (Tr S)^2/(2B~), S = Sigma, constants (86).
    Exact drift: see ``_IsotropicAffineFamily``.
    """

    I: Any
    A: Any = 0.0
    B: Any = 0.0

    parameters = ("I", "A", "B")
    exact_flow = True
    constrained_drift = "exact"  # the inertia maps every subalgebra g into itself
    symmetry = _closed({"spatial-euclidean", "material-affine"})

    def _iab(self):
        return tuple(as_float64(getattr(self, k), f"kinetic.{k}") for k in "IAB")

    def flow(self, state: State, h) -> State:
        return self._flow_right(state, h)

    def check(self, n: int | None = None) -> None:
        self._check_region("is-af", n)


AffineIsotropic.__doc__ += _REGION_DOC
IsotropicAffine.__doc__ += _REGION_DOC


@pytree.dataclass
class AffineAffine(_IsotropicAffineFamily, _LeftInvariantModel):
    """af-af: the doubly affine internal energy (72); (84a)/(85) with I = 0.

    T = A/2 Tr(Omega^2) + B/2 (Tr Omega)^2 = A/2 Tr(Omega_hat^2) + B/2 (Tr Omega_hat)^2.
    Indefinite by design for n >= 2 (A Tr(X^2) has both signs on symmetric and skew X), so
    ``check`` only demands a regular Legendre map: A != 0 and A + nB != 0.
    H = Tr(S^2)/(2A) - B (Tr S)^2 / (2A(A + nB)) with S = Sigma_hat (or Sigma: same value).
    Drift (exact): S is conserved, phi -> phi expm(h Omega_hat), pi -> expm(-h Omega_hat) pi.
    """

    A: Any
    B: Any = 0.0

    parameters = ("A", "B")
    exact_flow = True
    constrained_drift = "exact"  # the inertia maps every subalgebra g into itself
    symmetry = _closed({"spatial-affine", "material-affine"})

    def _iab(self):
        a = as_float64(self.A, "kinetic.A")
        return jnp.zeros_like(a), a, as_float64(self.B, "kinetic.B")

    def flow(self, state: State, h) -> State:
        return self._flow_left(state, h)

    def check(self, n: int | None = None) -> None:
        if not all(is_concrete(v) for v in self._iab()):
            return
        _, a, b = (np.asarray(v) for v in self._iab())
        if n == 1:
            ok = a + b != 0
            if not np.all(ok):
                raise ValueError(
                    f"kinetic.A + kinetic.B must be nonzero for af-af in n = 1: the Legendre "
                    f"map is singular {_first_bad(ok, A=a, B=b)}"
                )
            return
        ok = a != 0
        if not np.all(ok):
            raise ValueError(
                "kinetic.A must be nonzero for af-af: the Legendre map is singular at A = 0 "
                f"(af-af may be indefinite, not degenerate) {_first_bad(ok, A=a)}"
            )
        if n is not None:
            ok = a + n * b != 0
            if not np.all(ok):
                raise ValueError(
                    f"kinetic.A + n kinetic.B must be nonzero (n = {n}) for af-af: the "
                    f"Legendre map is singular on dilatations {_first_bad(ok, A=a, B=b)}"
                )


# --------------------------------------------------------------------------------------------
# The kinetic energy of a system of bodies
# --------------------------------------------------------------------------------------------


@pytree.dataclass
class KineticEnergy:
    """Total kinetic energy of N bodies, T = sum_A (T_tr)_A + (T_int)_A (10), (55).

    ``translational`` and ``internal`` are per-body terms (parameters scalar for identical
    bodies or with a leading body axis N). ``flow`` is the exact drift when the translational
    term is d'Alembert (its flow moves x only and commutes with every internal flow) and the
    internal flow is exact; otherwise the Strang composition tr(h/2) int(h) tr(h/2).
    """

    translational: Any
    internal: Any

    @property
    def pieces(self) -> tuple:
        """The (translational, internal) terms, for integrators that compose flows themselves."""
        return (self.translational, self.internal)

    @property
    def exact_flow(self) -> bool:
        commuting = self.translational.flow_moves_only_x
        return commuting and self.translational.exact_flow and self.internal.exact_flow

    @property
    def symmetry(self) -> frozenset[str]:
        return self.translational.symmetry & self.internal.symmetry

    def lagrangian(self, vs: VelocityState) -> jax.Array:
        """Total T [...] summed over the body axis."""
        t = self.translational.lagrangian(vs.phi, vs.v) + self.internal.lagrangian(vs.phi, vs.xi)
        return jnp.sum(t, axis=-1)

    def hamiltonian(self, state: State) -> jax.Array:
        """Total kinetic Hamiltonian [...] summed over the body axis (75a) without V."""
        t = self.translational.hamiltonian(state.phi, state.p)
        return jnp.sum(t + self.internal.hamiltonian(state.phi, state.pi), axis=-1)

    def legendre(self, vs: VelocityState) -> State:
        p = self.translational.legendre(vs.phi, vs.v)
        return State(vs.x, vs.phi, p, self.internal.legendre(vs.phi, vs.xi))

    def inverse_legendre(self, state: State) -> VelocityState:
        v = self.translational.inverse_legendre(state.phi, state.p)
        xi = self.internal.inverse_legendre(state.phi, state.pi)
        return VelocityState(state.x, state.phi, v, xi)

    def flow(self, state: State, h) -> State:
        if self.translational.flow_moves_only_x:  # commutes with every internal flow
            return self.internal.flow(self.translational.flow(state, h), h)
        state = self.translational.flow(state, 0.5 * h)
        state = self.internal.flow(state, h)
        return self.translational.flow(state, 0.5 * h)

    def check(self, n: int | None = None) -> None:
        self.translational.check(n)
        self.internal.check(n)


#: Internal kinetic models by configuration name.
MODELS: dict[str, type[AbstractKineticTerm]] = {
    "dalembert": DAlembert,
    "is-af": IsotropicAffine,
    "af-is": AffineIsotropic,
    "af-J": AffineJ,
    "H-af": HAffine,
    "l-af": LeftInvariant,
    "r-af": RightInvariant,
    "af-af": AffineAffine,
}

#: Translational kinetic models by configuration name ((63) is d'Alembert's (6)).
TRANSLATIONAL_MODELS: dict[str, type[AbstractKineticTerm]] = {
    "dalembert": DAlembertTranslational,
    "is-af": DAlembertTranslational,
    "af-is": AffineTranslational,
}


__all__ = [
    "MODELS", "SYMMETRIES", "TRANSLATIONAL_MODELS", "AbstractKineticTerm", "AffineAffine",
    "AffineIsotropic", "AffineJ", "AffineTranslational", "DAlembert", "DAlembertTranslational",
    "HAffine", "IsotropicAffine", "KineticEnergy", "LeftInvariant", "RightInvariant",
    "compile_host_drift", "host_drift_in_use", "host_drift_threads", "isotropic_flow",
    "isotropic_flow_host", "isotropic_flow_jax",
    "rank_one_splitting",
]
