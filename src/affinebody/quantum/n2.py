"""n = 2 sectors of one quantum affine body: the reduced blocks, their scales and the sector search.

Discretisations (all Galerkin, potential matrices by Gauss quadrature):

* n = 2, d'Alembert, J = I Id. Write phi = [[a+c, d-b], [b+d, a-c]] = Z + W with the conformal
  part z = a + ib and the anticonformal part w = c + id: Q_1 = |z| + |w|, Q_2 = |z| - |w|,
  Tr(phi^T phi) = 2(|z|^2 + |w|^2) and T = I(|z'|^2 + |w'|^2), so
  H = -(hbar^2 / 4I)(Lap_z + Lap_w) + V. L-rotations multiply z, w by e^{i alpha}, R-rotations
  by e^{-i beta}, e^{i beta}; a state e^{i(m1 arg z + m2 arg w)} has spin s = m1 + m2 and
  vorticity k = m2 - m1. In the sector (m1, m2) the reduced problem lives on r1 = |z|,
  r2 = |w| >= 0 with measure r1 r2 (= (Q_1^2 - Q_2^2)/4) and centrifugal terms
  hbar^2 m_i^2 / (4 I r_i^2), i.e. (rho -+ tau)^2 / (4 I (Q_1 +- Q_2)^2) of
  docs/theory/two-polar.md with rho = hbar s, tau = hbar k. Basis: products of 2D-radial
  oscillator functions r^|m| L_j^|m|(r^2/b^2) e^{-r^2/2b^2} (generalised Laguerre, orthonormal
  under r dr), exact for the oscillator and exponentially convergent for smooth confining V.
* n = 2, affine models (73) is-af, (74) af-is, (72) af-af on GL+(2). With x = q_1 - q_2 > 0 and
  sigma = q_1 + q_2, the reduced operator of docs/theory/two-polar.md (M = I + A) is
  H = -(hbar^2/M)(1/sinh x) d_x sinh x d_x - hbar^2/(M + 2B) d_sigma^2
      + hbar^2 (s+k)^2 / (16 M sinh^2(x/2)) - hbar^2 (s-k)^2 / (16 M cosh^2(x/2))
      + hbar^2 k^2 / (2 I~)   [is-af: s^2; af-af: none] + V(q).
  The basis is g(x) u_j(x) h_l(sigma) with g = sqrt(x / sinh x) (so the functions are
  orthonormal under sinh x dx dsigma), u_j the 2D-radial Laguerre functions of order
  m = |s+k|/2 and h_l Hermite functions. Conjugating by g turns the x-part into the flat 2D
  radial operator plus the smooth term W = 1/4 + (1/x^2 - 1/sinh^2 x)/4.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from affinebody.quantum.bases import (
    Basis,
    Hermite1D,
    Radial2D,
    centre_runs_away,
    inv_x2_minus_inv_sinh2,
    lowest_sum,
    product_potential_matrix,
    runaway_message,
    solve_block,
    variational_parameters,
    variational_scales,
)
from affinebody.quantum.bounds import haar2_shell_bounds, lebesgue2_shell_bounds
from affinebody.quantum.intervals import Unsupported
from affinebody.quantum.levels import (
    AffineInertia,
    LevelCollector,
    Potential,
    Sector,
    Settings,
    Spectrum,
)


def lebesgue2_block(potential: Potential, hbar: float, inertia: float, m1: int, m2: int,
                    size: int, scale: float, quad: int | None = None
                    ) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of the n = 2 d'Alembert sector (|m1|, |m2|), J = inertia * Id."""
    quad = quad or size + 24
    f1 = Radial2D(abs(m1), size, scale, quad)
    f2 = Radial2D(abs(m2), size, scale, quad)
    r1, B1 = f1.nodes()
    r2, B2 = f2.nodes()
    R1, R2 = np.meshgrid(r1, r2, indexing="ij")
    Q = np.stack([R1 + R2, R1 - R2], axis=-1)
    H = product_potential_matrix(B1, B2, potential(Q))
    eye = np.eye(size)
    H += (hbar**2 / (4 * inertia)) * (np.kron(f1.laplacian(), eye) + np.kron(eye, f2.laplacian()))
    return 0.5 * (H + H.T), Basis("lebesgue2", (f1, f2))

