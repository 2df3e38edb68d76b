"""Stochastic cell rescaling (Bernetti and Bussi 2020): a barostat for periodic systems of affine
bodies, isotropic or anisotropic, and the NPT run driver (docs/pressure.md).

The box is the cell matrix H (columns: lattice vectors), carried as an array beside the state
(``HamiltonianSystem.cell``): the pair terms' own box is only its reference. A barostat move
deforms the box by a matrix mu close to Id and moves the centres and their momenta with it,

    H -> mu H,   x_K -> mu x_K,   p_K -> mu^-T p_K,   phi_K, pi_K unchanged

(a canonical point transformation of the centres, fixed shapes: the convention of the pressure
tensor, :mod:`affinebody.pressure`).

Isotropic coupling: with eps = ln V, P the instantaneous scalar pressure (Tr P / n, kinetic part
included) and P0 the target (Tr P0 / n), one Euler-Maruyama step of

    d eps = (beta_T / tau) (P - P0) dt + sqrt(2 kT beta_T / (V tau)) dW,   mu = exp(d eps / n) Id.

Its stationary law is exp(-(H + P0 V)/kT) with the Lebesgue measure dV (Ito calculus: the
drift of the V-dependent noise cancels the Jacobian of eps = ln V; docs/pressure.md), so an
ideal gas has <V> = (N + 1) kT / P0.

Anisotropic coupling: the n(n+1)/2 entries of an upper-triangular cell (h_ab, a <= b) move,
or only the n edges of an orthorhombic box (which then stays orthorhombic), with the same
target exp(-(H + P0 V)/kT) dh (Lebesgue in those entries): in the strain coordinates
delta = dh H^-1,

    d delta_ab = (beta_T / tau) (P - P0)_ba dt + (Ito drift) + sqrt(2 kT beta_T / (V tau)) dW_ab,

where the Ito drift div(M) of the mobility M = (kT beta_T / (V tau)) J J^T (J: delta -> delta H)
makes the target stationary; it is computed by automatic differentiation of M (at most 6 x 6).
A non-hydrostatic P0 drives the mean stress to P0; the ensemble is exact for a hydrostatic P0.

Moves every few steps: with ``interval`` = m > 1 the box moves only after the steps k
(counted from the start of the run) with (k + 1) % m == 0, by one Euler-Maruyama step of
length m dt: the same equations in the same physical time, their discretisation coarser (as
GROMACS's nstpcouple). The steps in between are constant-volume steps that reuse the last
kick's forces, so an NPT step costs little more than an NVT one when m is about 10; the
barostat's relaxation time tau should stay many times m dt.

Metropolis test: with ``metropolis`` each move is a proposal, accepted with probability
min(1, exp(-work/kT) J q(reverse)/q(forward)) (Metropolis-adjusted Langevin for the cell):
work the change of H + P0 V the move makes (the map (x, p, H) -> (mu x, mu^-T p, mu H) keeps
the phase-space volume of (x, p)), J = V'/V for the isotropic move in eps = ln V (1 in the
cell entries of the anisotropic one), q the Gaussian densities of :meth:`log_proposal`, the
reverse move mu^-1 drawn at the moved state. The target is then stationary at any move
length; a rejected move changes nothing (docs/pressure.md, "The barostat: stochastic cell
rescaling").

Random numbers: the noise of step k (counted from the start of the run, resumed runs
included) comes from :func:`step_key` (``fold_in`` of the seed, of the barostat's own stream
:data:`STREAM` and of k), so a run resumed from its checkpoint repeats the uninterrupted one
bit for bit, and a thermostat drawing from the same seed gets independent numbers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from affinebody import _linalg as linalg
from affinebody import _pytree as pytree
from affinebody import neighbors as nb
from affinebody import pressure as pressure_module
from affinebody.integrators import get_integrator
from affinebody.integrators.splitting import update_neighbors
from affinebody.simulate import OVERFLOW_FIX, ListRestarts, kept_list_or_refit, scan_chunks
from affinebody.space import Space, as_space
from affinebody.state import State

#: The couplings of the box to the pressure (``[barostat] coupling``).
COUPLINGS = ("isotropic", "anisotropic")


def _target(value, n: int) -> tuple[tuple[float, ...], ...]:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim == 0:
        array = float(array) * np.eye(n)
    if array.shape != (n, n) or not np.all(np.isfinite(array)):
        raise ValueError(f"barostat.pressure must be a finite number or an {n} x {n} tensor "
                         f"(got {value!r})")
    return tuple(map(tuple, array))


@pytree.dataclass(static=True)
class StochasticCellRescaling:
    """c-rescale barostat (module docstring): target ``pressure`` P0 ([n, n]; a scalar means
    P0 Id), time constant ``tau``, isothermal ``compressibility`` beta_T (only sets the
    relaxation time, not the sampled distribution), temperature kT of the noise, ``coupling``
    "isotropic" or "anisotropic"; ``interval``: steps between two moves, each of length
    ``interval`` dt (GROMACS's nstpcouple; module docstring, "Moves every few steps");
    ``metropolis``: accept or reject each move by a Metropolis-Hastings test, which makes the
    sampled ensemble exact at any move length (module docstring, "Metropolis test")."""

    pressure: tuple[tuple[float, ...], ...]
    tau: float
    compressibility: float
    temperature: float
    coupling: str = "isotropic"
    interval: int = 1
    metropolis: bool = False

    def __post_init__(self):
        for name in ("tau", "compressibility", "temperature"):
            value = getattr(self, name)
            if isinstance(value, jax.core.Tracer):  # traced in an ensemble (sweep samples)
                continue
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"barostat.{name} must be > 0 (got {value})")
        if self.coupling not in COUPLINGS:
            raise ValueError(f"barostat.coupling must be one of {', '.join(COUPLINGS)} "
                             f"(got {self.coupling!r})")
        if isinstance(self.interval, bool) or int(self.interval) != self.interval \
                or self.interval < 1:
            raise ValueError(f"barostat.interval must be a positive whole number of steps "
                             f"(got {self.interval!r})")
        if not isinstance(self.metropolis, bool):
            raise ValueError(f"barostat.metropolis must be true or false "
                             f"(got {self.metropolis!r})")

    @property
    def target(self) -> np.ndarray:
        return np.asarray(self.pressure)

    def moves(self, first_step: int, last_step: int):
        """How many moves the steps first_step, ..., last_step - 1 make (one after each step k
        with (k + 1) % interval == 0; module docstring, "Moves every few steps")."""
        return last_step // self.interval - first_step // self.interval

    def propose(self, system, state: State, cell, space: Space, key, dt, neighbors=None,
                measured=None):
        """One move of length ``dt`` from ``state`` in ``cell`` (module docstring):
        (moved state, new cell, V before, log q), V the potential energy of ``state`` in
        ``cell`` (from the pass that computes the virial) and log q the log density of drawing
        this move (:meth:`log_proposal`), for the Metropolis test of :meth:`log_acceptance`.
        ``neighbors``: None (the virial over all pairs) or a list valid for ``state`` in
        ``cell``; ``measured``: None, or (V, W) of ``state`` in ``cell`` already known
        (``pressure.energy_forces_virial`` in the step's last force evaluation): then no pass
        over the pairs here."""
        n = cell.shape[-1]
        potential, p_inst = pressure_module.pressure_tensor(
            system.replace(cell=cell), state, space, neighbors, energy=True, measured=measured)
        drift, scale = self._drift(cell, p_inst, space, dt)
        if self.coupling == "isotropic":
            z = jax.random.normal(key)
            mu = jnp.exp((drift + scale * z) / n) * jnp.eye(n)
        else:
            mask = self._moving(space)
            z = jax.random.normal(key, (n, n))[np.nonzero(mask)]
            mu = jnp.eye(n) + drift + scale * (jnp.zeros((n, n)).at[np.nonzero(mask)].set(z))
        new_cell = mu @ cell
        mu_inv_t = linalg.inv(mu).T
        state = state._replace(x=state.x @ mu.T, p=state.p @ mu_inv_t.T)
        return state, new_cell, potential, self._log_density(z, scale, cell, space)

    def move_size(self, cell, p_inst, space: Space, dt: float) -> tuple[float, float]:
        """(drift, noise) of the next move from ``cell`` at the instantaneous pressure
        ``p_inst`` with steps of ``dt``: the mean change of ln V, beta_T / tau (P - P0)
        interval dt with P = Tr p_inst / n, and its standard deviation, sqrt(2 kT beta_T
        interval dt / (tau V)) (module docstring); anisotropic: of the strain's entries,
        the largest mean in magnitude."""
        drift, noise = self._drift(jnp.asarray(cell), jnp.asarray(p_inst), space,
                                   self.interval * dt)
        drift = jnp.ravel(drift)
        return float(drift[jnp.argmax(jnp.abs(drift))]), float(noise)

    def _drift(self, cell, p_inst, space: Space, dt):
        """(mean, standard deviation) of a move of length ``dt`` from ``cell`` at the
        instantaneous pressure ``p_inst``: of d eps (isotropic) or of the strain d delta
        [n, n] (anisotropic, the Ito drift included; the deviation of each moving entry)."""
        n = cell.shape[-1]
        rate = self.compressibility / self.tau
        diffusion = self.temperature * rate / linalg.det(cell)
        scale = jnp.sqrt(2.0 * diffusion * dt)
        if self.coupling == "isotropic":
            return rate * (jnp.trace(p_inst) - jnp.trace(jnp.asarray(self.pressure))) / n * dt, \
                scale
        mask = self._moving(space)
        stress = rate * (p_inst - jnp.asarray(self.pressure)).T
        return mask * stress * dt + self._ito_drift(cell, mask) * dt, scale

    def _log_density(self, z, scale, cell, space: Space):
        """log density of a move from ``cell`` whose standard normal draws are ``z`` (one per
        moving entry; :meth:`log_proposal`): the Gaussian's in d eps or in the strain,
        turned into a density in the cell's moving entries by the Jacobian of
        delta -> delta H, the product of h_bb over the moving entries (a, b)."""
        z = jnp.atleast_1d(z)
        jacobian = 0.0
        if self.coupling != "isotropic":
            cols = np.nonzero(self._moving(space))[1]
            jacobian = jnp.sum(jnp.log(jnp.abs(jnp.diagonal(cell)[cols])))
        return (-0.5 * jnp.sum(z * z) - z.size * (jnp.log(scale) + 0.5 * np.log(2 * np.pi))
                - jacobian)

    def log_proposal(self, cell, p_inst, mu, space: Space, dt):
        """log of the density of the move H -> mu H from ``cell`` at the instantaneous pressure
        ``p_inst`` in the coordinates whose Lebesgue measure the target carries times
        exp(-(H + P0 V)/kT) (module docstring, "Metropolis test"): eps = ln V (isotropic), the
        moving entries of the cell (anisotropic)."""
        drift, scale = self._drift(cell, p_inst, space, dt)
        if self.coupling == "isotropic":
            z = (jnp.log(linalg.det(mu)) - drift) / scale
        else:
            z = (mu - jnp.eye(mu.shape[-1]) - drift)[np.nonzero(self._moving(space))] / scale
        return self._log_density(z, scale, cell, space)

    def log_acceptance(self, work, cell, new_cell, p_after, forward, space: Space, dt):
        """log of the Metropolis-Hastings acceptance probability (before min(0, .)) of a move
        ``cell`` -> ``new_cell`` (= mu cell) that changed H + P0 V by ``work``, drawn with log
        density ``forward`` (:meth:`propose`), ``p_after`` the instantaneous pressure after
        it: the target's ratio exp(-work/kT) (times V'/V in eps = ln V,
        isotropic) and the ratio of the reverse move's density (mu^-1 from ``new_cell``) to
        the forward one's."""
        mu = new_cell @ linalg.inv(cell)
        reverse = self.log_proposal(new_cell, p_after, linalg.inv(mu), space, dt)
        log_target = -work / self.temperature
        if self.coupling == "isotropic":
            log_target = log_target + jnp.log(linalg.det(new_cell) / linalg.det(cell))
        return log_target + reverse - forward

    @staticmethod
    def _moving(space: Space) -> np.ndarray:
        """Which strain components move: the diagonal of an orthorhombic box, the upper
        triangle of a triclinic one."""
        n = space.dimension
        return np.eye(n) if space.orthorhombic else np.triu(np.ones((n, n)))

    def _ito_drift(self, cell, mask: np.ndarray):
        """div(M) in strain coordinates (module docstring): the drift that makes
        exp(-(H + P0 V)/kT) dh stationary for the V-dependent mobility."""
        rows, cols = np.nonzero(mask)
        n = cell.shape[-1]
        scale = self.temperature * self.compressibility / self.tau

        def h_of(q):
            return jnp.zeros((n, n), dtype=cell.dtype).at[rows, cols].set(q)

        def mobility(q):
            h = h_of(q)
            jac = jax.jacfwd(lambda d: (h_of(d) @ h)[rows, cols])(jnp.zeros_like(q))
            return scale / linalg.det(h) * jac @ jac.T

        q = cell[rows, cols]
        div = jnp.einsum("ijj->i", jax.jacfwd(mobility)(q))  # sum_j dM_ij / dq_j, in h
        return h_of(div) @ linalg.inv(cell)  # as a strain increment: dh H^-1


def c_rescale(pressure, n: int, *, tau: float, compressibility: float, temperature: float,
              coupling: str = "isotropic", interval: int = 1,
              metropolis: bool = False) -> StochasticCellRescaling:
    """The barostat of a ``[barostat]`` table: ``pressure`` a number (P0 Id) or an n x n
    tensor; ValueError (one line) for a value out of range."""
    return StochasticCellRescaling(_target(pressure, n), float(tau), float(compressibility),
                                   float(temperature), coupling, interval, metropolis)


@dataclass(frozen=True)
class NPTTrajectory:
    """Frames of an NPT run: ``times`` [F], ``states``, ``cells`` [F, n, n], ``observables``
    (``pressure`` [F, n, n] and ``volume`` [F] among them)."""

    times: np.ndarray
    states: State
    cells: np.ndarray
    observables: dict
    #: the first step (1-based, counted like ``first_step``) whose state or cell was not
    #: finite or whose cell lost its positive diagonal; from there on the frames repeat the
    #: last good state (None: every step was kept)
    failed_step: int | None = None
    #: (spec, list) of the run's neighbour list, valid for the last state and cell (None: all
    #: pairs)
    neighbors: tuple | None = None
    #: why ``failed_step`` failed when it was not a non-finite state or cell
    stop_reason: str | None = None

    @property
    def final_state(self) -> State:
        return jax.tree.map(lambda a: a[-1], self.states)


def first_narrow_frame(system, cells) -> int | None:
    """The first of ``cells`` [F, n, n] whose half smallest perpendicular width is below the
    largest pair cut-off of ``system`` (the minimum image stops being exact there: the box
    shrank too far), or None."""
    from affinebody.potentials import PairTerm, terms_of

    cuts = [t.cutoff.r_cut for t in terms_of(system.potential)
            if isinstance(t, PairTerm) and t.cutoff is not None]
    if not cuts:
        return None
    if len(cells) == 0:
        return None
    with np.errstate(all="ignore"):
        reciprocal = np.linalg.norm(np.linalg.inv(np.asarray(cells)), axis=-1)
        narrow = ~(0.5 / np.max(reciprocal, axis=-1) >= max(cuts) * (1 - 1e-12))
    return int(np.argmax(narrow)) if np.any(narrow) else None


def move_modulus(system, state: State, cell, space, neighbors=None, step: float = 1e-5) -> float:
    """K = -dP/d(ln V) along the isotropic move (x -> mu x, p -> mu^-T p, H -> mu H, phi and
    pi fixed; module docstring) at ``state`` in ``cell``, P = Tr P_inst / n with its kinetic
    part: the stiffness that the drift of a move feels, so the volume relaxes at the rate
    beta_T K / tau (:func:`move_length`): the affine (instantaneous) bulk modulus of one
    configuration, (1 + 2/n) P for an ideal gas (docs/pressure.md compares it with
    kT <V> / var(V) in a crystal). Central difference in ln V (``step``); ``neighbors``: None
    (all pairs) or the (spec, list) of ``state`` in ``cell``."""
    space = as_space(space)
    state = jax.tree.map(jnp.asarray, state)
    cell = jnp.asarray(space.matrix if cell is None else cell, dtype=state.x.dtype)
    spec, lst = (None, None) if neighbors is None else neighbors
    return float(move_modulus_jit(system, state, cell, lst, space=space, spec=spec,
                                  step=step))


@partial(jax.jit, static_argnames=("space", "spec", "step"))
def move_modulus_jit(system, state: State, cell, lst, *, space: Space, spec, step: float = 1e-5):
    """:func:`move_modulus` as a traceable function of arrays (``lst`` the list of ``spec``,
    or None with ``spec`` None): what the samples of ``affinebody sweep`` compute."""
    n = space.dimension

    def scalar_pressure(eps):
        mu = jnp.exp(eps / n)
        moved = state._replace(x=state.x * mu, p=state.p / mu)
        nbrs = lst
        if spec is not None:  # rebuilt only if the scaled centres may miss a pair
            nbrs = nb.update(spec, lst, moved.x, moved.phi, mu * cell)
        p = pressure_module.pressure_tensor(system.replace(cell=mu * cell), moved, space, nbrs)
        return jnp.trace(p) / n

    return -(scalar_pressure(step) - scalar_pressure(-step)) / (2.0 * step)


def move_length(barostat: StochasticCellRescaling, modulus: float, dt: float) -> float:
    """beta_T K m dt / tau: a move's length (m = ``interval`` steps of ``dt``) in units of
    the volume's relaxation time tau / (beta_T K), K from :func:`move_modulus`. The plain
    moves' error in the volume's fluctuations grows with it (:func:`variance_factor`)."""
    return barostat.compressibility * modulus * barostat.interval * dt / barostat.tau


def variance_factor(length: float) -> float:
    """Stationary variance of Euler-Maruyama steps of length h = ``length`` (in units of the
    relaxation time) of an Ornstein-Uhlenbeck process, over the exact one: x' = (1 - h) x +
    sqrt(2 h) z has var = 2h / (1 - (1 - h)^2) = 1 / (1 - h/2); no stationary law for h >= 2
    (inf). The plain moves' var(V) for a volume that responds linearly (docs/pressure.md)."""
    return 1.0 / (1.0 - length / 2.0) if length < 2.0 else np.inf


#: The move length (:func:`move_length`) above which plain moves get a warning: var(V) about
#: variance_factor(0.25) = 1.14 times the ensemble's for a linear response.
LONG_MOVE = 0.25
#: What the warnings about long plain moves advise (``affinebody run`` and ``sweep``).
LONG_MOVE_FIX = ("set barostat.metropolis = true, or raise barostat.tau or lower "
                 "barostat.interval")


def long_move_effect(length: float, readings: str) -> str:
    """What plain moves of ``length`` (:func:`move_length`) do, in the words of the warnings
    of ``affinebody run`` and ``sweep``: they inflate var(V) by :func:`variance_factor` (a
    linear response), and with it ``readings`` (what is read off var(V)); past 2 they are
    unstable (no stationary law)."""
    if length < 2:
        return (f"the plain moves inflate the volume's fluctuations (var(V) about "
                f"{variance_factor(length):.2g}x for a linear response) and {readings}")
    return "the plain moves are unstable past 2"


def long_move_warning(barostat: StochasticCellRescaling, modulus: float, dt: float):
    """The one-line warning of a run whose plain moves are long (:data:`LONG_MOVE`), or None
    (tested moves are exact at any length; a modulus <= 0 gives no relaxation time)."""
    length = move_length(barostat, modulus, dt)
    if barostat.metropolis or not length > LONG_MOVE:
        return None
    return (f"barostat moves are about {length:.2g} of the volume's relaxation time tau / "
            f"(compressibility K), K = {modulus:.3g} the bulk modulus under a move at the "
            f"last state: {long_move_effect(length, 'the compressibility read off them')}; "
            f"{LONG_MOVE_FIX}")


#: How much a move of the box may change ln V before a stopped run's message blames the
#: barostat's parameters (:func:`stop_advice`): a move should change it by much less than 1.
LARGE_MOVE = 0.5


def stop_advice(barostat: StochasticCellRescaling, cell, p_inst, space: Space,
                dt: float) -> str | None:
    """What to change when an NPT run stopped and its next move from the last good state
    (``cell``, instantaneous pressure ``p_inst``) is large
    (:meth:`~StochasticCellRescaling.move_size` beyond :data:`LARGE_MOVE`): the parameters at
    fault with their values, or None when the moves are short (the cause is elsewhere: dt,
    the initial state)."""
    drift, noise = barostat.move_size(cell, p_inst, space, dt)
    if not (abs(drift) > LARGE_MOVE or noise > LARGE_MOVE):  # nan: no advice
        return None
    n = np.shape(cell)[-1]
    volume = float(np.linalg.det(np.asarray(cell)))
    said = []
    if abs(drift) > LARGE_MOVE:
        pressure = float(np.trace(np.asarray(p_inst))) / n
        said.append(f"{drift:+.3g} from the pressure (barostat.compressibility "
                    f"{barostat.compressibility:.3g} / tau {barostat.tau:.3g} x (P - P0) x "
                    f"interval dt, P = {pressure:.3g})")
    if noise > LARGE_MOVE:
        said.append(f"+-{noise:.3g} from the noise (sqrt(2 barostat.temperature "
                    f"{barostat.temperature:.3g} x compressibility x interval dt / (tau V)), "
                    f"V = {volume:.3g})")
    nearer = (", or start from a state whose pressure is nearer barostat.pressure"
              if abs(drift) > LARGE_MOVE else "")
    return (f"a move of the box from the last good state changes ln V by {' and '.join(said)}"
            f", where it should change it by much less than 1: lower barostat.compressibility "
            f"or raise barostat.tau (compressibility sets only the relaxation time "
            f"tau / (compressibility K), K the bulk modulus){nearer}")


#: The barostat's own random stream (folded into the seed), apart from a thermostat's.
STREAM = 0x62617273


def step_key(seed: int, step):
    """The key of step ``step`` of a run with ``seed``:
    fold_in(fold_in(PRNGKey(seed), STREAM), step)."""
    return jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), STREAM), step)


