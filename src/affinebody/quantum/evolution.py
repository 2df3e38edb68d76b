"""Time evolution of a wave packet of one quantum affine body by its expansion in eigenstates
(paper, last section: amplitudes of the deformation invariants; docs/quantum-transitions.md).

The packet lives in the sector spin = vorticity = 0 of n = 2 (a state invariant under
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
the eigenvalues (nested and widened check bases) with the packet's populations: the accuracy of
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
    auto_scale_haar2,
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
    nested and widened check bases and is flagged converged or not). d'Alembert: ``key`` =
    (|m1|, |m2|) picks another block (the characters of z and w, n2.n2_sectors)."""
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
        bx, bs, c0 = auto_scale_haar2(potential, hbar, affine)
        bx, bs = settings.scale or bx, settings.scale_sigma or bs
        c0 = c0 if settings.centre is None else settings.centre
        info = {"scale": bx, "scale_sigma": bs, "centre": c0}

        def build(n, s):
            return haar2_block(potential, hbar, affine, 0, 0, (n, n), (s, bs * s / bx), c0)
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
    with np.errstate(divide="ignore", invalid="ignore"):
        psi = np.where(mu > 0, np.exp(-np.sum(d * d, -1) / (4 * packet.width**2)
                                      + 1j * (d @ p0) / hbar) / np.sqrt(np.where(mu > 0, mu, 1)),
                       0.0)
    psi /= math.sqrt(float(np.sum(weights * np.abs(psi) ** 2)))
    c = vectors.T @ (functions.T @ (weights * psi))
    captured = float(np.sum(np.abs(c) ** 2))
    if captured < 1 - CAPTURE:
        raise ValueError(f"evolve: the eigenstates of the basis hold only {captured:.6f} of the "
                         f"packet (it reaches energies or places the basis does not resolve): "
                         f"raise quantum.basis_size, or start the packet slower or nearer the "
                         f"minimum")
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




# ------------------------------------------- a packet around a classical (phi, pi), d'Alembert
#: the most angles per polar angle for the sector decomposition of a matrix packet
PACKET_ANGLES = 128
#: a sector holding less than this fraction of the packet is left out (its part is reported
#: in ``captured``)
SECTOR_FLOOR = 1e-12
#: the most blocks (|m1|, |m2|) one matrix packet may need
MAX_BLOCKS = 400


@dataclass(frozen=True)
class MatrixPacket:
    """A Gaussian in phi (d'Alembert, n = 2, J = inertia Id): |psi_0|^2 d^4 phi is the normal
    density of mean ``phi`` and standard deviation ``width`` per component, and the mean
    canonical momentum is ``pi`` (= inertia dphi/dt of the classical motion):

        psi_0(phi) = N exp(-|phi - phi0|^2 / (4 w^2) + i tr(pi0^T (phi - phi0)) / hbar).

    Spin and vorticity of the classical (phi0, pi0) make it a superposition of many sectors."""

    phi: tuple
    pi: tuple
    width: float


