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

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from affinebody import observables as obs
from affinebody.integrators import get_integrator
from affinebody.state import State
from affinebody.system import OPEN_GROUPS, HamiltonianSystem

#: Observables available by name in ``run(..., observers=...)``; each maps (system, state).
NAMED_OBSERVABLES: Mapping[str, Callable[[HamiltonianSystem, State], jax.Array]] = {
    "energy": lambda system, s: system.hamiltonian(s),
    "kinetic_energy": lambda system, s: system.kinetic_energy(s),
    "potential_energy": lambda system, s: system.potential_energy(s),
    "linear_momentum": lambda system, s: obs.linear_momentum(s),
    "affine_spin": lambda system, s: obs.affine_spin(s),
    "comoving_affine_spin": lambda system, s: obs.comoving_affine_spin(s),
    "affine_momentum": lambda system, s: obs.affine_momentum(s),
    "angular_momentum": lambda system, s: obs.angular_momentum(s),
    "vorticity": lambda system, s: obs.vorticity(s),
    "volumes": lambda system, s: obs.volumes(s),
    "relative_volumes": lambda system, s: obs.relative_volumes(s),
}

_OK, _LEFT_GROUP, _NON_FINITE = 0, 1, 2


@dataclass(frozen=True)
class StopReport:
    """Why and where a run stopped: ``step`` (1-based) failed, the state of step-1 is kept."""

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


def _evaluate(system, state, items):
    return {name: (NAMED_OBSERVABLES[spec](system, state) if isinstance(spec, str) else spec(state))
            for name, spec in items}


def _per_body_finite(state: State) -> jax.Array:
    return (jnp.all(jnp.isfinite(state.x), axis=-1) & jnp.all(jnp.isfinite(state.p), axis=-1)
            & jnp.all(jnp.isfinite(state.phi), axis=(-2, -1))
            & jnp.all(jnp.isfinite(state.pi), axis=(-2, -1)))


def _simulate(system, state, dt, *, n_chunks, every, method, observers):
    watch_det = system.group in OPEN_GROUPS
    sign0 = jnp.sign(jnp.linalg.det(state.phi))

    def one_step(carry, _):
        state, status, bad_step, bad_body, k = carry
        new = method.step(system, state, dt)
        finite = _per_body_finite(new)
        crossed = (jnp.sign(jnp.linalg.det(new.phi)) != sign0) & finite & watch_det
        bad_bodies = ~finite | crossed
        first = (status == _OK) & jnp.any(bad_bodies)
        code = jnp.where(jnp.any(~finite), _NON_FINITE, _LEFT_GROUP)
        status = jnp.where(first, code, status)
        bad_step = jnp.where(first, k + 1, bad_step)
        bad_body = jnp.where(first, jnp.argmax(bad_bodies), bad_body)
        keep_old = status != _OK
        state = jax.tree.map(lambda old, nw: jnp.where(keep_old, old, nw), state, new)
        return (state, status, bad_step, bad_body, k + 1), None

    def chunk(carry, _):
        carry, _ = lax.scan(one_step, carry, None, length=every)
        state, status, bad_step, _, k = carry
        done = jnp.where(status == _OK, k, bad_step - 1)
        return carry, (state, _evaluate(system, state, observers), done)

    zero = jnp.asarray(0)
    init = (state, zero, zero, zero, zero)
    carry, (frames, values, done) = lax.scan(chunk, init, None, length=n_chunks)
    _, status, bad_step, bad_body, _ = carry
    first_values = _evaluate(system, state, observers)
    frames = jax.tree.map(lambda a, f: jnp.concatenate([a[None], f]), state, frames)
    values = jax.tree.map(lambda a, f: jnp.concatenate([a[None], f]), first_values, values)
    done = jnp.concatenate([zero[None], done])
    return frames, values, done, status, bad_step, bad_body


_simulate_jit = jax.jit(_simulate, static_argnames=("n_chunks", "every", "method", "observers"))


def _is_array_pytree(obj) -> bool:
    try:
        hash(jax.tree.structure(obj))
    except TypeError:
        return False
    return all(isinstance(leaf, jax.Array | np.ndarray | np.generic | float | int)
               for leaf in jax.tree.leaves(obj))


def _compiled_call(system, state, dt, **static):
    if _is_array_pytree(system):
        return _simulate_jit(system, state, dt, **static)
    # models that are not pytrees: close over them (compiles per call)
    return jax.jit(partial(_simulate, system, **static))(state, dt)


