"""The Hamiltonian system of N affine bodies: H = T + V (75a), its vector field, kicks and drifts.

``HamiltonianSystem(kinetic, potential=None, group="GL+")`` bundles a ``KineticEnergy``
(``affinebody.kinetic``), a potential with ``energy(x, phi)`` (``affinebody.potentials``) or None,
and the configuration space of every phi_K (``affinebody.groups``):

- ``"GL+"`` (default) and ``"GL"``: the open group; a motion that reaches det phi = 0 has left it
  (the run driver stops there, see ``simulate.run``);
- ``"L"``: all of L(n, R), which the paper allows for d'Alembert motion (section 1);
- ``"SL"``, ``"UL"`` (incompressible), ``"SO"``, ``"O"`` (rigid), ``"R+SO"``, ``"R+O"``
  (shape-preserving): constrained bodies, see ``affinebody.constraints``.

Hamilton's equations in the project's placement pi[a, i] = pi^a_i (docs/theory/conventions.md):
``dx/dt = dH/dp, dp/dt = -dH/dx, dphi/dt = (dH/dpi)^T, dpi/dt = -(dH/dphi)^T`` (53), (87).

Constrained groups. For a subgroup G with Lie algebra g, the momentum of the constrained system is
a covector on T_phi G, i.e. pi modulo the annihilator {pi : Tr(pi phi X) = 0 for all X in g}. We
represent it by the unique pi whose co-moving affine spin Sigma_hat = pi phi lies in g itself
(traceless for SL/UL, skew for SO/O, R Id + skew for R+SO/R+O):

    pi  ->  P_g(pi phi) phi^-1,     P_g the Frobenius projection onto g (groups.project_algebra).

A kick then projects its momentum increment, ``pi -= h P_g((dV/dphi)^T phi) phi^-1``, which is the
exact flow of V restricted to G (phi is fixed during a kick). Each kinetic term drifts on G in the
way it declares (``constrained_drift`` of ``kinetic.AbstractKineticTerm``): its own exact flow
where that stays on G (isotropic af-is, is-af, af-af; translational terms), a Lie-group splitting
in g for the other left/right-invariant models (af-J, H-af, l-af, r-af), RATTLE for d'Alembert.
The kinetic energy on G is the restricted one, H evaluated at the metric lift of pi
(``constraints.metric_lift``).

Non-holonomic constraints. ``rotationless="spatial"`` imposes (40), Omega = Omega^T;
``rotationless="material"`` imposes (41), Omega_hat = Omega_hat^T (``affinebody.nonholonomic``).
Then pi is the momentum of an admissible velocity (``constrain`` projects onto them) and the
system is integrated by ``integrators.NONHOLONOMIC_RATTLE`` only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from affinebody import _linalg as linalg
from affinebody import _pytree as pytree
from affinebody import constraints, nonholonomic
from affinebody._checks import as_matrix, as_vector, is_concrete, transpose
from affinebody.constraints import CONSTRAINED_GROUPS
from affinebody.groups import CONFIGURATION_SPACES, is_member_jit, project_algebra
from affinebody.state import State

#: Configuration spaces a HamiltonianSystem accepts (the one list: groups.CONFIGURATION_SPACES).
SYSTEM_GROUPS = CONFIGURATION_SPACES
#: Groups whose boundary det phi = 0 the run driver watches.
OPEN_GROUPS = ("GL+", "GL")


def kinetic_terms(kinetic) -> tuple[Any, ...]:
    """The kinetic terms of ``kinetic`` in drift order: translational ones, then internal ones."""
    terms: list[Any] = []
    for part in (getattr(kinetic, "translational", None), getattr(kinetic, "internal", None)):
        if part is None:
            continue
        if isinstance(part, Sequence):
            terms.extend(t for t in part if t is not None)
        else:
            terms.append(part)
    return tuple(terms)


def project_momentum(phi: jax.Array, pi: jax.Array, group: str) -> jax.Array:
    """Representative of the constrained momentum: pi -> P_g(pi phi) phi^-1 (module docstring).

    Linear in pi; the identity on GL, GL+ and L.
    """
    if group not in CONSTRAINED_GROUPS:
        return pi
    sigma_hat = pi @ phi
    removed = sigma_hat - project_algebra(sigma_hat, group)
    # removed @ phi^-1, via a solve with phi^T
    return pi - transpose(linalg.solve(transpose(phi), transpose(removed)))


def _shapes_agree(state: State) -> None:
    """ValueError (one line) unless x, p are [..., N, n] and phi, pi [..., N, n, n] with the
    same leading axes (a mismatch reached H as a JAX broadcasting TypeError)."""
    x, phi, p, pi = (tuple(jnp.shape(a)) for a in state)
    if x != p or phi != pi or x[:-1] != phi[:-2]:
        raise ValueError(f"state shapes disagree: x {x}, p {p} must be [N, n] and phi {phi}, "
                         f"pi {pi} [N, n, n] with the same N, n")


@pytree.dataclass
class HamiltonianSystem:
    """H(x, phi, p, pi) = T(kinetic) + V(potential) on the configuration space ``group``.

    kinetic: a ``KineticEnergy`` (``hamiltonian(State)``, terms with exact ``flow``).
    potential: an object with ``energy(x, phi) -> scalar`` (summed over bodies), or None.
    group: one of SYSTEM_GROUPS.
    """

    # kinetic parameters are array leaves (traced under jit: one compilation serves every
    # inertia); potentials are hashable static objects and enter compiled functions as data of
    # the treedef, with the group and the constraint.
    kinetic: Any
    potential: Any = pytree.static_field(default=None)
    group: str = pytree.static_field(default="GL+")
    rotationless: str | None = pytree.static_field(default=None)
    #: None, or the current cell matrix [n, n] of a periodic box that a barostat deforms (an
    #: array leaf: the pair terms' own box is then only the reference; a neighbour list must
    #: be built in this cell, docs/pressure.md)
    cell: Any = None

    def __post_init__(self):
        if self.group not in SYSTEM_GROUPS:
            raise ValueError(
                f"system.group must be one of {', '.join(SYSTEM_GROUPS)} (got {self.group!r})"
            )
        nonholonomic.check_rotationless(self.rotationless, self.group)
        if not hasattr(self.kinetic, "hamiltonian"):
            return  # a placeholder leaf while JAX maps over the pytree, not a user's system
        if not kinetic_terms(self.kinetic):
            raise ValueError("system.kinetic has no kinetic terms: give a translational or "
                             "internal kinetic energy")

    @property
    def constrained(self) -> bool:
        """True on the subgroups SL, UL, SO, O, R+SO, R+O (holonomic constraints on phi)."""
        return self.group in CONSTRAINED_GROUPS

    @property
    def nonholonomic(self) -> bool:
        """True with a rotationless constraint (40) or (41)."""
        return self.rotationless is not None

    @property
    def _needs_metric_lift(self) -> bool:
        return self.constrained and any(
            constraints.drift_mode(t) != "exact" for t in kinetic_terms(self.kinetic))

    # ----------------------------------------------------------------- energies
    def potential_energy(self, state: State, neighbors=None) -> jax.Array:
        """V(x, phi), a scalar per batch element (0 without a potential).

        neighbors: None (pair terms sum over all pairs) or a ``neighbors.NeighborList`` valid
        for ``state``, which the pair terms sum over instead (``potentials.PairTerm.energy``).
        """
        if self.potential is None:
            return jnp.zeros(state.phi.shape[:-3], dtype=state.phi.dtype)
        return self._potential_energy(state.x, state.phi, neighbors)

    def _potential_energy(self, x, phi, neighbors):
        if self.cell is not None:
            from affinebody.potentials import total_potential

            return total_potential([self.potential]).energy(x, phi, neighbors, cell=self.cell)
        if neighbors is None:  # potentials written as energy(x, phi) keep working
            return self.potential.energy(x, phi)
        return self.potential.energy(x, phi, neighbors)

    def kinetic_energy(self, state: State) -> jax.Array:
        """T(x, phi, p, pi) summed over bodies (76a)-(85); on a subgroup the restricted T."""
        if self.nonholonomic:
            return self.kinetic.hamiltonian(state)
        state = self.constrain(state)
        if self._needs_metric_lift:
            state = constraints.metric_lift(self.kinetic.hamiltonian, state, self.group)
        return self.kinetic.hamiltonian(state)

    def hamiltonian(self, state: State, neighbors=None) -> jax.Array:
        """H = T + V (75a); ``neighbors`` as in :meth:`potential_energy`."""
        _shapes_agree(state)  # static shapes: also under jit, at no cost
        return self.kinetic_energy(state) + self.potential_energy(state, neighbors)

    # ----------------------------------------------------------------- dynamics
    def vector_field(self, state: State) -> State:
        """(dx/dt, dphi/dt, dp/dt, dpi/dt) of Hamilton's equations, by autodiff of H.

        Defined on GL+, GL and L, where phase space is an open subset of a vector space.
        """
        if self.constrained or self.nonholonomic:
            raise ValueError(
                f"vector_field is defined on GL+, GL and L without constraints; on "
                f"{self.group} use the splitting integrators, whose sub-flows stay on the group, "
                f"and with a rotationless constraint nonholonomic.lagrange_dalembert_field"
            )
        grad = jax.grad(lambda s: jnp.sum(self.hamiltonian(s)))(state)
        return State(x=grad.p, phi=transpose(grad.pi), p=-grad.x, pi=-transpose(grad.phi))

    def constrain(self, state: State) -> State:
        """``state`` with pi replaced by the constrained-momentum representative (no-op on GL).

        With a rotationless constraint: the momentum of the admissible velocity nearest in the
        kinetic metric (the velocity projection of non-holonomic RATTLE).
        """
        if self.nonholonomic:
            return nonholonomic.admissible_momentum(self.kinetic, state, self.rotationless,
                                                    self.group)
        if not self.constrained:
            return state
        return state._replace(pi=project_momentum(state.phi, state.pi, self.group))

    def forces(self, state: State, neighbors=None) -> tuple[jax.Array, jax.Array]:
        """(dV/dx, dV/dphi) at ``state`` (zeros without a potential); ``neighbors`` as in
        :meth:`potential_energy` (then the closed-form kernels of ``affinebody.pair_kernels``)."""
        if self.potential is None:
            return jnp.zeros_like(state.x), jnp.zeros_like(state.phi)
        return jax.grad(lambda x, phi: jnp.sum(self._potential_energy(x, phi, neighbors)),
                        argnums=(0, 1))(state.x, state.phi)

    def energy_and_forces(self, state: State, neighbors=None) -> tuple[jax.Array, tuple]:
        """(V, (dV/dx, dV/dphi)) at ``state`` from one pass (the energy is the primal of
        :meth:`forces`' gradient); ``neighbors`` as in :meth:`potential_energy`."""
        if self.potential is None:
            return self.potential_energy(state), self.forces(state)
        return jax.value_and_grad(
            lambda x, phi: jnp.sum(self._potential_energy(x, phi, neighbors)),
            argnums=(0, 1))(state.x, state.phi)

    def kick(self, state: State, h, neighbors=None, forces=None) -> State:
        """Exact flow of V for time h: p -= h dV/dx, pi -= h (dV/dphi)^T (projected on G).

        neighbors: None (all pairs) or a ``neighbors.NeighborList`` valid for ``state`` (the
        pair forces then come from the closed-form kernels of ``affinebody.pair_kernels``).
        forces: (dV/dx, dV/dphi) at ``state`` if already known (:meth:`forces`): the
        configuration does not move during a kick, so a step can reuse the forces of the
        kick before it.
        """
        if self.potential is None:
            return state
        gx, gphi = self.forces(state, neighbors) if forces is None else forces
        dpi = project_momentum(state.phi, -h * transpose(gphi), self.group)
        return state._replace(p=state.p - h * gx, pi=state.pi + dpi)

    def drift(self, state: State, h) -> State:
        """Flow of T for time h: palindromic (Strang) composition of the terms' exact flows.

        With one kinetic term (or commuting ones, e.g. d'Alembert translational + any internal
        term) this is the exact geodesic flow; otherwise a symmetric second-order composition.
        """
        terms = kinetic_terms(self.kinetic)
        if len(terms) == 1:
            return self._term_flow(terms[0], state, h)
        for term in terms[:-1]:
            state = self._term_flow(term, state, 0.5 * h)
        state = self._term_flow(terms[-1], state, h)
        for term in reversed(terms[:-1]):
            state = self._term_flow(term, state, 0.5 * h)
        return state

    def _term_flow(self, term, state: State, h) -> State:
        if not self.constrained:
            return term.flow(state, h)
        state = constraints.constrained_flow(term, state, h, self.group)
        # exact for terms that keep phi fixed (their momentum increment is constant); for
        # RATTLE the same covector as its velocity projection; a round-off clean-up otherwise
        return self.constrain(state)

    # ----------------------------------------------------------------- neighbour lists
    def neighbor_range(self):
        """(space, cutoff, variable) that one neighbour list must cover for this potential
        (:func:`affinebody.potentials.neighbor_range`: every pair term needs a cut-off on the
        same variable in the same space); ValueError otherwise, saying why (the run then has
        to sum over all pairs)."""
        from affinebody.potentials import neighbor_range

        return neighbor_range(() if self.potential is None else self.potential)

    # ----------------------------------------------------------------- validation
    def check(self, state: State) -> State:
        """Validate ``state`` eagerly (shapes, float64, group membership, model/group match).

        Returns the state with the constrained-momentum representative. Call once before
        compiled runs (``simulate.run`` does).
        """
        x = as_vector(state.x, "state.x")
        phi = as_matrix(state.phi, "state.phi")
        p = as_vector(state.p, "state.p", n=phi.shape[-1])
        pi = as_matrix(state.pi, "state.pi", n=phi.shape[-1])
        state = State(x, phi, p, pi)
        _shapes_agree(state)
        if is_concrete(phi):
            body = self.outside_group(phi)
            if body is not None:
                raise ValueError(
                    f"state.phi of body {body} is not in {self.group}(n) (tolerance 1e-9): "
                    f"start on the group (e.g. groups.project(phi, {self.group!r}))"
                )
            if self.constrained:
                self._check_drifts_preserve_group(phi.shape[-1])
        return _constrain(self, state)

    def outside_group(self, phi) -> int | None:
        """The first body whose phi [N, n, n] is not in the configuration group to tolerance
        1e-9 (:func:`groups.is_member`: on GL and GL+, singular as far as float64 resolves),
        or None."""
        member = np.atleast_1d(np.asarray(is_member_jit(phi, group=self.group, tol=1e-9)))
        return None if np.all(member) else int(np.argwhere(~member)[0][-1])

    def _check_drifts_preserve_group(self, n: int) -> None:
        """Refuse kinetic terms with no constrained drift (unknown types: a numeric probe)."""
        rng = np.random.default_rng(12345)
        g = self.group
        a = 0.3 * rng.standard_normal((1, n, n))
        phi = linalg.expm(project_algebra(jnp.asarray(a), g))
        sigma_hat = project_algebra(jnp.asarray(rng.standard_normal((1, n, n))), g)
        pi = sigma_hat @ linalg.inv(phi)
        probe = State(jnp.asarray(rng.standard_normal((1, n))), phi,
                      jnp.asarray(rng.standard_normal((1, n))), pi)
        for term in kinetic_terms(self.kinetic):
            if constraints.drift_mode(term) is not None:
                continue
            out = term.flow(probe, 0.37)
            sh = out.pi @ out.phi
            stays = bool(np.all(np.asarray(is_member_jit(out.phi, group=g, tol=1e-9))))
            in_algebra = bool(np.max(np.abs(np.asarray(sh - project_algebra(sh, g)))) < 1e-9)
            fixed_phi = bool(np.max(np.abs(np.asarray(out.phi - phi))) == 0.0)
            if not stays or not (in_algebra or fixed_phi):
                raise ValueError(
                    f"kinetic term {type(term).__name__} does not keep phi in {g}(n): its exact "
                    f"drift leaves the group and it is neither d'Alembert nor left/right "
                    f"affinely invariant (no constrained drift); use group = 'GL+'"
                )

    def replace(self, **changes) -> HamiltonianSystem:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


#: :meth:`HamiltonianSystem.constrain` as one program, for ``check`` on a concrete state (op by
#: op, the Newton solve of the non-holonomic projection compiled each of its operations apart).
_constrain = pytree.compiled_for_models(HamiltonianSystem.constrain)


__all__ = [
    "OPEN_GROUPS", "SYSTEM_GROUPS", "HamiltonianSystem", "kinetic_terms", "project_momentum",
]