def _npt(system, state, cell, first_step, seed, dt, neighbors, exchanged, active=None, *,
         method, barostat, space, thermostat, n_chunks, every, observers, spec):
    """The compiled NPT run; with a neighbour list (``spec`` not None) the carry holds the
    list, valid for the carried state in the carried cell, and a step whose list overflowed
    is not kept (``lost``: what the reallocation must hold, as in ``simulate.run``).
    ``active``: None, or how many of the ``n_chunks`` chunks to run (traced): a run that goes
    on after a reallocation runs its remaining chunks through the program of the same
    ``n_chunks``, compiled once for the new list, not once more for its shorter length."""
    p0 = jnp.trace(jnp.asarray(barostat.pressure)) / space.dimension  # may be traced (sweep)
    if thermostat is not None and hasattr(thermostat, "prepare"):  # once, not every step
        thermostat = thermostat.prepare(system, state)

    def enthalpy(state, cell, nbrs):
        """H + P0 V in ``cell`` (P0 = Tr P0 / n)."""
        return system.replace(cell=cell).hamiltonian(state, nbrs) + p0 * linalg.det(cell)

    def measure(state, cell, nbrs, exchanged, rejections):
        boxed = system.replace(cell=cell)
        extra = () if spec is None else (nbrs,)
        values = {name: f(boxed, state, *extra) for name, f in observers}
        values["pressure"] = pressure_module.pressure_tensor(boxed, state, space, nbrs)
        values["volume"] = linalg.det(cell)
        values["heat"], values["work"] = exchanged
        values["effective_energy"] = enthalpy(state, cell, nbrs) - exchanged[0] - exchanged[1]
        if barostat.metropolis:
            values["rejected_moves"] = rejections
        return values

    carries = getattr(method, "carries_forces", False)
    interval = barostat.interval
    # a box moving every step after a list step: the virial and energy the move needs come
    # from the step's last force pass over the pairs (pressure.energy_forces_virial), not
    # from one of their own; the state is that of the pass (a thermostat after the step
    # changes momenta only)
    one_pass = carries and interval == 1 and spec is not None

    def force_pass(boxed, state, nbrs):
        energy, forces, w = pressure_module.energy_forces_virial(boxed, state, space, nbrs)
        return forces, (energy, w)

    def one_step(carry, _):
        (old_state, old_cell, old_nbrs, k, failed, overflowed, narrow, lost, exchanged,
         old_forces, rejections) = carry
        key_thermo, key_baro = jax.random.split(step_key(seed, k))
        boxed = system.replace(cell=old_cell)
        measured = None
        if not carries:
            state, tracked, forces = method.step(boxed, old_state, dt), None, old_forces
        elif one_pass:  # the move's (V, W) from the step's last force evaluation
            state, tracked, forces, measured = method.advance(
                boxed, old_state, old_forces, dt, spec, old_nbrs, force_pass=force_pass)
        else:  # the forces after the last move, carried (first same as last)
            state, tracked, forces = method.advance(boxed, old_state, old_forces, dt, spec,
                                                    old_nbrs)
        heat = jnp.zeros((), dtype=state.x.dtype)
        if thermostat is not None:  # the kinetic energy it puts in: the heat
            before = boxed.kinetic_energy(state)
            state = thermostat(boxed, state, key_thermo, dt)
            heat = boxed.kinetic_energy(state) - before

        def move(state, tracked, forces):
            nbrs = None if spec is None else tracked.neighbors
            kinetic = boxed.kinetic_energy(state)
            key_move, key_test = (jax.random.split(key_baro) if barostat.metropolis
                                  else (key_baro, None))
            moved, cell, potential, forward = barostat.propose(
                system, state, old_cell, space, key_move, interval * dt, nbrs, measured)
            before = kinetic + potential + p0 * linalg.det(old_cell)  # H + P0 V before
            moved_tracked = tracked
            if spec is not None:  # the list follows the box (rebuilt when it may miss a pair)
                moved_tracked = update_neighbors(spec, tracked, moved, cell)
                nbrs = moved_tracked.neighbors
            # the move's work: the exact change of H + P0 V it made (the list, valid for the
            # moved state in the new cell unless the step is not kept); the same pass gives
            # the forces that the next step starts with (and, to test the move, the virial)
            moved_boxed = system.replace(cell=cell)
            if barostat.metropolis and spec is not None:
                energy, moved_forces, w = pressure_module.energy_forces_virial(
                    moved_boxed, moved, space, nbrs)
            else:
                energy, moved_forces = moved_boxed.energy_and_forces(moved, nbrs)
                if barostat.metropolis:  # all pairs: the virial's own pass
                    w = pressure_module.virial(moved_boxed, moved, space)
            work = (boxed.kinetic_energy(moved) + energy + p0 * linalg.det(cell)) - before
            if not barostat.metropolis:
                return moved, cell, moved_tracked, moved_forces, work, int0
            p_after = (pressure_module.kinetic_tensor(moved_boxed, moved) + w) / linalg.det(cell)
            log_alpha = barostat.log_acceptance(work, old_cell, cell, p_after, forward, space,
                                                interval * dt)
            in_support = jnp.all(jnp.diagonal(cell) > 0) & jnp.all(jnp.isfinite(cell))
            accept = in_support & (jnp.log(jax.random.uniform(key_test)) < log_alpha)
            if spec is not None:  # a list that misses pairs cannot judge the move: kept, so
                # that the run reallocates (overflow) or stops (box too narrow) as without
                unjudged = (moved_tracked.overflow != 0) | ~nb.fits_box(spec, moved.phi, cell)
                accept |= in_support & unjudged
            pick = lambda new, old: jax.tree.map(  # noqa: E731
                lambda a, b: jnp.where(accept, a, b), new, old)
            return (pick(moved, state), pick(cell, old_cell), pick(moved_tracked, tracked),
                    pick(moved_forces, forces), jnp.where(accept, work, 0.0),
                    (~accept).astype(jnp.int32))

        def stay(state, tracked, forces):  # a constant-volume step: its last kick's forces
            return state, old_cell, tracked, forces, jnp.zeros_like(heat), int0

        if interval == 1:
            state, cell, tracked, forces, work, rejected = move(state, tracked, forces)
        else:  # a move after the steps k with (k + 1) % interval == 0 (module docstring)
            state, cell, tracked, forces, work, rejected = lax.cond(
                (k + 1) % interval == 0, move, stay, state, tracked, forces)
        # a cell whose volume overflows (edges past ~1e154 in 2D) is not finite either, nor a
        # step whose heat or work is not: the effective energy would be nan from it on
        ok = (jnp.all(jnp.diagonal(cell) > 0) & jnp.all(jnp.isfinite(cell))
              & jnp.isfinite(linalg.det(cell)) & jnp.isfinite(heat) & jnp.isfinite(work))
        for leaf in jax.tree.leaves(state):
            ok &= jnp.all(jnp.isfinite(leaf))
        nbrs = None
        if spec is not None:
            nbrs = tracked.neighbors
            fits = nb.fits_box(spec, state.phi, cell)  # else the list cannot be rebuilt
            narrow = narrow | (~fits & ok & (failed < 0))
            ok &= fits
            over = (tracked.overflow != 0) & ok & (failed < 0)
            seen = (tracked.overflow, tracked.most_pairs, tracked.largest_reach)
            lost = jax.tree.map(lambda old, new: jnp.where(over, new, old), lost, seen)
            overflowed = overflowed | over
            ok &= ~over
        failed = jnp.where((failed < 0) & ~ok, k + 1, failed)
        keep = lambda old, new: jnp.where(failed < 0, new, old)  # noqa: E731
        # the list is not kept back with the state (as in simulate.run: that cost a copy of
        # it per step): a chunk in which a step failed gives the kept state a list after it
        state, cell = jax.tree.map(keep, old_state, state), keep(old_cell, cell)
        exchanged = jax.tree.map(keep, exchanged, (exchanged[0] + heat, exchanged[1] + work))
        carried = jax.tree.map(keep, old_forces, forces)
        rejections = keep(rejections, rejections + rejected)
        return (state, cell, nbrs, k + 1, failed, overflowed, narrow, lost, exchanged,
                carried, rejections), None

    int0 = jnp.zeros((), dtype=jnp.int32)
    first = measure(state, cell, neighbors, exchanged, int0)

    def chunk(carry):  # the rejected moves are counted from frame to frame
        # after a failed step the frames left keep its previous state: not computed (as
        # simulate._simulate)
        running = carry[4] < 0
        carry = lax.cond(running, lambda c: lax.scan(one_step, c, None, length=every)[0],
                         lambda c: c, carry[:-1] + (int0,))
        if spec is not None:  # the kept state and cell get a list of their own; one that
            # does not fit is an overflow, which run reallocates from the frame before
            state, cell, nbrs, k, failed, overflowed, narrow, lost = carry[:8]
            nbrs, refit, lost = kept_list_or_refit(spec, running & (failed >= 0), state, nbrs,
                                                   lost, cell)
            carry = (state, cell, nbrs, k, failed, overflowed | refit, narrow, lost,
                     *carry[8:])
        return carry, (carry[0], carry[1], measure(*carry[:3], carry[8], carry[10]))

    lost = (int0, int0, jnp.zeros((), dtype=state.x.dtype))
    no = jnp.asarray(False)
    init = (state, cell, neighbors, first_step, -jnp.ones_like(first_step), no, no, lost,
            exchanged, system.replace(cell=cell).energy_and_forces(state, neighbors)[1], int0)
    (_, _, last_list, _, failed, overflowed, narrow, lost, *_), (states, cells, values) = \
        scan_chunks(chunk, lambda carry: (carry, (carry[0], carry[1], first)), init, n_chunks,
                    active)
    join = lambda a, f: jnp.concatenate([a[None], f])  # noqa: E731
    return (jax.tree.map(join, state, states), join(cell, cells),
            jax.tree.map(join, first, values), failed, overflowed, narrow, lost, last_list)