def _diagnose_non_finite(system, method, initial, state, dt) -> str:
    """Reason for a blow-up, judged from the last finite state (a heuristic).

    A symplectic step that is stable keeps the energy near its initial value: if the energy
    had already run away, or if ten steps of dt/10 from the last finite state stay finite, the
    step was too large for the stiffness met; otherwise the potential is singular there.
    """
    energy = jax.jit(system.hamiltonian)
    e0, e1 = float(energy(initial)), float(energy(state))
    error = abs(e1 - e0) / max(abs(e0), 1e-300)
    if not np.isfinite(error) or error > 0.5:
        return (f"time step too large: the relative energy error had grown to {error:.3g} "
                f"before the blow-up (unstable for the stiffness of the potential); reduce dt")
    finer = jax.jit(lambda s: jax.lax.fori_loop(
        0, 10, lambda _, z: method.step(system, z, dt / 10), s))(state)
    if bool(jnp.all(_per_body_finite(finer))):
        return ("time step too large: the same interval in ten steps of dt/10 stays finite; "
                "reduce dt")
    return ("potential too stiff or singular: the motion stays non-finite with dt/10 "
            "(check the potential and the initial data, e.g. det phi -> 0 or coinciding bodies)")


def run(system: HamiltonianSystem, state: State, dt: float, steps: int, integrator="strang",
        every: int = 1, observers=("energy",), on_stop: str = "raise") -> Trajectory:
    """Integrate ``steps`` steps of size ``dt``, recording a frame every ``every`` steps.

    observers: names from NAMED_OBSERVABLES, or a mapping name -> (name or function(state)).
    integrator: a name from ``integrators.INTEGRATORS`` or an integrator object.
    on_stop: "raise" (IntegrationStopped) or "return" (trajectory with ``.stop``).
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
    if system.constrained and not hasattr(method, "weights"):
        method.step(system, state, dt)  # raises the integrator's own ValueError
    state = system.check(state)
    if state.phi.ndim != 3:
        raise ValueError(f"run integrates one system: state.phi must be [N, n, n] "
                         f"(got {tuple(state.phi.shape)}); vmap for ensembles")
    items = _observer_items(observers)
    frames, values, done, status, bad_step, bad_body = _compiled_call(
        system, state, jnp.asarray(dt), n_chunks=int(steps) // int(every), every=int(every),
        method=method, observers=items)
    done = np.asarray(done)
    status = int(status)
    keep = slice(None)
    report = None
    if status != _OK:
        step, body = int(bad_step), int(bad_body)
        # frames up to and including the first one that holds the last good state
        last = int(np.argmax(done == step - 1)) if np.any(done == step - 1) else len(done) - 1
        keep = slice(0, last + 1)
        t0, t1 = (step - 1) * dt, step * dt
        if status == _LEFT_GROUP:
            reason = "left the group"
            message = (
                f"body {body} left {system.group}(n): det phi crossed 0 at step {step} "
                f"(t between {t0:.6g} and {t1:.6g}); use group = \"L\" to allow singular "
                f"configurations or reduce dt"
            )
        else:
            # the state freezes at the last good one, so frame `last` holds it exactly
            good = jax.tree.map(lambda a: a[last], frames)
            reason = _diagnose_non_finite(system, method, state, good, dt)
            message = (f"non-finite state of body {body} at step {step} "
                       f"(t between {t0:.6g} and {t1:.6g}): {reason}")
        report = StopReport(step=step, time=t1, body=body, reason=reason, message=message)
    trajectory = Trajectory(
        times=done[keep] * dt,
        states=jax.tree.map(lambda a: np.asarray(a)[keep], frames),
        observables={k: np.asarray(v)[keep] for k, v in values.items()},
        stop=report,
    )
    if report is not None and on_stop == "raise":
        raise IntegrationStopped(report, trajectory)
    return trajectory


def energy_error(trajectory: Trajectory, key: str = "energy") -> np.ndarray:
    """|E(t) - E(0)| / max(|E(0)|, tiny) for a trajectory recorded with an energy observer."""
    e = np.asarray(trajectory.observables[key])
    return np.abs(e - e[0]) / max(abs(float(e[0])), np.finfo(float).tiny)


__all__: Sequence[str] = (
    "IntegrationStopped", "NAMED_OBSERVABLES", "StopReport", "Trajectory", "energy_error", "run",
)
