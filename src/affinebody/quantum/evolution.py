"""Time evolution of a wave packet of one quantum affine body by its expansion in eigenstates
(paper, last section: amplitudes of the deformation invariants; docs/quantum-transitions.md).

n = 2 (n = 3: :mod:`affinebody.quantum.evolution3`). Two kinds of packets: a Gaussian in phi
around a classical (phi, pi) over every sector it populates (:class:`MatrixPacket`, every
model), and the one below.

A :class:`Packet` lives in the sector spin = vorticity = 0 of n = 2 (a state invariant under
phi -> U phi V^T, U, V in SO(2): it carries no angular momentum, and its classical
counterpart is a motion with zero spin and vorticity, along which phi stays diagonal when it
starts diagonal with a diagonal velocity). In the variables X of the model (d'Alembert: the
signed singular values Q1 >= |Q2|; affine models: q_a = ln Q_a, q1 >= q2) it is

    psi_0 = N exp(-|X - X0|^2 / (4 w^2) + i p0 . (X - X0) / hbar) / sqrt(m(X)),

with m(X) the reduced measure per dX (so |psi_0|^2 m dX is the Gaussian of centre X0 and
standard deviation w in each variable, and the mean momentum conjugate to X is p0). With the
eigenpairs (E_n, a_n) of the sector, c_n = <a_n|psi_0> and

    psi(t) = sum_n c_n e^{-i E_n t / hbar} a_n,
    <A>(t) = sum_{mn} conj(c_m(t)) c_n(t) <a_m|A|a_n>,
    S(t) = |<psi(0)|psi(t)>|^2 = |sum_n |c_n|^2 e^{-i E_n t / hbar}|^2,

exactly, for any t (no time step). ``captured`` = sum |c_n|^2 is the part of the packet the
eigenstates of the basis hold (1 up to the basis' resolution; a packet that the basis does not
hold is refused); ``energy_error`` = sum |c_n|^2 err_n / captured weighs the error estimates of
the eigenvalues (nested and widened check bases; one per degenerate level,
:func:`affinebody.quantum.bases.level_errors`) with the packet's populations: the accuracy of
the propagated phases (a state beyond the check bases counts with its full energy). The
Fourier transform of S has its lines at the differences (E_m - E_n)/hbar.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from affinebody._checks import require_x64
from affinebody.quantum.bases import solve_block, sqrt_x_over_sinh
from affinebody.quantum.densities import joint_density, measure
from affinebody.quantum.levels import (
    AffineInertia,
    Block,
    Level,
    Potential,
    Settings,
    Spectrum,
    is_converged,
)
from affinebody.quantum.n2 import (
    affine_scales,
    auto_scale_lebesgue2,
    haar2_block,
    lebesgue2_block,
    n2_sectors,
)
from affinebody.quantum.transitions import invariants_at

#: the largest reduced basis (functions per coordinate) evolve solves densely
MAX_BASIS = 48
#: the most (time points) x (basis functions)^2 one evolution may cost
MAX_WORK = 4e9
#: the most time intervals of one evolution
MAX_STEPS = 100000
#: the packet must be held by the eigenstates of the basis to this
CAPTURE = 1e-6
#: the least distance of the packet's centre from the wall of the domain, in widths
WALL = 6
#: Gauss-Legendre nodes per reduced coordinate: NODES + 2 x basis size (the product of two
#: eigenfunctions is a polynomial of degree about 4 x basis size times a Gaussian)
NODES = 32
#: the observables reported (the model's two variables, det phi, Tr G)
VARIABLES = {"dalembert": ("Q1", "Q2", "det", "trG"), "affine": ("q1", "q2", "det", "trG")}


def sector_spectrum(model: str, potential: Potential, hbar: float, *, inertia: float = 1.0,
                    I: float = 1.0, A: float = 0.0, B: float = 0.0,  # noqa: E741
                    settings: Settings | None = None, key: tuple[int, int] = (0, 0)
                    ) -> Spectrum:
    """Every eigenpair of the n = 2 sector spin = vorticity = 0 (the reduced block of
    :mod:`affinebody.quantum.n2`, solved densely; each level carries the error estimate of its
    nested and widened check bases and is flagged converged or not). ``key`` picks another
    block (n2.n2_sectors): d'Alembert (|m1|, |m2|), the characters of z and w; affine models
    (s, k), the sectors (s, -k) and (-s, k) (spin, vorticity)."""
    require_x64()  # a potential expression is evaluated by JAX
    settings = settings or Settings()
    size = settings.basis_size
    check_work(size, 1)
    if model == "dalembert":
        b = settings.scale or auto_scale_lebesgue2(potential, hbar, inertia)
        info = {"scale": b}

        def build(n, s):
            return lebesgue2_block(potential, hbar, inertia, key[0], key[1], n, s)
    else:
        affine = AffineInertia(model, I, A, B)
        bx, bs, c0 = affine_scales(model, potential, hbar, affine, settings)  # as spectrum's
        info = {"scale": bx, "scale_sigma": bs, "centre": c0}

        def build(n, s):
            return haar2_block(potential, hbar, affine, key[0], key[1], (n, n),
                               (s, bs * s / bx), c0)
    E, vec, err, basis = solve_block(build, size, info["scale"], size * size, settings)
    sectors = n2_sectors(key, model)
    # every eigenpair its own level (degenerate ones are not merged: each is a state); the
    # Galerkin space is what the packet evolves in, so every one is used, each with its estimate
    levels = [Level(float(E[i]), 1, sectors, float(err[i]), key, i,
                    is_converged(E[i], err[i], settings)) for i in range(len(E))]
    info["basis_size"] = size
    blocks = {key: Block(key, sectors, basis, E, vec, err)}
    return Spectrum(levels, [], blocks, model, 2, "all", info)


@dataclass(frozen=True)
class Packet:
    """A Gaussian packet in the model's variables (module docstring)."""

    centre: tuple[float, float]
    momentum: tuple[float, float]
    width: float