_npt_jit = jax.jit(_npt, static_argnames=("method", "barostat", "space", "thermostat",
                                          "n_chunks", "every", "observers", "spec"))


def advance(system, state: State, cell, first_step, seed, dt, neighbors=None, *, steps: int,
            method, barostat: StochasticCellRescaling, space: Space,
            thermostat: Callable | None = None,
            observers: Sequence[tuple[str, Callable]] = (), spec=None):
    """``steps`` steps of the NPT run (the compiled loop of :func:`run`) from ``state`` in
    ``cell`` at global step ``first_step``, as a traceable function (no host work, vmappable):
    the building block of ensembles of NPT runs (the samples of ``affinebody sweep``). ``seed``
    may be traced. Returns (state, cell, values, failed, overflowed, narrow, lost, list) after
    the last step: ``values`` the observers with ``pressure`` and ``volume`` there, ``failed``
    the first step not kept (-1: none; the state and cell are then the last good ones),
    ``overflowed``/``narrow``/``lost`` what :func:`run` reallocates from, ``list`` the
    neighbour list (valid for the state in the cell) or None."""
    exchanged = (jnp.zeros((), dtype=state.x.dtype),) * 2  # heat and work since the start
    states, cells, values, failed, overflowed, narrow, lost, last_list = _npt(
        system, state, cell, first_step, seed, dt, neighbors, exchanged, method=method,
        barostat=barostat,
        space=space, thermostat=thermostat, n_chunks=1, every=int(steps),
        observers=tuple(observers), spec=spec)
    last = lambda a: a[-1]  # noqa: E731
    return (jax.tree.map(last, states), cells[-1], jax.tree.map(last, values), failed,
            overflowed, narrow, lost, last_list)