def _rotation(t: np.ndarray) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def packet_harmonics(packet: MatrixPacket, y: np.ndarray, hbar: float
                     ) -> dict[tuple[int, int], np.ndarray]:
    """(spin s, vorticity v) -> psi_(s,v)(y) [P]: the coefficient of e^{i(s alpha - v beta)} in
    psi_0(R(alpha) diag(Q(y)) R(beta)^T), by the trapezoidal rule on N^2 angles (exact for the
    harmonics it resolves; N = 32, 64, ... until the harmonics beyond N/2 - 4 hold less than
    1e-12 of the packet). With M = R(alpha)^T X R(beta), the exponent is
    -(|Q|^2 + |phi0|^2)/(4 w^2) - i tr(pi0^T phi0)/hbar + sum_j Q_j (M(phi0)_jj/(2 w^2)
    + i M(pi0)_jj/hbar), linear in Q at fixed angles."""
    Q = invariants_at("lebesgue2", y)
    phi0, pi0 = np.asarray(packet.phi, float), np.asarray(packet.pi, float)
    w2 = packet.width**2
    const = (-(np.sum(Q * Q, -1) + np.sum(phi0 * phi0)) / (4 * w2)
             - 1j * np.sum(pi0 * phi0) / hbar)
    N = 32
    while True:
        t = 2 * np.pi * np.arange(N) / N
        R = _rotation(t)
        A = phi0 / (2 * w2) + 1j * pi0 / hbar
        M = np.einsum("aji,jk,bkl->abil", R, A, R)  # R(alpha)^T A R(beta) [N, N, 2, 2]
        psi = np.exp(const[:, None, None] + Q[:, 0, None, None] * M[None, :, :, 0, 0]
                     + Q[:, 1, None, None] * M[None, :, :, 1, 1])
        F = np.fft.fft2(psi, axes=(1, 2)) / N**2
        mass = np.sum(np.abs(F) ** 2, 0)
        k = np.fft.fftfreq(N, 1 / N).astype(int)
        K, L = np.meshgrid(k, k, indexing="ij")
        edge = (np.abs(K) > N // 2 - 4) | (np.abs(L) > N // 2 - 4)
        if np.sum(mass[edge]) <= 1e-12 * np.sum(mass):
            break
        if N >= PACKET_ANGLES:
            raise ValueError("evolve: the packet's angular momentum (spin, vorticity) exceeds "
                             f"what {N} angles resolve: give a smaller --pi or a larger hbar")
        N *= 2
    keep = mass > SECTOR_FLOOR * np.max(mass)
    # e^{-i(k alpha + l beta)} picks the state e^{i(s alpha - v beta)} with s = k, v = -l
    return {(int(K[a, b]), int(-L[a, b])): F[:, a, b] for a, b in zip(*np.nonzero(keep),
                                                                      strict=True)}


def evolve_matrix_packet(potential: Potential, hbar: float, inertia: float, settings: Settings,
                         packet: MatrixPacket, times: np.ndarray, progress=None) -> Evolution:
    """The evolution of a :class:`MatrixPacket` of the d'Alembert body (n = 2) by its expansion
    in the eigenstates of every sector it populates: psi_(s,v) of
    :func:`packet_harmonics` projected on the sector's eigenvectors (the blocks (|m1|, |m2|) of
    n2, m1 = (s + v)/2, m2 = (s - v)/2, solved densely by :func:`sector_spectrum`)."""
    require_x64()
    if not (math.isfinite(packet.width) and packet.width > 0):
        raise ValueError(f"--width must be > 0 (got {packet.width})")
    times = np.asarray(times, float)
    size = settings.basis_size
    r = np.linalg.svd(np.asarray(packet.phi, float), compute_uv=False)
    reach = float(np.sum(r)) / 2 + 10 * packet.width  # |z|, |w| <= (Q1 + |Q2|) / 2 + ...
    # the states of the bases (and so psi(t)) live where the highest state of (0, 0) does
    first = sector_spectrum("dalembert", potential, hbar, inertia=inertia, settings=settings)
    settings = replace(settings, scale=first.settings["scale"])  # one scale for every block
    R_hi = max(reach, float(np.max(joint_density(first, first.levels[-1]).box[:, 1])))
    x, w = np.polynomial.legendre.leggauss(NODES + 2 * size)
    r1 = R_hi * (x + 1) / 2
    Y0, Y1 = np.meshgrid(r1, r1, indexing="ij")
    y = np.stack([Y0.ravel(), Y1.ravel()], -1)
    weights = np.outer(w, w).ravel() * (R_hi / 2) ** 2 * measure("lebesgue2", y)
    harmonics = packet_harmonics(packet, y, hbar)
    total = sum(float(np.sum(weights * np.abs(h) ** 2)) for h in harmonics.values())
    keys: dict[tuple[int, int], list] = {}
    for (s, v), h in harmonics.items():
        keys.setdefault((abs(s + v) // 2, abs(s - v) // 2), []).append(((s, v), h))
    if len(keys) > MAX_BLOCKS:
        raise ValueError(f"evolve: the packet populates {len(keys)} blocks of sectors (more than "
                         f"{MAX_BLOCKS}): give a smaller --pi or a larger hbar")
    check_work(size, len(times) * len(keys))
    parts = []
    for key, members in sorted(keys.items()):
        if progress is not None:
            progress(f"sector block (|m1|, |m2|) = {key}")
        spectrum = first if key == (0, 0) else sector_spectrum(
            "dalembert", potential, hbar, inertia=inertia, settings=settings, key=key)
        levels = spectrum.levels
        functions, vectors = block_functions(spectrum, levels, y)
        E = np.array([lv.energy for lv in levels])
        errors = np.array([lv.error for lv in levels])
        labels = {(sec.spin, sec.vorticity) for sec in spectrum.blocks[key].sectors}
        for sector, h in members:
            if sector not in labels:
                raise ValueError(f"evolve: sector {sector} is not one of the block {key}")
            c = vectors.T @ (functions.T @ (weights * h)) / math.sqrt(total)
            parts.append((c, E, errors, functions, vectors))
    result = _propagate(parts, "dalembert", y, weights, times, hbar)
    if result.captured < 1 - CAPTURE:
        raise ValueError(f"evolve: the eigenstates of the bases hold only {result.captured:.6f} "
                         f"of the packet: raise quantum.basis_size, or start it slower or nearer "
                         f"the minimum")
    return result


__all__ = ["MAX_BASIS", "MAX_STEPS", "MAX_WORK", "VARIABLES", "sector_spectrum", "Packet",
           "variables_at", "check_packet", "check_work", "Evolution", "evolve", "spectrum_lines",
           "MatrixPacket", "packet_harmonics", "evolve_matrix_packet", "PACKET_ANGLES",
           "MAX_BLOCKS"]
