"""Run driver: integrate a ``HamiltonianSystem`` with ``lax.scan``, record frames and observables.

``run(system, state, dt, steps, integrator="strang", every=1, observers=("energy",))`` compiles
one function: an outer ``lax.scan`` over ``steps // every`` chunks, each an inner ``lax.scan`` of
``every`` steps, recording the state and the observables after every chunk (frame 0 is the
initial state). Every step is watched:

- non-finite numbers in a body's x, phi, p or pi stop the run at that step (the state of the step
  before is kept), reporting step, body and a reason: "time step too large" when the same interval
  done in ten steps of dt/10 stays finite, "potential too stiff or singular" otherwise;
- on GL+ and GL a change of sign of det phi_K (the body left the group through det phi = 0, as
  unconfined d'Alembert motion does in finite time) stops the run with a message suggesting
  ``group = "L"`` (paper §1 allows L(n, R) as configuration space).

A stop raises ``IntegrationStopped`` (with ``.report`` and the partial ``.trajectory``), or with
``on_stop="return"`` returns the partial trajectory with ``trajectory.stop`` set.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from affinebody import _linalg as linalg
from affinebody import neighbors as nb
from affinebody import observables as obs
from affinebody import thermostats as th
from affinebody._pytree import is_array_pytree
from affinebody.integrators import get_integrator
from affinebody.state import State
from affinebody.system import OPEN_GROUPS, HamiltonianSystem

#: Observables available by name in ``run(..., observers=...)``; each maps (system, state) or,
#: in a run with a neighbour list, (system, state, list) (the list is valid for the state).
NAMED_OBSERVABLES: Mapping[str, Callable[..., jax.Array]] = {
    "energy": lambda system, s, neighbors=None: system.hamiltonian(s, neighbors),
    "kinetic_energy": lambda system, s, neighbors=None: system.kinetic_energy(s),
    "potential_energy": lambda system, s, neighbors=None: system.potential_energy(s, neighbors),
    "linear_momentum": lambda system, s, neighbors=None: obs.linear_momentum(s),
    "affine_spin": lambda system, s, neighbors=None: obs.affine_spin(s),
    "comoving_affine_spin": lambda system, s, neighbors=None: obs.comoving_affine_spin(s),
    "affine_momentum": lambda system, s, neighbors=None: obs.affine_momentum(s),
    "angular_momentum": lambda system, s, neighbors=None: obs.angular_momentum(s),
    "vorticity": lambda system, s, neighbors=None: obs.vorticity(s),
    "volumes": lambda system, s, neighbors=None: obs.volumes(s),
    "relative_volumes": lambda system, s, neighbors=None: obs.relative_volumes(s),
    "translational_temperature":
        lambda system, s, neighbors=None: th.translational_temperature(system, s),
    "internal_temperature": lambda system, s, neighbors=None: th.internal_temperature(system, s),
}



class Stop(enum.IntEnum):
    """Why the driver did not keep a step: the one status type of ``run``, ``sweep`` and the
    studies (a compiled loop carries it as an integer)."""

    NONE = 0
    LEFT_GROUP = 1  #: det phi of a body changed sign on GL+ / GL (it crossed det phi = 0)
    NON_FINITE = 2  #: a body's x, phi, p or pi is not finite
    OVERFLOW = 3  #: the neighbour list overflowed its capacities (reallocate and go on)

    @property
    def reason(self) -> str:
        """A short phrase for reports and sweep results."""
        return _STOP_REASONS[self]


_STOP_REASONS = {
    Stop.NONE: "",
    Stop.LEFT_GROUP: "left the group (det phi crossed 0)",
    Stop.NON_FINITE: "non-finite state",
    Stop.OVERFLOW: "neighbour list overflow",
}
_OK, _LEFT_GROUP, _NON_FINITE, _OVERFLOW = (int(s) for s in Stop)


@dataclass(frozen=True)
class StopReport:
    """Why and where a run stopped: ``step`` (1-based) failed, the state of step-1 is kept;
    ``body``: the first body at fault, -1 for a stop that is no one body's (a neighbour-list
    overflow, the box of an NPT run)."""

    step: int
    time: float
    body: int
    reason: str
    message: str


@dataclass(frozen=True)
class Trajectory:
    """Frames of a run: ``times`` [F], ``states`` (State stacked over F), ``observables``."""

    times: np.ndarray
    states: State
    observables: dict[str, np.ndarray]
    stop: StopReport | None = None
    #: (spec, list) of the run's neighbour list, valid for the last state (None: all pairs)
    neighbors: tuple[nb.NeighborSpec, nb.NeighborList] | None = None
    #: rebuilds of the list inside the compiled loop (kept steps only)
    neighbor_rebuilds: int = 0
    #: reallocations after an overflow of the list's capacities (the run went on transparently)
    neighbor_reallocations: int = 0

    @property
    def final_state(self) -> State:
        """The last recorded state."""
        return jax.tree.map(lambda a: a[-1], self.states)


class IntegrationStopped(RuntimeError):
    """A run stopped early; ``report`` says where and why, ``trajectory`` holds the frames."""

    def __init__(self, report: StopReport, trajectory: Trajectory):
        super().__init__(report.message)
        self.report = report
        self.trajectory = trajectory


def _observer_items(observers) -> tuple[tuple[str, object], ...]:
    if observers is None:
        return ()
    if isinstance(observers, str):
        observers = (observers,)
    items = observers.items() if isinstance(observers, Mapping) else ((o, o) for o in observers)
    out = []
    for name, spec in items:
        if isinstance(spec, str):
            if spec not in NAMED_OBSERVABLES:
                raise ValueError(
                    f"unknown observer {spec!r} (choose from {', '.join(NAMED_OBSERVABLES)} "
                    f"or give a function of the state)"
                )
        elif not callable(spec):
            raise ValueError(f"observer {name!r} must be a name or a function of the state")
        out.append((str(name), spec))
    return tuple(out)


def _evaluate(system, state, items, neighbors=None):
    def named(spec):
        if neighbors is None:
            return NAMED_OBSERVABLES[spec](system, state)
        return NAMED_OBSERVABLES[spec](system, state, neighbors)

    def call(spec):  # a function of the state, or of (system, state, list) if it says so
        if getattr(spec, "takes_system", False):
            return spec(system, state, neighbors)
        return spec(state)

    return {name: (named(spec) if isinstance(spec, str) else call(spec))
            for name, spec in items}


def _per_body_finite(state: State) -> jax.Array:
    return (jnp.all(jnp.isfinite(state.x), axis=-1) & jnp.all(jnp.isfinite(state.p), axis=-1)
            & jnp.all(jnp.isfinite(state.phi), axis=(-2, -1))
            & jnp.all(jnp.isfinite(state.pi), axis=(-2, -1)))


class Watched(NamedTuple):
    """One step of the driver with its verdict (see :func:`watched_step`)."""

    state: State
    neighbors: object  # the list after the step (None without a list)
    forces: object  # the forces at ``state`` (first same as last), () when not carried
    stop: jax.Array  # int, a :class:`Stop` code: NONE when the step may be kept
    bad_bodies: jax.Array  # [N] bool, the bodies that made it fail
    tracked: object  # integrators.NeighborStep of the step, or None without a list


def watched_step(system, method, dt, spec=None, *, sign0, watch_det: bool):
    """``step(state, neighbors, forces) -> Watched``: one step of ``method`` and the checks
    that decide whether it may be kept, shared by every loop that integrates (``run``, the
    samples of ``sweep``).

    A step fails when a body's state is not finite (``Stop.NON_FINITE``), when, on GL+ / GL
    (``watch_det``), det phi of a body no longer has the sign ``sign0`` it started with
    (``Stop.LEFT_GROUP``: it crossed det phi = 0, the boundary of the group), or when the
    neighbour list of ``spec`` overflowed (``Stop.OVERFLOW``: the forces may be wrong).
    Integrators that carry the forces from step to step (``method.carries_forces``: the
    splittings, first same as last) take and return them; others get and return ``()``.
    """
    carries = getattr(method, "carries_forces", False)

    def step(state, neighbors, forces) -> Watched:
        tracked = None
        if carries:
            new, tracked, new_forces = method.advance(system, state, forces, dt, spec, neighbors)
        else:
            new, new_forces = method.step(system, state, dt), forces
        if tracked is None:
            new_list, overflow = neighbors, jnp.asarray(False)
        else:
            new_list, overflow = tracked.neighbors, tracked.overflow != 0
        finite = _per_body_finite(new)
        crossed = (jnp.sign(linalg.det(new.phi)) != sign0) & finite & watch_det
        stop = jnp.where(overflow, _OVERFLOW, jnp.where(
            jnp.any(~finite), _NON_FINITE, jnp.where(jnp.any(crossed), _LEFT_GROUP, _OK)))
        return Watched(new, new_list, new_forces, stop, ~finite | crossed, tracked)

    return step


def initial_forces(system, method, state, neighbors=None, first_step=0, heat=0.0):
    """What :func:`watched_step` carries in at the first step: the forces at ``state`` for an
    integrator that carries them, else ``()``; a thermostatted integrator's carry
    (``integrators.Thermostatted.initial_carry``) at global step ``first_step`` with the heat
    ``heat`` exchanged so far."""
    if not getattr(method, "carries_forces", False):
        return ()
    forces = system.forces(state, neighbors)
    if hasattr(method, "initial_carry"):
        return method.initial_carry(system, state, forces, first_step, heat)
    return forces


def _recompute_frame(system, items, values, frame, state, neighbors) -> None:
    """``values[...][frame]`` again for ``state`` with ``neighbors`` (in place; the heat,
    which no list changes, kept)."""
    again = jax.jit(lambda s, lst: _evaluate(system, s, items, lst))(state, neighbors)
    if "heat" in values:
        again["effective_energy"] = (system.hamiltonian(state, neighbors)
                                     - values["heat"][frame])
    for key, value in again.items():
        values[key][frame] = np.asarray(value)


def _thermostat_values(system, method, state, carried, neighbors) -> dict:
    """``heat`` and ``effective_energy`` (H minus the heat) of a thermostatted run, else {}."""
    if not hasattr(method, "initial_carry"):
        return {}
    return {"heat": carried.heat,
            "effective_energy": system.hamiltonian(state, neighbors) - carried.heat}


def _simulate(system, state, dt, neighbors, start=(0, 0.0), active=None, *, n_chunks, every,
              method, observers, spec):
    """The compiled run. With a neighbour list (``spec`` not None) the carry holds the list,
    valid for the carried state; a step whose list overflowed is discarded like a non-finite
    one (status _OVERFLOW), recording what the reallocation must hold in ``lost``.
    ``active``: None, or how many of the ``n_chunks`` chunks to run (traced): a run that goes
    on after a reallocation runs its remaining chunks through the program of the same
    ``n_chunks``, compiled once for the new list, not once more for its shorter length."""
    # not weakly typed: the step's int32 codes then promote to it, so the carry keeps its
    # types through a chunk (as a skipped chunk returns it)
    zero = jnp.zeros((), dtype=jnp.int64)
    step = watched_step(system, method, dt, spec, sign0=jnp.sign(linalg.det(state.phi)),
                        watch_det=system.group in OPEN_GROUPS)

    def one_step(carry, _):
        state, nbrs, forces, status, bad_step, bad_body, k, rebuilds, lost = carry
        w = step(state, nbrs, forces)
        first = (status == _OK) & (w.stop != _OK)
        status = jnp.where(first, w.stop, status)
        bad_step = jnp.where(first, k + 1, bad_step)
        bad_body = jnp.where(first, jnp.argmax(w.bad_bodies), bad_body)
        keep_old = status != _OK
        keep = lambda old, nw: jnp.where(keep_old, old, nw)  # noqa: E731
        state = jax.tree.map(keep, state, w.state)
        # the list is not kept back with the state: holding the old one for that cost two
        # copies of it per step (XLA then copies it through the update's lax.cond too,
        # ~0.3 ms at 4096 bodies); the chunk gives the kept state a list of its own instead
        nbrs = w.neighbors
        forces = jax.tree.map(keep, forces, w.forces)
        if w.tracked is not None:
            rebuilds = rebuilds + jnp.where(keep_old, 0, w.tracked.rebuilds)
            seen = (w.tracked.overflow, w.tracked.most_pairs, w.tracked.largest_reach)
            lost = jax.tree.map(lambda old, nw: jnp.where(first, nw, old), lost, seen)
        return (state, nbrs, forces, status, bad_step, bad_body, k + 1, rebuilds, lost), None

    flags_and_count = jnp.zeros((), dtype=jnp.int32)
    lost = (flags_and_count, flags_and_count, jnp.zeros((), dtype=state.x.dtype))
    forces = initial_forces(system, method, state, neighbors, *start)
    first_values = _evaluate(system, state, observers, neighbors)
    first_values.update(_thermostat_values(system, method, state, forces, neighbors))

    def chunk(carry):
        # once a step has failed, the frames left in this call keep the state of the step
        # before it: their steps are not computed (a reallocation goes on from the last frame,
        # a stop is reported at once)
        running = carry[3] == _OK
        carry = lax.cond(running, lambda c: lax.scan(one_step, c, None, length=every)[0],
                         lambda c: c, carry)
        if spec is not None:
            # a step that failed in this chunk left the list of its own discarded state (and
            # the steps after it, theirs): the state kept gets a list built for it, for this
            # frame's observables and the list the run returns
            failed_here = running & (carry[3] != _OK)
            carry = (carry[0], lax.cond(failed_here, lambda: list_for_kept_state(spec, carry[0]),
                                        lambda: carry[1]), *carry[2:])
        state, nbrs, carried, status, bad_step = carry[:5]
        k = carry[6]
        done = jnp.where(status == _OK, k, bad_step - 1)
        values = _evaluate(system, state, observers, nbrs)
        values.update(_thermostat_values(system, method, state, carried, nbrs))
        return carry, (state, values, done)

    init = (state, neighbors, forces, zero, zero, zero, zero, zero, lost)
    carry, (frames, values, done) = scan_chunks(
        chunk, lambda carry: (carry, (carry[0], first_values, zero)), init, n_chunks, active)
    _, last_list, _, status, bad_step, bad_body, _, rebuilds, lost = carry
    frames = jax.tree.map(lambda a, f: jnp.concatenate([a[None], f]), state, frames)
    values = jax.tree.map(lambda a, f: jnp.concatenate([a[None], f]), first_values, values)
    done = jnp.concatenate([zero[None], done])
    return frames, values, done, status, bad_step, bad_body, last_list, rebuilds, lost


def list_for_kept_state(spec, state, cell=None):
    """The list a failed step's chunk gives the state it keeps (the step's own list is for its
    discarded state): built for it, with the run's capacities (``run`` reallocates it where
    they are too small); ``cell``: the kept cell of a box that a barostat deforms."""
    return nb.build(spec, state.x, state.phi, cell)


def kept_list_or_refit(spec, failed, state, nbrs, lost, cell=None):
    """For loops that keep back the state, not the list, of a step they discard (keeping the
    list cost two copies of it per step): where ``failed`` (traced), the list of
    :func:`list_for_kept_state` in place of ``nbrs`` (the discarded step's), and ``refit``,
    whether it overflows the capacities, with ``lost`` (overflow flags, most pairs, largest
    reach) grown to hold it: the run or sample is then repeated with room, as after an
    overflow in a step. Else ``nbrs``, False and ``lost`` as given. Returns (list, refit,
    lost)."""
    nbrs = lax.cond(failed, lambda: list_for_kept_state(spec, state, cell), lambda: nbrs)
    refit = failed & (nbrs.overflow != 0)
    lost = (lost[0] | jnp.where(refit, nbrs.overflow, 0),
            jnp.maximum(lost[1], jnp.where(refit, nbrs.count, 0)),
            jnp.maximum(lost[2], jnp.where(refit, nbrs.reach, 0.0)))
    return nbrs, refit, lost


def scan_chunks(chunk, skipped, init, n_chunks: int, active=None):
    """``lax.scan`` of ``chunk`` (carry -> (carry, frame)) over ``n_chunks`` chunks of a run;
    with ``active`` (traced) only the first ``active`` run, the others are ``skipped`` (carry
    -> (carry, a filler frame of the same shapes), which the caller drops): a run that goes on
    after a reallocation of its list thus keeps the compiled length of the run."""
    if active is None:
        return lax.scan(lambda carry, _: chunk(carry), init, None, length=n_chunks)
    return lax.scan(lambda carry, c: lax.cond(c < active, chunk, skipped, carry), init,
                    jnp.arange(n_chunks))


_simulate_jit = jax.jit(
    _simulate, static_argnames=("n_chunks", "every", "method", "observers", "spec"))


def _compiled_call(system, state, dt, neighbors, start, active, **static):
    if is_array_pytree(system):
        return _simulate_jit(system, state, dt, neighbors, start, active, **static)
    # models that are not pytrees: close over them (compiles per call)
    return jax.jit(partial(_simulate, system, **static))(state, dt, neighbors, start, active)


# --------------------------------------------------------------------------------------------
# neighbour lists


def _initial_neighbors(system, method, state, neighbors, neighbor_skin):
    """(spec, list) valid for ``state``, or (None, None) for all pairs (see ``run``)."""
    if neighbors is None and neighbor_skin is None:
        return None, None
    if neighbors is not None and neighbor_skin is not None:
        raise ValueError("give run(...) either neighbors=(spec, list) or neighbor_skin, not both")
    if not method.uses_neighbor_lists:
        raise ValueError(
            f"integrator {getattr(method, 'name', method)!r} sums over all pairs: neighbour lists "
            f"work with the splitting integrators (strang, yoshida4, suzuki4, yoshida6); run "
            f"without neighbors or neighbor_skin"
        )
    space, cutoff, variable = system.neighbor_range()
    if neighbors is None:
        skin = float(neighbor_skin)
        if not (np.isfinite(skin) and skin >= 0):
            raise ValueError(f"neighbor_skin must be a finite number >= 0 (got {neighbor_skin})")
        return nb.allocate(space, state.x, state.phi, cutoff, variable, skin)
    try:
        spec, lst = neighbors
    except (TypeError, ValueError):
        raise ValueError("neighbors must be the (spec, list) pair of neighbors.allocate "
                         f"(got {type(neighbors).__name__})") from None
    if not isinstance(spec, nb.NeighborSpec) or not isinstance(lst, nb.NeighborList):
        raise ValueError("neighbors must be the (spec, list) pair of neighbors.allocate")
    if (spec.space != space or spec.variable != variable or spec.cutoff < cutoff
            or spec.bodies != state.x.shape[0]):
        raise ValueError(
            f"the neighbour list does not fit the system: it covers a cut-off {spec.cutoff} on "
            f"{spec.variable} for {spec.bodies} bodies in {spec.space}, the potential needs "
            f"{cutoff} on {variable} for {state.x.shape[0]} bodies in {space}: allocate it with "
            f"neighbors.allocate(space, x, phi, {cutoff}, {variable!r}, skin)"
        )
    if bool(nb.needs_rebuild(spec, lst, state.x, state.phi)):
        lst = nb.build_jit(spec, state.x, state.phi)
    if int(lst.overflow):
        return nb.allocate(space, state.x, state.phi, cutoff, variable, spec.skin)
    return spec, lst


#: What a run whose list cannot be reallocated is told to do (``run``, ``barostat.run``).
OVERFLOW_FIX = "run without a neighbour list or with a larger box"


class ListRestarts:
    """The one overflow policy of a run's compiled calls (:func:`run` and
    ``barostat.run``): a call stops computing at the first step whose list overflowed its
    capacities; its frames up to the last one before that step are kept, the list is
    reallocated for that frame's state by :func:`neighbors.reallocate` (from what the failed
    step saw) and the run goes on from that frame, so the frames are those of a run whose
    list never overflowed. After ``neighbors.MAX_REALLOCATIONS_IN_A_ROW`` reallocations at
    the same frame, or one that cannot be built (a reach beyond half the box), the run stops
    there with every frame it has (``failure`` says why), as for any other stop.

    Each call's frames are a pytree ``part`` of arrays with the frame axis first; a restart's
    frame 0 is the frame it restarted from, already kept."""

    def __init__(self):
        self.segments = []  # (part, first, upto): frames [first, upto) of each call
        self.in_a_row = 0  # restarts at the same frame
        self.count = 0  # reallocations made
        self.failure: str | None = None  # why the run gave up its list

    def keep(self, part, upto: int | None = None) -> None:
        """Keep the frames of ``part`` before ``upto`` (default all)."""
        first = 0 if not self.segments else 1
        frames = len(jax.tree.leaves(part)[0])
        self.segments.append((part, first, frames if upto is None else upto))

    def restart(self, part, aligned: int, state: State, spec, lost, *, cell=None,
                at_step: int, bad_step: int):
        """After a call (``part``) whose list (``spec``) overflowed at ``bad_step``: keep its
        frames up to ``aligned``, the last one before that step (at global step ``at_step``,
        holding ``state``), and return a (spec, list) reallocated for ``state`` from what
        the failed step saw (``lost`` = overflow flags, largest pair count, largest reach);
        ``cell``: the cell of a box that moves (its new cells get more room at each restart
        in a row). None when the run must stop: then every frame of ``part`` is kept."""
        self.in_a_row = self.in_a_row + 1 if aligned == 0 else 1
        try:
            if self.in_a_row > nb.MAX_REALLOCATIONS_IN_A_ROW:
                raise nb.NeighborListOverflow(
                    f"{self.in_a_row - 1} reallocations at step {at_step} did not get past "
                    f"step {bad_step}")
            lists = nb.reallocate(spec, state.x, state.phi, flags=int(lost[0]),
                                  pairs=int(lost[1]), reach=float(lost[2]), cell=cell,
                                  box_headroom=nb.BOX_HEADROOM * 2 ** (self.in_a_row - 1))
        except ValueError as error:  # NeighborListOverflow, or a reach beyond half the box
            self.failure = str(error)
            self.keep(part)
            return None
        self.keep(part, aligned + 1)
        self.count += 1
        return lists

    def joined(self):
        """The kept frames of every call, as one ``part``."""
        bounds = [(first, upto) for _, first, upto in self.segments]
        return jax.tree.map(lambda *parts: np.concatenate(
            [p[first:upto] for p, (first, upto) in zip(parts, bounds, strict=True)]),
            *[part for part, _, _ in self.segments])


def _diagnose_non_finite(system, method, initial, state, dt, spec=None) -> str:
    """Reason for a blow-up, judged from the last finite state (a heuristic).

    A symplectic step that is stable keeps the energy near its initial value: if the energy
    had already run away, or if ten steps of dt/10 from the last finite state stay finite, the
    step was too large for the stiffness met; otherwise the potential is singular there.
    With a neighbour list (``spec``) energies and steps use lists built for the states.
    """
    if spec is None:
        energy = jax.jit(system.hamiltonian)
        finer = jax.jit(lambda s: jax.lax.fori_loop(
            0, 10, lambda _, z: method.step(system, z, dt / 10), s))
    else:
        def energy(s):
            _, lst = _initial_neighbors(system, method, s, None, spec.skin)
            return jax.jit(system.hamiltonian)(s, lst)

        def finer(s):
            fresh, lst = _initial_neighbors(system, method, s, None, spec.skin)

            def tenth(_, carry):
                z, tracked = method.step_with_neighbors(system, carry[0], dt / 10, fresh,
                                                        carry[1])
                return z, tracked.neighbors

            return jax.jit(lambda z, l0: jax.lax.fori_loop(0, 10, tenth, (z, l0))[0])(s, lst)
    e0, e1 = float(energy(initial)), float(energy(state))
    error = abs(e1 - e0) / max(abs(e0), 1e-300)
    if not np.isfinite(error) or error > 0.5:
        return (f"time step too large: the relative energy error had grown to {error:.3g} "
                f"before the blow-up (unstable for the stiffness of the potential); reduce dt")
    if bool(jnp.all(_per_body_finite(finer(state)))):
        return ("time step too large: the same interval in ten steps of dt/10 stays finite; "
                "reduce dt")
    return ("potential too stiff or singular: the motion stays non-finite with dt/10 "
            "(check the potential and the initial data, e.g. det phi -> 0 or coinciding bodies)")


def run(system: HamiltonianSystem, state: State, dt: float, steps: int, integrator="strang",
        every: int = 1, observers=("energy",), on_stop: str = "raise", neighbors=None,
        neighbor_skin: float | None = None, thermostat=None, first_step: int = 0,
        heat: float = 0.0) -> Trajectory:
    """Integrate ``steps`` steps of size ``dt``, recording a frame every ``every`` steps.

    observers: names from NAMED_OBSERVABLES, or a mapping name -> (name or function(state)).
    integrator: a name from ``integrators.INTEGRATORS`` or an integrator object.
    on_stop: "raise" (IntegrationStopped) or "return" (trajectory with ``.stop``).
    neighbors: None (pair terms sum over all pairs) or the (spec, list) pair of
    ``neighbors.allocate`` for the pair cut-off (``system.neighbor_range()``); e.g. the
    ``trajectory.neighbors`` of a previous run, which then compiles nothing new.
    neighbor_skin: instead of ``neighbors``, allocate a list with this skin for ``state``.

    With a list (splitting integrators only) the pair forces are summed over it, and it is
    updated after every drift inside the compiled loop (rebuilt when the bodies moved or
    stretched more than the skin allows). A step whose list overflowed its capacities is
    discarded; the run reallocates the list at the last recorded frame and goes on from there,
    so the frames are those of an all-pairs run (to round-off). ``trajectory`` reports
    ``neighbor_rebuilds`` and ``neighbor_reallocations``.

    thermostat: None (NVE) or a ``thermostats.Langevin`` / ``thermostats.Bussi``, composed
    into the splitting integrator (``integrators.Thermostatted``); the observables then also
    hold ``heat`` and ``effective_energy`` per frame. first_step: the global index of the
    step ``state`` is at (the noise of step k comes from fold_in(PRNGKey(seed), k), so a
    resumed run repeats an uninterrupted one); heat: the heat exchanged before it.
    """
    dt = float(dt)
    if not np.isfinite(dt) or dt == 0.0:
        raise ValueError(f"dt must be a finite non-zero number (got {dt})")
    if int(steps) != steps or steps < 1:
        raise ValueError(f"steps must be a positive integer (got {steps})")
    if int(every) != every or every < 1 or steps % every:
        raise ValueError(f"every must be a positive divisor of steps={steps} (got {every})")
    if on_stop not in ("raise", "return"):
        raise ValueError(f"on_stop must be 'raise' or 'return' (got {on_stop!r})")
    method = get_integrator(integrator)
    method.check(system)  # a one-line ValueError before any work
    if thermostat is not None:
        method = _thermostatted(system, method, thermostat, state)
    state = system.check(state)
    if state.phi.ndim == 3 and state.phi.shape[0] == 0:  # failed inside NumPy (an argmax)
        raise ValueError("run needs at least one body (the state has N = 0)")
    if state.phi.ndim != 3:
        raise ValueError(f"run integrates one system: state.phi must be [N, n, n] "
                         f"(got {tuple(state.phi.shape)}); vmap for ensembles")
    items = _observer_items(observers)
    spec, nbrs = _initial_neighbors(system, method, state, neighbors, neighbor_skin)
    every, n_chunks = int(every), int(steps) // int(every)
    restarts = ListRestarts()  # the frames of each compiled call, numpy
    start, start_state = 0, state  # start: the chunk the segment starts at
    start_heat = float(heat)
    rebuilds = 0
    while True:
        frames, values, done, status, bad_step, bad_body, last_list, more, lost = _compiled_call(
            system, start_state, jnp.asarray(dt), nbrs,
            (jnp.asarray(int(first_step) + start * every, dtype=jnp.int64),
             jnp.asarray(start_heat)), jnp.asarray(n_chunks - start, dtype=jnp.int32),
            n_chunks=n_chunks, every=every, method=method, observers=items, spec=spec)
        frames, values, done = jax.tree.map(  # the frames of the chunks that ran
            lambda a, ran=n_chunks - start + 1: np.asarray(a)[:ran], (frames, values, done))
        part = (frames, values, done + start * every)
        status, bad_step, bad_body = int(status), int(bad_step) + start * every, int(bad_body)
        rebuilds += int(more)
        if status != _OVERFLOW:
            restarts.keep(part)
            break
        nominal = (start + np.arange(len(part[2]))) * every
        aligned = int(np.argmin(part[2] == nominal)) - 1  # the last frame before the stop
        restart_state = jax.tree.map(lambda a, j=aligned: a[j], part[0])
        lists = restarts.restart(part, aligned, restart_state, spec, lost,
                                 at_step=(start + aligned) * every, bad_step=bad_step)
        if lists is None:
            break
        spec, nbrs = lists
        start, start_state = start + aligned, restart_state
        if "heat" in part[1]:
            start_heat = float(part[1]["heat"][aligned])
    frames, values, done = restarts.joined()
    keep = slice(None)
    report = None
    if status != _OK:
        step, body = bad_step, bad_body
        # frames up to and including the first one that holds the last good state
        last = int(np.argmax(done == step - 1)) if np.any(done == step - 1) else len(done) - 1
        keep = slice(0, last + 1)
        if spec is not None and status != _OVERFLOW and int(last_list.overflow):
            # the list the loop built for the state kept (frame `last`) did not fit the
            # capacities: that frame's observables again with one that does, returned too
            kept = jax.tree.map(lambda a: a[last], frames)
            spec, last_list = nb.allocate(spec.space, kept.x, kept.phi, spec.cutoff,
                                          spec.variable, spec.skin)
            _recompute_frame(system, items, values, last, kept, last_list)
        t0, t1 = (step - 1) * dt, step * dt
        if status == _LEFT_GROUP:
            reason = "left the group"
            message = (
                f"body {body} left {system.group}(n): det phi crossed 0 at step {step} "
                f"(t between {t0:.6g} and {t1:.6g}); use group = \"L\" to allow singular "
                f"configurations or reduce dt"
            )
        elif status == _OVERFLOW:
            reason, body = "neighbour list overflow", -1
            message = (f"the neighbour list overflowed at step {step} (t between {t0:.6g} and "
                       f"{t1:.6g}) and could not be reallocated: {restarts.failure}; "
                       f"{OVERFLOW_FIX}")
        else:
            # the state freezes at the last good one, so frame `last` holds it exactly
            good = jax.tree.map(lambda a: a[last], frames)
            reason = _diagnose_non_finite(system, method, state, good, dt, spec)
            message = (f"non-finite state of body {body} at step {step} "
                       f"(t between {t0:.6g} and {t1:.6g}): {reason}")
        report = StopReport(step=step, time=t1, body=body, reason=reason, message=message)
    trajectory = Trajectory(
        times=done[keep] * dt,
        states=jax.tree.map(lambda a: a[keep], frames),
        observables={k: v[keep] for k, v in values.items()},
        stop=report,
        neighbors=None if spec is None else (spec, last_list),
        neighbor_rebuilds=rebuilds,
        neighbor_reallocations=restarts.count,
    )
    if report is not None and on_stop == "raise":
        raise IntegrationStopped(report, trajectory)
    return trajectory


def _thermostatted(system, method, thermostat, state):
    """``method`` with ``thermostat`` composed in (``integrators.Thermostatted``), or a
    one-line ValueError: thermostats need a positive definite T."""
    from affinebody.integrators import Thermostatted

    th.check(system, thermostat, np.shape(state.phi)[-1])
    return Thermostatted(method, thermostat)


def relative_error(values, reference) -> np.ndarray:
    """|E - E_0| / max(|E_0|, tiny): the relative energy error every report uses (run's
    progress bar and summary, sweep samples, ``energy_error``). Broadcasts."""
    values, reference = np.asarray(values, dtype=float), np.asarray(reference, dtype=float)
    return np.abs(values - reference) / np.maximum(np.abs(reference), np.finfo(float).tiny)


def energy_error(trajectory: Trajectory, key: str = "energy") -> np.ndarray:
    """:func:`relative_error` of a trajectory's energy observable against its first frame."""
    e = np.asarray(trajectory.observables[key])
    return relative_error(e, e[0])


__all__: Sequence[str] = (
    "IntegrationStopped", "ListRestarts", "NAMED_OBSERVABLES", "OVERFLOW_FIX", "Stop",
    "StopReport", "Trajectory", "Watched",
    "energy_error", "initial_forces", "kept_list_or_refit", "list_for_kept_state",
    "relative_error", "run",
    "scan_chunks", "watched_step",
)