def _initial_list(system, method, state, cell, neighbors):
    """(spec, list) valid for ``state`` in ``cell``, from the (spec, list) pair given (built
    again in ``cell`` when it may miss a pair, reallocated when it overflows); (None, None)
    for all pairs."""
    if neighbors is None:
        return None, None
    if not method.uses_neighbor_lists:
        raise ValueError(f"integrator {method.name!r} sums over all pairs: neighbour lists work "
                         f"with the splitting integrators")
    try:
        spec, lst = neighbors
    except (TypeError, ValueError):
        raise ValueError("neighbors must be the (spec, list) pair of neighbors.allocate(..., "
                         "cell=...)") from None
    if not isinstance(spec, nb.NeighborSpec) or not isinstance(lst, nb.NeighborList):
        raise ValueError("neighbors must be the (spec, list) pair of neighbors.allocate")
    space, cutoff, variable = system.neighbor_range()
    if spec.space != space or spec.variable != variable or spec.cutoff < cutoff:
        raise ValueError("the neighbour list does not fit the system's pair cut-off and box")
    if lst.cell is None or bool(nb.needs_rebuild(spec, lst, state.x, state.phi, cell)):
        lst = nb.build_jit(spec, state.x, state.phi, cell)
    if int(lst.overflow):
        return nb.list_at(spec, state.x, state.phi, cell)
    return spec, lst


