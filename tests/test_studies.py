"""The paper's claims about bounded motion (text around (78)-(81)) as sweeps, at small size.

Sweeps run in this process (``workers=0``; the Dask path is tested in test_sweep.py). Every
expectation is derived independently of the simulator: closed forms of the geodesics
exp(t S/(I + A)) (docs/theory/exact-flows.md, af-is/af-af drifts), scipy's expm, spectra,
energy bounds, and Monte Carlo with numpy for the predicted fractions. docs/studies.md runs the
same at full size.
"""

import math

import numpy as np
import pytest
from scipy.linalg import expm

from affinebody.studies import (
    SHAPE_POTENTIAL,
    dilatation_fraction,
    sl2_isotropic_fraction,
    sweep_config,
)
from affinebody.sweep import run_sweep

BOUND = 1000.0


def run(config):
    return run_sweep(config, workers=0)


def spin(omega, i, a):
    """S = I Omega^T + A Omega (traceless Omega): dT/dOmega^T of (72)-(74) (af-af: I = 0)."""
    return i * np.swapaxes(omega, -1, -2) + a * omega


def sl2_decided(generator, horizon):
    """Which samples the closed form exp(t G) decides at ``horizon``, and how (True: bounded).

    Elliptic G (det G = w^2 > 0): exp(tG) = cos(wt) Id + sin(wt)/w G has sigma_max and
    sigma_max of its inverse <= 1 + |G|_2 / w. Hyperbolic G: sigma_max(exp(TG)) >= e^{wT}."""
    det = np.linalg.det(generator)
    norm = np.linalg.norm(generator, 2, axis=(-2, -1))
    w = np.sqrt(np.abs(det))
    surely_bounded = (det > 0) & (1 + norm / np.where(w > 0, w, 1e-300) < BOUND)
    surely_unbounded = (det < 0) & (w * horizon >= math.log(BOUND) + 1e-9)
    return surely_bounded | surely_unbounded, surely_bounded


def test_predicted_sl2_fractions_agree_with_monte_carlo():
    rng = np.random.default_rng(0)
    z = rng.standard_normal((400_000, 2, 2))
    omega = z - np.trace(z, axis1=1, axis2=2)[:, None, None] / 2 * np.eye(2)
    for i, a in ((0.0, 1.0), (1.0, 0.5), (1.0, -0.5), (2.0, 0.3)):
        mc = np.mean(np.linalg.det(spin(omega, i, a)) > 0)
        assert abs(mc - sl2_isotropic_fraction(i, a)) < 5 * math.sqrt(0.25 / 400_000)
    assert sl2_isotropic_fraction(0.0, 1.0) == pytest.approx(1 - 1 / math.sqrt(2))
    tr = 0.7 * np.trace(z, axis1=1, axis2=2)
    for i, a, b in ((1.0, -0.5, 0.0), (1.0, 0.5, 1.0)):
        mc = np.mean((i + a + 2 * b) * tr**2 / 4 < 1.0)
        assert abs(mc - dilatation_fraction(i, a, b, 1.0, 0.7)) < 5 * math.sqrt(0.25 / 400_000)


def test_af_af_on_sl2_is_bounded_exactly_for_elliptic_velocities():
    """(72) on SL(2): phi(t) = phi0 exp(t Omega_hat), bounded iff det Omega_hat > 0; the bounded
    fraction of normal Omega_hat is 1 - 1/sqrt 2 (an open set, and so is its complement)."""
    horizon, samples = 40.0, 300
    result = run(sweep_config(internal="af-af", kinetic={"A": 1.0, "B": 0.5}, dt=0.5,
                              steps=80, samples=samples, batch=150))
    omega = result.samples["omega_hat"][0, :, 0]
    status = result.status[0]
    decided, bounded = sl2_decided(omega, horizon)
    assert decided.mean() > 0.95
    np.testing.assert_array_equal(status[decided] == "bounded", bounded[decided])
    fraction = result.summary["points"][0]["fraction_bounded"]
    predicted = 1 - 1 / math.sqrt(2)
    assert abs(fraction - predicted) < 4 * math.sqrt(predicted * (1 - predicted) / samples)
    # doubling the horizon (T/2 -> T) only turns slow hyperbolic samples unbounded
    exit_time = result.samples["exit_time"][0]
    changed = np.isfinite(exit_time) & (exit_time > horizon / 2)
    det = np.linalg.det(omega[changed])
    assert np.all(det < 0)
    # sigma_max(exp(t Omega)) >= e^{wt}: only samples with w T/2 < ln(bound) can change
    assert np.all(np.sqrt(-det) * horizon / 2 < math.log(BOUND))
    assert changed.sum() <= 0.1 * samples
    # exact flow: energy kept to round-off, eps |Omega|^2 (E = -A det Omega) times the
    # condition number^2 reached by phi
    drift = np.abs(result.samples["final_energy"][0] - result.samples["initial_energy"][0])
    scale = np.sum(omega**2, axis=(1, 2)) * result.samples["max_spread"][0] ** 2
    assert np.all(drift[status == "bounded"] < 100 * 2.2e-16 * scale[status == "bounded"])