def variables_at(model: str, y: np.ndarray) -> np.ndarray:
    """The packet's variables X [..., 2] at reduced coordinates y: Q (d'Alembert), q (affine)."""
    Q = invariants_at("lebesgue2" if model == "dalembert" else "haar2", y)
    return Q if model == "dalembert" else np.log(Q)


def check_packet(model: str, packet: Packet) -> None:
    X1, X2 = packet.centre
    w = packet.width
    if not (math.isfinite(w) and w > 0):
        raise ValueError(f"--width must be > 0 (got {w})")
    gap = (X1 - abs(X2) if model == "dalembert" else X1 - X2) / math.sqrt(2)
    name = "Q1 = |Q2|" if model == "dalembert" else "q1 = q2"
    if gap < WALL * w:
        raise ValueError(f"--at: the packet must lie inside the domain, at least {WALL} widths "
                         f"from the wall {name} (got {gap / w:.3g} widths): move it or narrow it")


def block_functions(spectrum: Spectrum, levels: list[Level], y: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The basis functions [P, N] of the block of ``levels`` at y and the levels' eigenvectors
    [N, S]: amplitudes = functions @ vectors, normalised as those of
    :func:`affinebody.quantum.densities.joint_density` (under its ``measure``; the Haar
    conjugation g = sqrt(x / sinh x) is divided out for the affine models, whose joint measure
    is x = g^2 sinh x)."""
    block = spectrum.blocks[levels[0].block]
    values = block.basis.reduced_values((y[:, 0], y[:, 1]))  # [P, N]
    if block.basis.kind == "haar2":
        values = values / sqrt_x_over_sinh(y[:, 0])[:, None]
    return values, block.vectors[:, [lv.index for lv in levels]]


def check_work(basis_size: int, times: int) -> None:
    """Refuse at once an evolution whose work, (times) x (basis functions)^2 for the packet on
    the quadrature, exceeds :data:`MAX_WORK`, or whose basis exceeds :data:`MAX_BASIS`."""
    if basis_size > MAX_BASIS:
        raise ValueError(f"quantum.basis_size = {basis_size} is more than evolve solves "
                         f"({MAX_BASIS}: a dense eigenproblem of {basis_size ** 2} functions "
                         f"takes minutes)")
    work = times * basis_size**4
    if work > MAX_WORK:
        raise ValueError(f"evolve: {times} times x {basis_size ** 2} states is more work than "
                         f"allowed ({work:.1e} > {MAX_WORK:.0e}): ask for fewer --steps or a "
                         f"smaller quantum.basis_size")


def require_captured(captured: float) -> None:
    """Refuse a packet the eigenstates hold to less than 1 - :data:`CAPTURE`, or whose
    expansion is not finite."""
    if not math.isfinite(captured):
        raise ValueError(f"evolve: the packet's expansion in the eigenstates is {captured} in "
                         f"float64 (its momentum or its inverse width is too large for it): "
                         f"lower --momentum (--pi) or widen --width")
    if captured < 1 - CAPTURE:
        raise ValueError(f"evolve: the eigenstates of the basis hold only {captured:.6f} of the "
                         f"packet (it reaches energies or places the basis does not resolve): "
                         f"raise quantum.basis_size, or start the packet slower or nearer the "
                         f"minimum")


#: the largest phase (E_n - E_0) t / hbar, in radians, an evolution reports: float64 resolves
#: a phase to eps x its size, 2e-3 rad at 1e13, beyond which the means and the survival
#: probability are noise
MAX_PHASE = 1e13


def check_phases(evolution: Evolution, hbar: float) -> None:
    """ValueError (one line) when the phases of ``evolution`` at its last time exceed
    :data:`MAX_PHASE`: its numbers would be round-off, printed as if they were results."""
    spread = float(np.ptp(evolution.energies)) if len(evolution.energies) else 0.0
    phase = spread * float(evolution.times[-1]) / hbar
    if not phase <= MAX_PHASE:
        raise ValueError(f"--time {evolution.times[-1]:.6g}: the phases (E_n - E_0) t / hbar "
                         f"reach {phase:.1e} rad, which float64 holds only to "
                         f"{phase * 2.2e-16:.1e} rad (the results would be round-off): give "
                         f"--time up to {MAX_PHASE * hbar / spread:.3g}")


@dataclass(frozen=True)
class Evolution:
    times: np.ndarray
    energies: np.ndarray  # E_n of the states used
    coefficients: np.ndarray  # c_n
    captured: float
    energy_error: float
    mean: dict  # name -> [T]
    spread: dict  # name -> [T]
    survival: np.ndarray  # |<psi(0)|psi(t)>|^2 [T]
    norm: np.ndarray  # [T]
    energy: np.ndarray  # <H>(t) [T]

    def as_dict(self) -> dict:
        return {"times": self.times.tolist(), "captured": self.captured,
                "energy_error": self.energy_error,
                "states": len(self.energies),
                "mean": {k: v.tolist() for k, v in self.mean.items()},
                "spread": {k: v.tolist() for k, v in self.spread.items()},
                "survival": self.survival.tolist(), "norm": self.norm.tolist(),
                "energy": self.energy.tolist()}


def evolve(spectrum: Spectrum, packet: Packet, times: np.ndarray, hbar: float) -> Evolution:
    """The packet's evolution over ``times`` in the eigenstates of ``spectrum`` (a
    :func:`sector_spectrum`; module docstring)."""
    model = spectrum.model
    check_packet(model, packet)
    times = np.asarray(times, float)
    levels = spectrum.levels
    check_work(spectrum.settings["basis_size"], len(times))
    first = joint_density(spectrum, levels[0])  # the box where the states live
    last = joint_density(spectrum, levels[-1])
    kind = first.model
    lo = np.minimum(first.box[:, 0], last.box[:, 0])
    hi = np.maximum(first.box[:, 1], last.box[:, 1])
    x, w = np.polynomial.legendre.leggauss(NODES + 2 * spectrum.settings["basis_size"])
    axes = [(lo[k] + (hi[k] - lo[k]) * (x + 1) / 2, (hi[k] - lo[k]) * w / 2) for k in range(2)]
    Y0, Y1 = np.meshgrid(axes[0][0], axes[1][0], indexing="ij")
    y = np.stack([Y0.ravel(), Y1.ravel()], -1)
    mu = measure(kind, y)
    weights = np.outer(axes[0][1], axes[1][1]).ravel() * mu
    functions, vectors = block_functions(spectrum, levels, y)  # [P, N], [N, S]
    X = variables_at(model, y)
    # |psi_0|^2 mu dy = Gaussian(X) dX: psi_0 = gauss / sqrt(mu |dy/dX|), |dy/dX| constant
    X0, p0 = np.asarray(packet.centre, float), np.asarray(packet.momentum, float)
    d = X - X0
    # a packet beyond float64 (a momentum of 1e308) gives nan here: require_captured says so
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        psi = np.where(mu > 0, np.exp(-np.sum(d * d, -1) / (4 * packet.width**2)
                                      + 1j * (d @ p0) / hbar) / np.sqrt(np.where(mu > 0, mu, 1)),
                       0.0)
        psi /= math.sqrt(float(np.sum(weights * np.abs(psi) ** 2)))
        c = vectors.T @ (functions.T @ (weights * psi))
        captured = float(np.sum(np.abs(c) ** 2))
    require_captured(captured)
    errors = np.array([lv.error for lv in levels])
    E = np.array([lv.energy for lv in levels])
    return _propagate([(c, E, errors, functions, vectors)], model, y, weights, times, hbar)


def _propagate(parts, model: str, y: np.ndarray, weights: np.ndarray, times: np.ndarray,
               hbar: float) -> Evolution:
    """The evolution of sum over ``parts`` (c [S], E [S], errors [S], functions [P, N], vectors
    [N, S]) of c_n e^{-i E_n t/hbar} a_n: parts of different sectors are orthogonal and the
    invariants observed do not connect them, so densities, norms and energies add."""
    kind = "lebesgue2" if model == "dalembert" else "haar2"
    names = VARIABLES["dalembert" if model == "dalembert" else "affine"]
    Q = invariants_at(kind, y)
    X = variables_at(model, y)
    values = {names[0]: X[:, 0], names[1]: X[:, 1], "det": np.prod(Q, -1),
              "trG": np.sum(Q * Q, -1)}
    density = np.zeros((len(times), len(y)))
    amplitude = np.zeros(len(times), complex)
    norm, energy = np.zeros(len(times)), np.zeros(len(times))
    c_all, E_all, p_err = [], [], 0.0
    for c, E, errors, functions, vectors in parts:
        phases = np.exp(-1j * np.outer(times, E) / hbar)  # [T, S]
        ct = c[None, :] * phases
        basis_ct = ct @ vectors.T  # [T, N]; psi(t, y) = basis_ct @ functions.T
        density += ((basis_ct.real @ functions.T) ** 2
                    + (basis_ct.imag @ functions.T) ** 2) * weights
        p = np.abs(c) ** 2
        amplitude += phases @ p
        norm += np.sum(np.abs(ct) ** 2, -1)
        energy += np.abs(ct) ** 2 @ E
        p_err += float(np.sum(p * np.where(np.isfinite(errors), errors, np.abs(E))))
        c_all.append(c)
        E_all.append(E)
    c, E = np.concatenate(c_all), np.concatenate(E_all)
    captured = float(np.sum(np.abs(c) ** 2))
    energy = energy / norm
    mean, spread = {}, {}
    for name, v in values.items():
        m1 = density @ v / captured
        m2 = density @ (v * v) / captured
        mean[name] = m1
        spread[name] = np.sqrt(np.maximum(m2 - m1 * m1, 0.0))
    survival = np.abs(amplitude) ** 2 / captured**2
    return Evolution(times, E, c, captured, p_err / captured, mean, spread, survival, norm,
                     energy)


def spectrum_lines(evolution: Evolution, count: int = 5) -> list[float]:
    """The ``count`` strongest angular frequencies of the survival probability S(t) (peaks of
    |FFT(S - mean S)| on the uniform ``times``, refined by a parabola through the peak and its
    neighbours): approximations of level spacings (E_m - E_n)/hbar."""
    t = evolution.times
    S = evolution.survival - np.mean(evolution.survival)
    F = np.abs(np.fft.rfft(S * np.hanning(len(S))))
    omega = 2 * np.pi * np.fft.rfftfreq(len(S), t[1] - t[0])
    peaks = [k for k in range(1, len(F) - 1) if F[k] >= F[k - 1] and F[k] >= F[k + 1]]
    peaks.sort(key=lambda k: -F[k])
    out = []
    for k in peaks[:count]:
        a, b, c = F[k - 1], F[k], F[k + 1]
        shift = 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c != 0 else 0.0
        out.append(float(omega[k] + shift * (omega[1] - omega[0])))
    return out




# ------------------------------------------------- a packet around a classical (phi, pi)
#: the most angles per polar angle for the sector decomposition of a matrix packet
PACKET_ANGLES = 512
#: a sector holding less than this fraction of the packet is left out (its part is reported
#: in ``captured``)
SECTOR_FLOOR = 1e-12
#: the most blocks (|m1|, |m2|) (d'Alembert) or (s, k) (affine models) one matrix packet may
#: need
MAX_BLOCKS = 400
#: the packet's reach beyond its centre, in widths, for the quadrature box
REACH = 10


@dataclass(frozen=True)
class MatrixPacket:
    """A Gaussian in phi (n = 2): |psi_0|^2 d^4 phi is the normal density of mean ``phi`` and
    standard deviation ``width`` per component, and the mean canonical momentum is ``pi`` (=
    inertia dphi/dt of the classical d'Alembert motion; the momentum of the classical state
    (phi, pi) of any model):

        d'Alembert:       psi_0(phi) = N exp(-|phi - phi0|^2 / (4 w^2)
                                         + i tr(pi0^T (phi - phi0)) / hbar),
        affine models:    the same times det phi on GL+(2) (states are normalised under the
                          Haar measure d^4 phi / det^2 phi), 0 where det phi <= 0: a
                          Gaussian restricted to GL+(2), whose moments are those of the
                          Gaussian when its smallest singular value is many widths.

    Spin and vorticity of the classical (phi0, pi0) make it a superposition of many sectors."""

    phi: tuple
    pi: tuple
    width: float


def packet_harmonics(packet: MatrixPacket, y: np.ndarray, hbar: float, kind: str = "lebesgue2"
                     ) -> dict[tuple[int, int], np.ndarray]:
    """(spin s, vorticity v) -> psi_(s,v)(y) [P]: the coefficient of e^{i(s alpha - v beta)} in
    psi_0(R(alpha) diag(Q(y)) R(beta)^T). With A = phi0/(2 w^2) + i pi0/hbar split into its
    conformal part p Id + q J and anticonformal part u diag(1, -1) + r [[0, 1], [1, 0]]
    (R^T(alpha) A R(beta) has the diagonal (c + d, c - d), c = p cos t1 - q sin t1,
    d = u cos t2 + r sin t2, t1 = beta - alpha, t2 = alpha + beta), the exponent is

        -(|Q|^2 + |phi0|^2)/(4 w^2) - i tr(pi0^T phi0)/hbar
        + (Q1 + Q2)(p cos t1 - q sin t1) + (Q1 - Q2)(u cos t2 + r sin t2),

    a product of a function of t1 and one of t2. Their Fourier coefficients F1[a], F2[b] (FFT
    on N angles; N = 32, 64, ... until the harmonics beyond N/2 - 4 hold less than 1e-12 of
    the packet) give the coefficient F1[a] F2[b] of e^{i(b - a) alpha + i(a + b) beta}: s = b - a,
    v = -(a + b) (a, b: the charges m1 = -a of z and m2 = b of w in n2). ``kind``: the reduced
    coordinates y (:func:`affinebody.quantum.transitions.invariants_at`); "haar2" adds the
    factor det phi = Q1 Q2 of the affine packet."""
    Q = invariants_at(kind, y)
    phi0, pi0 = np.asarray(packet.phi, float), np.asarray(packet.pi, float)
    w2 = packet.width**2
    const = (-(np.sum(Q * Q, -1) + np.sum(phi0 * phi0)) / (4 * w2)
             - 1j * np.sum(pi0 * phi0) / hbar)
    if kind == "haar2":
        const = const + np.log(Q[:, 0] * Q[:, 1])
    A = phi0 / (2 * w2) + 1j * pi0 / hbar
    p, q = (A[0, 0] + A[1, 1]) / 2, (A[1, 0] - A[0, 1]) / 2
    u, r = (A[0, 0] - A[1, 1]) / 2, (A[0, 1] + A[1, 0]) / 2
    N = 32
    while True:
        t = 2 * np.pi * np.arange(N) / N
        k = np.fft.fftfreq(N, 1 / N).astype(int)
        edge = np.abs(k) > N // 2 - 4
        logs = [(Q[:, 0] + Q[:, 1])[:, None] * (p * np.cos(t) - q * np.sin(t)),
                (Q[:, 0] - Q[:, 1])[:, None] * (u * np.cos(t) + r * np.sin(t))]
        factors, shift = [], const.real.copy()
        for g in logs:  # scaled by their largest modulus per point (no overflow)
            top = np.max(g.real, -1)
            factors.append(np.fft.fft(np.exp(g - top[:, None]), axis=-1) / N)
            shift += top
        with np.errstate(under="ignore"):
            front = np.exp(shift + 1j * const.imag)  # [P]
        mass1 = np.abs(front)[:, None] ** 2 * np.abs(factors[0]) ** 2  # [P, N]
        mass2 = np.abs(factors[1]) ** 2
        total = np.sum(mass1 * np.sum(mass2, -1, keepdims=True))
        beyond = (np.sum(mass1[:, edge] * np.sum(mass2, -1, keepdims=True))
                  + np.sum(mass1 * np.sum(mass2[:, edge], -1, keepdims=True)))
        if beyond <= 1e-12 * total:
            break
        if N >= PACKET_ANGLES:
            raise ValueError("evolve: the packet's angular momentum (spin, vorticity) exceeds "
                             f"what {N} angles resolve: give a smaller --pi or a larger hbar")
        N *= 2
    mass = np.einsum("pa,pb->ab", mass1, mass2)
    keep = mass > SECTOR_FLOOR * np.max(mass)
    # F[k] = mean f e^{-i k t}: the coefficient of e^{i k t}
    return {(int(k[b] - k[a]), int(-(k[a] + k[b]))): front * factors[0][:, a] * factors[1][:, b]
            for a, b in zip(*np.nonzero(keep), strict=True)}


def block_of(model: str, sector: tuple[int, int]) -> tuple[int, int]:
    """The reduced block (n2.n2_sectors) holding the sector (spin s, vorticity v):
    d'Alembert (|m1|, |m2|) with m1 = (s + v)/2, m2 = (s - v)/2; affine models the
    representative (s, k) of {(s, k), (-s, -k)}, k = -v, with s > 0 or s = 0, k >= 0."""
    s, v = sector
    if model == "dalembert":
        return abs(s + v) // 2, abs(s - v) // 2
    k = -v
    return (s, k) if s > 0 or (s == 0 and k >= 0) else (-s, -k)


def check_matrix_packet(model: str, packet: MatrixPacket) -> None:
    """One-line refusals of a packet evolve cannot represent: a width that is not positive;
    for the affine models (GL+(2), where the packet is the Gaussian times det phi restricted
    to det phi > 0) a centre with det phi <= 0."""
    w = packet.width
    if not (math.isfinite(w) and w > 0):
        raise ValueError(f"--width must be > 0 (got {w})")
    if model != "dalembert" and np.linalg.det(np.asarray(packet.phi, float)) <= 0:
        raise ValueError(f"--phi: the affine models live on GL+(2): the packet's centre needs "
                         f"det phi > 0 (got {np.linalg.det(np.asarray(packet.phi, float)):.4g})")


def evolve_matrix_packet(potential: Potential, hbar: float, inertia: float, settings: Settings,
                         packet: MatrixPacket, times: np.ndarray, progress=None, *,
                         model: str = "dalembert", I: float = 1.0,  # noqa: E741
                         A: float = 0.0, B: float = 0.0) -> Evolution:
    """The evolution of a :class:`MatrixPacket` (n = 2; d'Alembert with J = inertia Id, or an
    affine model with I, A, B) by its expansion in the eigenstates of every sector it
    populates: psi_(s,v) of :func:`packet_harmonics` projected on the sector's eigenvectors
    (the block :func:`block_of`, solved densely by :func:`sector_spectrum` with the scales of
    the block (0, 0) for every block)."""
    require_x64()
    check_matrix_packet(model, packet)
    times = np.asarray(times, float)
    size = settings.basis_size
    kind = "lebesgue2" if model == "dalembert" else "haar2"
    constants = dict(inertia=inertia, I=I, A=A, B=B)
    # the states of the bases (and so psi(t)) live where the highest state of (0, 0) does
    first = sector_spectrum(model, potential, hbar, settings=settings, **constants)
    settings = replace(settings, scale=first.settings["scale"],  # one scale for every block
                       scale_sigma=first.settings.get("scale_sigma"),
                       centre=first.settings.get("centre"))
    box = joint_density(first, first.levels[-1]).box
    r = np.linalg.svd(np.asarray(packet.phi, float), compute_uv=False)
    x, w = np.polynomial.legendre.leggauss(NODES + 2 * size)
    if kind == "lebesgue2":
        reach = float(np.sum(r)) / 2 + REACH * packet.width  # |z|, |w| <= (Q1 + |Q2|) / 2 + ..
        lo, hi = np.zeros(2), np.full(2, max(reach, float(np.max(box[:, 1]))))
    else:  # x = q1 - q2, sigma = q1 + q2 over Q in [Q2 - 10 w, Q1 + 10 w] (and > Q2 / 10)
        low = math.log(max(r[1] - REACH * packet.width, r[1] / 10))
        high = math.log(r[0] + REACH * packet.width)
        lo = np.array([0.0, min(2 * low, box[1, 0])])
        hi = np.array([max(high - low, box[0, 1]), max(2 * high, box[1, 1])])
    axes = [lo[k] + (hi[k] - lo[k]) * (x + 1) / 2 for k in range(2)]
    Y0, Y1 = np.meshgrid(*axes, indexing="ij")
    y = np.stack([Y0.ravel(), Y1.ravel()], -1)
    weights = np.outer(w, w).ravel() * np.prod(hi - lo) / 4 * measure(kind, y)
    harmonics = packet_harmonics(packet, y, hbar, kind)
    if kind == "haar2":  # the joint frame: amplitudes / g under the measure x (block_functions)
        g = sqrt_x_over_sinh(y[:, 0])
        harmonics = {key: h / g for key, h in harmonics.items()}
    total = sum(float(np.sum(weights * np.abs(h) ** 2)) for h in harmonics.values())
    keys: dict[tuple[int, int], list] = {}
    for sector, h in harmonics.items():
        keys.setdefault(block_of(model, sector), []).append((sector, h))
    if len(keys) > MAX_BLOCKS:
        raise ValueError(f"evolve: the packet populates {len(keys)} blocks of sectors (more than "
                         f"{MAX_BLOCKS}): give a smaller --pi or a larger hbar")
    check_work(size, len(times) * len(keys))
    parts = []
    for count, (key, members) in enumerate(sorted(keys.items())):
        if progress is not None:
            name = "(|m1|, |m2|)" if kind == "lebesgue2" else "(s, k)"
            progress(f"sector block {name} = {key} ({count + 1} of {len(keys)})")
        spectrum = first if key == (0, 0) else sector_spectrum(
            model, potential, hbar, settings=settings, key=key, **constants)
        levels = spectrum.levels
        functions, vectors = block_functions(spectrum, levels, y)
        E = np.array([lv.energy for lv in levels])
        errors = np.array([lv.error for lv in levels])
        labels = {(sec.spin, sec.vorticity) for sec in spectrum.blocks[key].sectors}
        for sector, _ in members:
            if sector not in labels:
                raise ValueError(f"evolve: sector {sector} is not one of the block {key}")
        H = np.stack([h for _, h in members], -1) * (weights / math.sqrt(total))[:, None]
        C = vectors.T @ (functions.T @ H.real + 1j * (functions.T @ H.imag))  # [S, members]
        parts.extend((C[:, i], E, errors, functions, vectors) for i in range(len(members)))
    result = _propagate(parts, model, y, weights, times, hbar)
    require_captured(result.captured)
    return result


__all__ = ["MAX_BASIS", "MAX_STEPS", "MAX_WORK", "VARIABLES", "sector_spectrum", "Packet",
           "variables_at", "check_packet", "check_work", "require_captured", "Evolution",
           "evolve", "spectrum_lines", "MatrixPacket", "packet_harmonics",
           "evolve_matrix_packet", "PACKET_ANGLES", "MAX_BLOCKS", "block_of",
           "check_matrix_packet",
           "block_functions", "MAX_PHASE", "check_phases",
]