def run(system, state: State, space, barostat: StochasticCellRescaling, dt: float, steps: int,
        *, seed: int, cell=None, first_step: int = 0, integrator="strang", every: int = 1,
        thermostat: Callable | None = None,
        observers: Sequence[tuple[str, Callable]] = (), neighbors=None, heat: float = 0.0,
        work: float = 0.0) -> NPTTrajectory:
    """Integrate ``steps`` steps at constant pressure: each step is one step of the
    integrator in the current box, the ``thermostat`` (a function
    ``(system, state, key, dt) -> state``, or None; one with a ``prepare(system, state)``
    method, as ``runner.ThermostatHook``, is replaced by what that returns once per compiled
    call, for what does not change from step to step) and a barostat move.

    Besides ``pressure`` and ``volume`` the frames record the energy exchanged with the baths
    since the start: ``heat``, the kinetic energy the thermostat put in, and ``work``, the
    change of H + P0 V made by the barostat's moves (P0 = Tr P0 / n), each summed exactly
    step by step from ``heat`` and ``work`` (their values before ``first_step``), and the
    ``effective_energy`` H + P0 V - heat - work, whose drift is the error of the integrator
    at fixed cell (docs/pressure.md); with ``barostat.metropolis`` also ``rejected_moves``,
    the moves rejected since the previous frame.

    space: the reference periodic box (that of the pair terms); cell: the box now (default
    ``space``'s cell); first_step: the index of the first step (keys: :func:`step_key`).
    observers: (name, function(system, state)) pairs recorded with the pressure and volume
    (with a neighbour list: function(system, state, list)).
    A step that makes the state or the cell non-finite, or the cell's diagonal non-positive
    (the barostat's step too large), or with a list the box narrower than twice its radius,
    is not kept: ``failed_step`` says where (``stop_reason`` why, in the last case).
    neighbors: None (pair terms over all pairs) or the (spec, list) pair of
    ``neighbors.allocate(space, x, phi, cutoff, variable, skin, cell=cell)`` (splitting
    integrators): forces, virial and observables are then summed over the list, which follows
    the box (rebuilt after a drift or a barostat move when it may miss a pair); an overflow of
    its capacities is recovered by reallocating at the last frame, or stops the run there
    (``failed_step``, ``stop_reason``) where it cannot be, as in ``simulate.run``
    (``simulate.ListRestarts``).
    """
    space = pressure_module.check_space(system, as_space(space))
    if not isinstance(barostat, StochasticCellRescaling):
        raise ValueError("barostat must be a StochasticCellRescaling")
    if barostat.target.shape != (space.dimension,) * 2:
        raise ValueError(f"barostat.pressure must be {space.dimension} x {space.dimension} "
                         f"(got {barostat.target.shape})")
    if int(steps) != steps or steps < 1 or int(every) != every or every < 1 or steps % every:
        raise ValueError(f"steps must be a positive multiple of every (got {steps}, {every})")
    if (barostat.coupling == "anisotropic" and not space.orthorhombic
            and np.any(np.tril(space.matrix, -1) != 0)):
        raise ValueError("anisotropic coupling of a triclinic box needs an upper-triangular "
                         "cell matrix (lattice vectors as columns: a along x, b in the xy "
                         "plane, ...)")
    method = get_integrator(integrator)
    method.check(system)
    state = system.check(state)
    cell = jnp.asarray(space.matrix if cell is None else cell, dtype=state.x.dtype)
    spec, nbrs = _initial_list(system, method, state, cell, neighbors)
    every = int(every)
    exchanged = (jnp.asarray(float(heat), dtype=state.x.dtype),
                 jnp.asarray(float(work), dtype=state.x.dtype))
    restarts = ListRestarts()  # the frames of each compiled call, numpy
    start, failed = int(first_step), -1
    end = int(first_step) + int(steps)
    n_chunks = (end - start) // every  # of every call: a restart runs its last ones
    while True:
        active = (end - start) // every
        states, cells, values, failed, overflowed, narrow, lost, last_list = _npt_jit(
            system, state, cell, jnp.asarray(start), int(seed), jnp.asarray(float(dt)), nbrs,
            exchanged, jnp.asarray(active, dtype=jnp.int32),
            method=method, barostat=barostat, space=space, thermostat=thermostat,
            n_chunks=n_chunks, every=every, observers=tuple(observers), spec=spec)
        part = jax.tree.map(lambda a, ran=active + 1: np.asarray(a)[:ran],  # chunks that ran
                            (states, cells, values))
        failed = int(failed)
        if not bool(overflowed):
            restarts.keep(part)
            break
        aligned = (failed - 1 - start) // every  # the last frame before the overflow
        state = jax.tree.map(lambda a, j=aligned: jnp.asarray(a[j]), part[0])
        cell = jnp.asarray(part[1][aligned])
        lists = restarts.restart(part, aligned, state, spec, lost, cell=cell,
                                 at_step=start + aligned * every, bad_step=failed)
        if lists is None:
            break
        spec, nbrs = lists
        exchanged = tuple(jnp.asarray(part[2][k][aligned]) for k in ("heat", "work"))
        start += aligned * every
    states, cells, values = restarts.joined()
    times = (first_step + np.arange(len(cells)) * every) * float(dt)
    reason = None
    if restarts.failure is not None:
        reason = (f"the neighbour list overflowed and could not be reallocated: "
                  f"{restarts.failure}; {OVERFLOW_FIX}")
    elif bool(narrow):
        reason = ("the box shrank below twice the neighbour-list radius (reach + skin; the "
                  "minimum image is no longer exact): use a larger box, a lower pressure or a "
                  "smaller skin")
    return NPTTrajectory(times, states, cells, values, None if failed < 0 else failed,
                         None if spec is None else (spec, last_list), reason)


__all__ = ["COUPLINGS", "NPTTrajectory", "STREAM", "StochasticCellRescaling", "advance",
           "LONG_MOVE", "LONG_MOVE_FIX", "c_rescale", "first_narrow_frame", "long_move_effect",
           "long_move_warning",
           "LARGE_MOVE", "move_length", "move_modulus", "move_modulus_jit", "run", "step_key",
           "stop_advice",
           "variance_factor"]