def test_af_is_on_sl2_bounded_fraction_depends_on_i_and_a_as_predicted():
    """(74) on SL(2): phi(t) = phi0 exp(t S/(I + A)) R(t), bounded iff det S > 0, fraction
    1 - rho/sqrt(1 + rho^2), rho = (I + A)/(I - A); B plays no role on SL(n)."""
    horizon, samples = 40.0, 200
    result = run(sweep_config(internal="af-is", kinetic={"I": 1.0, "A": 0.0, "B": 0.7}, dt=0.5,
                              steps=80, samples=samples, batch=200,
                              scan={"kinetic.A": [-0.5, 0.5]}))
    for point in result.points:
        a = point.parameter_dict["kinetic.A"]
        omega = result.samples["omega_hat"][point.index, :, 0]
        decided, bounded = sl2_decided(spin(omega, 1.0, a) / (1.0 + a), horizon)
        status = result.status[point.index]
        assert decided.mean() > 0.9
        np.testing.assert_array_equal(status[decided] == "bounded", bounded[decided])
        predicted = sl2_isotropic_fraction(1.0, a)
        fraction = result.summary["points"][point.index]["fraction_bounded"]
        assert abs(fraction - predicted) < 4 * math.sqrt(predicted * (1 - predicted) / samples)


def test_af_af_on_sl3_bounded_set_shrinks_with_the_horizon():
    """(72) on SL(3): the sweep agrees with scipy's expm sample by sample; bounded up to T
    forces every eigenvalue of Omega_hat within ln(bound)/T of the imaginary axis (no open set
    survives T -> infinity)."""
    dt, steps, samples = 0.5, 80, 100
    horizon = dt * steps
    result = run(sweep_config(n=3, internal="af-af", kinetic={"A": 1.0}, dt=dt, steps=steps,
                              samples=samples, batch=100))
    status = result.status[0]
    exit_time = result.samples["exit_time"][0]
    times = dt * np.arange(1, steps + 1)
    for k in range(samples):
        omega = result.samples["omega_hat"][0, k, 0]
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            # long after the exit exp(t Omega) overflows: those times are cut off below
            sigma = np.linalg.svd(np.nan_to_num(expm(times[:, None, None] * omega)),
                                  compute_uv=False)
            spreads = np.maximum(sigma[:, 0], 1 / sigma[:, -1])
        over = np.flatnonzero(spreads >= BOUND)
        spreads = spreads[: over[0] + 1] if over.size else spreads
        if np.min(np.abs(spreads / BOUND - 1)) < 1e-9:
            continue  # a tie with the bound: either answer is right
        if spreads[-1] >= BOUND:
            assert status[k] == "unbounded"
            assert exit_time[k] == pytest.approx(dt * len(spreads), abs=1e-12)
        else:
            assert status[k] == "bounded"
            real = np.linalg.eigvals(omega).real
            assert np.max(np.abs(real)) < math.log(BOUND) / horizon
    early = np.mean((status == "bounded") | (exit_time > horizon / 4))
    assert np.mean(status == "bounded") < early