def haar2_block(potential: Potential, hbar: float, inertia: AffineInertia, spin: int,
                vorticity: int, size: tuple[int, int], scale: tuple[float, float], centre: float,
                quad: tuple[int, int] | None = None) -> tuple[np.ndarray, Basis]:
    """Galerkin Hamiltonian of the n = 2 affine sector (s, k) on GL+(2), see module docstring."""
    nx, ns = size
    qx, qs = quad or (nx + 24, ns + 24)
    m = abs(spin + vorticity) // 2
    fx = Radial2D(m, nx, scale[0], qx)
    fs = Hermite1D(ns, scale[1], centre, qs)
    x, Bx = fx.nodes()
    sigma, Bs = fs.nodes()
    M = inertia.M
    W = 0.25 + 0.25 * inv_x2_minus_inv_sinh2(x)
    centrifugal = m * m * (1 / (4 * np.sinh(x / 2) ** 2) - 1 / x**2)
    rotational = {"af-is": vorticity**2, "is-af": spin**2, "af-af": 0}[inertia.model]
    smooth_x = (hbar**2 / M) * (W + centrifugal) - (
        hbar**2 * (spin - vorticity) ** 2 / (16 * M * np.cosh(x / 2) ** 2))
    X, S = np.meshgrid(x, sigma, indexing="ij")
    q = np.stack([(S + X) / 2, (S - X) / 2], axis=-1)
    with np.errstate(over="ignore"):  # e^q overflows far out, where V is +inf anyway
        V = np.asarray(potential(np.exp(q)), float) + smooth_x[:, None]
    H = product_potential_matrix(Bx, Bs, V)
    H += np.kron((hbar**2 / M) * fx.laplacian(), np.eye(ns))
    H += np.kron(np.eye(nx), (hbar**2 / inertia.dilatation) * fs.laplacian())
    H += np.eye(nx * ns) * (hbar**2 * rotational * inertia.inv_I_tilde / 2)
    return 0.5 * (H + H.T), Basis("haar2", (fx, fs))


# ------------------------------------------------------------------------ scale choice

def auto_scale_lebesgue2(potential: Potential, hbar: float, inertia: float) -> float:
    """Oscillator length minimising the sum of the 3 lowest (0,0)-sector levels in a basis of
    6 x 6 functions. Where that sum is flat to round-off around its minimum (an oscillator,
    whose lowest levels the basis holds to ~1e-14 at any length within a few per cent of its
    own, so that round-off picked the minimum: a 1 % change of the length lost two of the ten
    N = 2 states of the tests' oscillator at basis_size 9), the length minimising the same sum
    in a basis of 3 x 3 functions, which holds them only at the oscillator's length."""
    def energy(logb, size):
        b = float(np.exp(np.clip(logb[0], -6, 6)))
        H, _ = lebesgue2_block(potential, hbar, inertia, 0, 0, size, b, 30)
        return lowest_sum(H, 3)

    logb = variational_parameters(lambda p: energy(p, 6), np.array([0.0]))
    lowest = energy(logb, 6)
    change = max(abs(energy(logb + step, 6) - lowest) for step in (-0.02, 0.02))
    if not change > 1e-12 * max(1.0, abs(lowest)):  # flat: round-off's choice
        logb = variational_parameters(lambda p: energy(p, 3), logb)
    return float(np.exp(np.clip(logb[0], -6, 6)))


def auto_scale_haar2(potential: Potential, hbar: float, inertia: AffineInertia,
                     given: tuple[float | None, float | None, float | None] = (None,) * 3
                     ) -> tuple[float, float, float]:
    """(scale_x, scale_sigma, centre_sigma) minimising the sum of the 3 lowest (0,0)-sector
    levels in a basis of 6 x 6 functions, over those of the three that ``given`` leaves None
    (the others are kept as given)."""
    sig = np.linspace(-8, 8, 161)
    Vline = np.asarray(potential(np.exp(np.stack([sig / 2, sig / 2], -1))), float)
    centre0 = float(sig[np.argmin(np.where(np.isfinite(Vline), Vline, np.inf))])
    return variational_scales(_scale_objective(potential, hbar, inertia), (0.0, 0.0, centre0),
                              given, (-5, 3))


def _scale_objective(potential: Potential, hbar: float, inertia: AffineInertia):
    """What :func:`auto_scale_haar2` minimises: the sum of the 3 lowest (0,0)-sector levels in
    a basis of 6 x 6 functions at (scale_x, scale_sigma, centre_sigma)."""
    def energy(bx, bs, c):
        H, _ = haar2_block(potential, hbar, inertia, 0, 0, (6, 6), (bx, bs), c, (30, 30))
        return lowest_sum(H, 3)
    return energy