def test_gl2_dilatation_is_held_by_a_well_exactly_below_its_depth():
    """(74) on GL(2) with V = D (1 - exp(-(ln det)^2/2)): the dilatation decouples with energy
    E = (I + A + 2B)(Tr Omega)^2/4; below D, |ln det| stays under the turning point
    sqrt(-2 ln(1 - E/D)); above, the volume escapes (judged on elliptic shapes, whose spread
    cannot reach the bound first)."""
    depth, scale = 1.0, 1.0
    result = run(sweep_config(group="GL+", internal="af-is", kinetic={"I": 1.0, "A": -0.5},
                              potentials=[{"kind": "dilatation",
                                           "expr": "1.0*(1 - exp(-log(det)**2/2))"}],
                              dt=0.05, steps=400, samples=64, batch=64, velocity_scale=scale))
    omega = result.samples["omega_hat"][0, :, 0]
    trace = np.trace(omega, axis1=1, axis2=2)
    energy = 0.5 * trace**2 / 4
    log_det = np.maximum(np.log(result.samples["max_det"][0]),
                         -np.log(result.samples["min_det"][0]))
    traceless = omega - trace[:, None, None] / 2 * np.eye(2)
    elliptic = np.linalg.det(spin(traceless, 1.0, -0.5)) > 0
    assert not np.any(result.status[0] == "failed")
    below = energy < 0.8 * depth
    # Strang's energy error at dt = 0.05 (omega = 2 for this dilatation) is below 1%
    turning = np.sqrt(-2 * np.log1p(-1.01 * energy[below] / depth))
    assert np.all(log_det[below] <= turning)
    assert np.all(log_det[below] >= 0.9 * np.sqrt(-2 * np.log1p(-energy[below] / depth)))
    above = (energy > 1.3 * depth) & elliptic
    assert above.sum() >= 3 and below.sum() >= 20
    assert np.all(log_det[above] >= math.log(BOUND))
    assert np.all(result.status[0][above] == "unbounded")


@pytest.mark.parametrize("with_81", [False, True], ids=["binary", "binary+(81)"])
def test_binary_potential_bounds_relative_volumes_and_81_bounds_single_volumes(with_81):
    """Two af-is bodies (I = 2, A = 0.5, B = 0.3) on GL(2), binary f = (1/2)(ln det Gamma)^2
    (78), (79) and a volume-neutral shape term. Energy bound |ln det Gamma| <= sqrt(2E).
    Without (81), global scaling is a symmetry: ln det phi_1 + ln det phi_2 = t Tr(Omega_1 +
    Omega_2) exactly, so the single volumes grow linearly; with (81) (1/2)(ln det phi_K)^2,
    |ln det phi_K| <= sqrt(2E) and every sample is bounded."""
    potentials = [{"kind": "pair", "expr": "0.5*log(det)**2"}, SHAPE_POTENTIAL]
    if with_81:
        potentials.append({"kind": "dilatation", "stiffness": 1.0})
    dt, steps = 0.05, 400
    horizon = dt * steps
    result = run(sweep_config(group="GL+", internal="af-is", kinetic={"I": 2.0, "A": 0.5,
                                                                      "B": 0.3},
                              bodies=2, potentials=potentials, dt=dt, steps=steps, samples=32,
                              batch=32, velocity_scale=0.3))
    s = result.samples
    energy = s["initial_energy"][0]
    assert not np.any(result.status[0] == "failed")
    assert np.all(s["followed_time"][0] == pytest.approx(horizon))
    assert np.all(s["energy_error"][0] < 1e-3)
    assert np.all(np.log(s["max_relative_volume"][0]) <= np.sqrt(2 * energy) * 1.001)
    log_volume = np.maximum(np.log(s["max_det"][0]), -np.log(s["min_det"][0]))
    if with_81:
        assert np.all(log_volume <= np.sqrt(2 * energy) * 1.001)
        assert np.all(result.status[0] == "bounded")
    else:
        rate = np.abs(np.trace(s["omega_hat"][0].sum(axis=1), axis1=1, axis2=2))
        slack = np.sqrt(2 * energy) * 1.001
        assert np.all(log_volume >= (horizon * rate - slack) / 2 - 1e-9)
        assert np.all(log_volume <= (horizon * rate + slack) / 2 + 1e-9)
        assert np.any(log_volume > math.log(BOUND))  # single volumes leave the bound