def n2_sectors(key: tuple, model: str) -> tuple[Sector, ...]:
    """The (s, k) sectors sharing the reduced block ``key``."""
    if model == "dalembert":
        a, b = key  # |m1|, |m2|
        pairs = {(s1 * a, s2 * b) for s1 in (1, -1) for s2 in (1, -1)}
        out = [(m1 + m2, m2 - m1) for m1, m2 in pairs]
    else:
        s, k = key
        out = list({(s, k), (-s, -k)})
    out.sort(key=lambda p: (-p[0], -p[1]))
    # k labels R -> R(beta) R, i.e. phi -> phi R(beta)^T: the vorticity V_12 = (Sigma_hat -
    # Sigma_hat^T)_12, generating phi -> phi R(t), has eigenvalue -hbar k (reduction.py).
    return tuple(Sector(s, -k, (-1) ** abs(s)) for s, k in out)

def solve_n2(model: str, potential: Potential, hbar: float, inertia: float,
             affine: AffineInertia, levels: int, settings: Settings,
             progress: Callable[[str], None] | None = None) -> Spectrum:
    """The lowest ``levels`` states of the n = 2 body over the sectors (s, k), shell by shell
    (d'Alembert: shell |m1| + |m2|; affine: max(|s|, |k|)) up to ``settings.max_spin``;
    arguments as in :func:`affinebody.quantum.spectra.solve` (``affine``: the constants of the
    affine models).

    Stopping rule (docs/theory/two-polar.md, "Lower bounds of a sector"): with E_K the
    ``levels``-th lowest candidate found, a block whose certified lower bound
    (:mod:`affinebody.quantum.bounds`) exceeds E_K is not solved, and the search stops after the
    shell L when every sector of the shells above L has its bound above E_K (``certified``).
    Without a bound (a Python callable, af-af, a bound that stays below E_K) every shell up to
    max_spin is searched and the result is conditional (``certificate`` says why).
    ``progress`` receives a line as each shell starts."""
    found = LevelCollector(settings)
    info: dict = {"basis_size": settings.basis_size}
    count = levels + 4
    if model == "dalembert":
        b = settings.scale or auto_scale_lebesgue2(potential, hbar, inertia)
        info["scale"] = b

        def build_for(a, c):
            return lambda size, s: lebesgue2_block(potential, hbar, inertia, a, c, size, s)
        shells = ((a, L - a) for L in range(settings.max_spin + 1) for a in range(L + 1))
        shell_of = lambda key: key[0] + key[1]
    else:
        inert = affine
        bx, bs, c0 = affine_scales(model, potential, hbar, inert, settings)
        info.update(scale=bx, scale_sigma=bs, centre=c0)

        def build_for(s, k):
            return lambda size, sc: haar2_block(
                potential, hbar, inert, s, k, (size, size), (sc, bs * sc / bx), c0)
        # representatives of (s, k) ~ (-s, -k), s + k even; shell = max(|s|, |k|)
        shells = ((s, k) for L in range(settings.max_spin + 1) for s in range(0, L + 1)
                  for k in range(-L, L + 1) if max(s, abs(k)) == L and (s + k) % 2 == 0
                  and (s > 0 or k >= 0))
        shell_of = lambda key: max(abs(key[0]), abs(key[1]))

    bounds, reason = None, ""
    try:
        if model == "dalembert":
            bounds = lebesgue2_shell_bounds(potential, hbar, inertia, settings.max_spin, b)
        else:
            bounds = haar2_shell_bounds(potential, hbar, affine, settings.max_spin, c0, bs)
    except Unsupported as err:
        reason = str(err)
    by_shell: dict[int, list] = {}
    for key in shells:
        by_shell.setdefault(shell_of(key), []).append(key)
    shell_minima: list[float] = []
    certified, searched, pruned = False, -1, 0
    for shell in range(settings.max_spin + 1):
        if progress is not None:
            progress(f"shell {shell} of at most {settings.max_spin} "
                     f"({found.state_count()} states found)")
        shell_min = np.inf
        for key in by_shell.get(shell, []):
            if bounds is not None and found.state_count() >= levels and (
                    bounds.of(key) > found.kth_energy(levels)):
                pruned += 1  # no level of this block can be among the lowest: not solved
                continue
            E, vec, err, basis = solve_block(build_for(*key), settings.basis_size,
                                             info["scale"], count, settings)
            shell_min = min(shell_min, float(E[0]))
            found.record(key, n2_sectors(key, model), basis, E, vec, err)
        shell_minima.append(shell_min)
        searched = shell
        if bounds is not None and found.state_count() >= levels and (
                bounds.beyond(shell) > found.kth_energy(levels)):
            certified = True
            break
    info["shells_searched"] = searched
    info["sectors_pruned"] = pruned
    warnings = []
    bounded = True
    if model == "af-af":
        bounded = False
        warnings.append(afaf_warning(hbar, affine.A, settings.max_spin, shell_minima))
        certificate = "none: af-af is unbounded below"
    elif certified:
        certificate = (f"{bounds.method}; every sector beyond shell {searched} has no level "
                       f"below {bounds.beyond(searched):.6g} > the {levels}-th candidate "
                       f"{found.kth_energy(levels):.6g}")
    else:
        beyond = "" if bounds is None else (
            f" (certified lower bound beyond shell {searched}: {bounds.beyond(searched):.6g})")
        why = reason or "the bound of the sectors not searched does not exceed the K-th level"
        certificate = (f"conditional: {why}; searched every sector up to max_spin = "
                       f"{settings.max_spin}{beyond}")
        if bounds is None:  # a Python callable, or an expression the bounds do not take
            fix = "raise quantum.max_spin or give the potential as an expression"
        else:  # an expression whose bound stays below the K-th level
            fix = (f"raise quantum.max_spin; the bound beyond the last shell searched is "
                   f"{bounds.beyond(searched):.6g}, and a potential that does not confine the "
                   f"body keeps it at its infimum at every spin")
        warnings.append(f"the {levels} lowest states are conditional: {why}; only sectors up "
                        f"to max_spin = {settings.max_spin} were searched ({fix})")
    merged, unconverged = found.levels(levels)
    return Spectrum(merged, unconverged, found.blocks, model, 2, "all", info, bounded, warnings,
                    certified=certified, certificate=certificate, requested=levels)


def affine_scales(model: str, potential: Potential, hbar: float, inertia: AffineInertia,
                  settings: Settings) -> tuple[float, float, float]:
    """(scale, scale_sigma, centre) of the basis of an affine model: those ``settings`` gives,
    the others by :func:`auto_scale_haar2` with the given ones held; ValueError
    (:func:`runaway_message`) where the automatic ones leave the basis not finite."""
    given = settings.scale, settings.scale_sigma, settings.centre
    if None not in given:
        return given
    bx, bs, c0 = auto_scale_haar2(potential, hbar, inertia, given)
    size = (settings.basis_size,) * 2
    if not np.all(np.isfinite(haar2_block(potential, hbar, inertia, 0, 0, size, (bx, bs),
                                          c0)[0])):
        raise ValueError(runaway_message(model, bx, bs, c0))
    if settings.centre is None and centre_runs_away(
            _scale_objective(potential, hbar, inertia), bx, bs, c0):
        raise ValueError(runaway_message(model, bx, bs, c0))
    return bx, bs, c0


def afaf_warning(hbar: float, A: float, max_spin: int, shell_minima: list[float]) -> str:
    """af-af (72) is indefinite: in the sector s = -k the reduced potential (module docstring,
    no rotational term since 1/I~ = 0) is -hbar^2 s^2 / (4 A cosh^2((q1 - q2)/2)), a well
    whose depth grows like s^2: the lowest level of shell |s| tends to -infinity."""
    trend = ", ".join(f"{e:.4g}" for e in shell_minima[-4:] if np.isfinite(e))
    return (f"af-af: the kinetic energy (72) is indefinite and the spectrum is unbounded below "
            f"(sector s = -k has the well -hbar^2 s^2/(4A cosh^2((q1-q2)/2)), depth "
            f"{hbar**2 * max_spin**2 / (4 * A):.4g} at |s| = {max_spin}); lowest level per shell "
            f"up to max_spin = {max_spin}: {trend}; the levels listed are those of the sectors "
            f"|s|, |k| <= max_spin only, not the lowest of the body")


__all__ = [
    "lebesgue2_block", "haar2_block", "auto_scale_lebesgue2", "auto_scale_haar2", "affine_scales",
    "n2_sectors", "solve_n2", "runaway_message", "afaf_warning"
]
