"""The paper's claims about bounded affine motion (text around (78)-(81)) as reproducible sweeps.

Each study builds a config with a ``[sweep]`` table, runs it with :func:`affinebody.sweep.run_sweep`
(through a ``runner``: in this process for the tests, on a Dask cluster for the docs) and compares
the bounded fractions with predictions derived independently of the simulator:

- :func:`sl2_isotropic_fraction`: on SL(2) the geodesics of af-af (72), af-is (74) and is-af (73)
  are phi(t) = phi0 exp(t S/(I + A)) R(t) (af-is; is-af: R(t) exp(t S/(I + A)) phi0) with R(t)
  a rotation and S = I Omega^T + A Omega the affine spin of the initial velocity (af-af: I = 0),
  so a motion is bounded iff exp(t S) is, iff det S > 0 (S elliptic). For Omega the projection
  onto sl(2) of a matrix with i.i.d. N(0, 1) entries, (sym, skew) coordinates of Omega are
  i.i.d. N(0, 1/2), and P(det S > 0) = 1 - rho / sqrt(1 + rho^2), rho = |I + A| / |I - A|
  (af-af: 1 - 1/sqrt 2 = 0.2929).
- On SL(n), n >= 3, exp(t S) is bounded iff S is diagonalisable with imaginary eigenvalues,
  a condition of codimension 1 in sl(n): bounded geodesics have no interior, and the fraction
  bounded up to a horizon T decays like 1/T (:func:`sl3_study`).
- On GL(n) the dilatation q = ln(det phi)/n decouples (docs/theory/exact-flows.md): for
  (72)-(74) the kinetic energy is T_sl(traceless part) + n (I + A + nB) q'^2 / 2 (af-af:
  I = 0), so ln det phi moves freely (unbounded) unless a potential V(det phi) (80), (81)
  holds it; a well of depth D holds it iff the dilatational energy
  (I + A + nB) (Tr Omega)^2 / (2n) is below D (:func:`dilatation_fraction`), and the shape
  still moves as on SL(n).
- Two bodies with a binary affine potential (78): relative volumes (79) bounded, single volumes
  not; with (81) both bounded (:func:`binary_study`).

Run ``python -m affinebody.studies --out docs`` to regenerate docs/figures/*.png and the numbers
quoted in docs/studies.md (printed as JSON).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from affinebody.config import Config, check_config, parse_config
from affinebody.sweep import SweepResult, binomial_summary, run_sweep

Runner = Callable[[Config], SweepResult]


def inline_runner() -> Runner:
    """Run sweeps in this process (no Dask)."""
    return lambda config: run_sweep(config, workers=0)


def client_runner(client) -> Runner:
    """Run sweeps on a Dask client's cluster."""
    return lambda config: run_sweep(config, client=client)


# --------------------------------------------------------------------------- configs
def _toml_value(value) -> str:
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) \
            + " }"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value)
    return repr(float(value)) if isinstance(value, float) else str(value)


def sweep_config(*, n: int = 2, group: str = "SL", internal: str = "af-af",
                 kinetic: dict | None = None, potentials: Sequence[dict] = (), bodies: int = 1,
                 dt: float = 0.25, steps: int = 400, samples: int = 1000, seed: int = 0,
                 velocity_scale: float = 1.0, bound: float = 1000.0, batch: int = 250,
                 scan: dict | None = None) -> Config:
    """A checked config: ``bodies`` identical bodies at rest at phi = Id (spaced by 3 along x1)
    with random internal velocities Omega_hat (the [sweep] table)."""
    kinetic = {"A": 1.0} if kinetic is None else kinetic
    lines = ["[system]", f"n = {n}", f'group = "{group}"', f"bodies = {bodies}",
             "[body]", "mass = 1.0", "[kinetic]", f'internal = "{internal}"']
    lines += [f"{k} = {_toml_value(float(v))}" for k, v in kinetic.items()]
    for entry in potentials:
        lines.append("[[potential]]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in entry.items()]
    x = [[3.0 * k] + [0.0] * (n - 1) for k in range(bodies)]
    lines += ["[initial]", f"x = {_toml_value(x)}", "[run]", f"dt = {dt!r}", f"steps = {steps}",
              "[sweep]", f"samples = {samples}", f"seed = {seed}", 'initial_velocity = "normal"',
              f"velocity_scale = {velocity_scale!r}", f"bound = {bound!r}", f"batch = {batch}"]
    if scan:
        lines.append(f"scan = {_toml_value(scan)}")
    return check_config(parse_config("\n".join(lines) + "\n", "study"))


# --------------------------------------------------------------------------- predictions
def sl2_isotropic_fraction(I: float, A: float) -> float:  # noqa: E741
    """P(det(I Omega^T + A Omega) > 0) for Omega = P_sl(Z), Z with i.i.d. N(0, 1) entries:
    the bounded fraction of geodesics of af-is / is-af (I, A) on SL(2); af-af is I = 0."""
    rho = abs(I + A) / abs(I - A)
    return 1.0 - rho / math.sqrt(1.0 + rho * rho)


def affine_spin_of_velocity(omega: np.ndarray, I: float, A: float, B: float = 0.0) -> np.ndarray:  # noqa: E741
    """S = I Omega^T + A Omega + B Tr(Omega) Id, the affine spin of (73)/(74) (af-af: I = 0),
    computed here with numpy from the Lagrangian, not from the library's Legendre maps."""
    omega = np.asarray(omega)
    n = omega.shape[-1]
    tr = np.trace(omega, axis1=-2, axis2=-1)[..., None, None]
    return I * np.swapaxes(omega, -1, -2) + A * omega + B * tr * np.eye(n)


def exp_spread(generator: np.ndarray, times: np.ndarray) -> np.ndarray:
    """max over ``times`` of max(sigma_max, 1/sigma_min) of expm(t X), per generator X [..., n, n]
    (scipy's expm: an independent evaluation of the geodesics exp(t X))."""
    from scipy.linalg import expm

    generator = np.asarray(generator)
    out = np.empty(generator.shape[:-2])
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        for index in np.ndindex(out.shape):
            mats = expm(times[:, None, None] * generator[index])
            sigma = np.linalg.svd(np.nan_to_num(mats, posinf=1e300, neginf=-1e300),
                                  compute_uv=False)
            out[index] = np.max(np.maximum(sigma[:, 0], 1.0 / sigma[:, -1]))
    return out


def dilatation_fraction(I: float, A: float, B: float, depth: float, scale: float,  # noqa: E741
                        n: int = 2) -> float:
    """P((I + A + nB) (Tr Omega)^2 / (2n) < depth) for Omega = scale Z, Z i.i.d. N(0, 1):
    Tr Omega ~ N(0, n scale^2). The fraction of samples whose volume a well of depth D holds."""
    mass = I + A + n * B
    limit = math.sqrt(2.0 * n * depth / mass)
    return math.erf(limit / (scale * math.sqrt(2.0 * n)))


def fraction_at(result: SweepResult, point: int, horizon: float) -> dict:
    """The bounded fraction of one point judged up to ``horizon`` (<= the sweep's): a sample is
    unbounded at T when its exit time is <= T (failed samples excluded)."""
    status = result.status[point]
    exit_time = result.samples["exit_time"][point]
    classified = status != "failed"
    unbounded = classified & np.isfinite(exit_time) & (exit_time <= horizon * (1 + 1e-12))
    return {"horizon": horizon, **binomial_summary(int(np.sum(classified & ~unbounded)),
                                                   int(np.sum(classified)))}


def _z(measured: dict, predicted: float) -> float:
    sigma = math.sqrt(predicted * (1 - predicted) / max(1, _trials(measured)))
    return (measured["fraction"] - predicted) / sigma if sigma > 0 else math.nan


def _trials(measured: dict) -> int:
    return int(measured.get("trials", 0))


def _with_trials(summary: dict, trials: int) -> dict:
    return {**summary, "trials": trials}


# --------------------------------------------------------------------------- studies
@dataclass(frozen=True)
class Sizes:
    """Sample counts and horizons of the studies (tests use small ones)."""

    samples: int = 2000
    horizon: float = 100.0
    dt: float = 0.25
    well_dt: float = 0.05
    sl3_samples: int = 1000
    sl3_horizon: float = 200.0
    check_samples: int = 100
    sl3_models: int = 5


def sl2_study(run: Runner, sizes: Sizes = Sizes()) -> dict:
    """Studies 1 and 2 of docs/studies.md: af-af, af-is and is-af geodesics on SL(2).

    af-af with A = 1: bounded fraction at T/2 and T vs 1 - 1/sqrt 2, and the per-sample rule
    det(Omega_hat) > 0. af-is and is-af with I = 1 and A in {-0.8, -0.5, 0, 0.5, 0.8}:
    bounded fractions vs 1 - rho/sqrt(1 + rho^2) and the per-sample rule det S > 0.
    """
    steps = int(round(sizes.horizon / sizes.dt))
    out: dict = {"horizon": sizes.horizon, "samples": sizes.samples}
    afaf = run(sweep_config(internal="af-af", kinetic={"A": 1.0, "B": 0.5}, dt=sizes.dt,
                            steps=steps, samples=sizes.samples))
    omega = afaf.samples["omega_hat"][0, :, 0]
    det = np.linalg.det(omega)
    classified = afaf.status[0] != "failed"
    predicted = sl2_isotropic_fraction(0.0, 1.0)
    half = _with_trials(fraction_at(afaf, 0, sizes.horizon / 2), int(classified.sum()))
    full = _with_trials(fraction_at(afaf, 0, sizes.horizon), int(classified.sum()))
    exit_time = afaf.samples["exit_time"][0]
    changed = int(np.sum(classified & np.isfinite(exit_time) & (exit_time > sizes.horizon / 2)))
    out["af-af"] = {
        "predicted": predicted, "half_horizon": half, "horizon_fraction": full,
        "z": _z(full, predicted), "changed_on_doubling": changed,
        "rule_agreement": float(np.mean((det > 0) == (afaf.status[0] == "bounded"))),
        "failed": int(np.sum(~classified)),
        "energy_error_median_bounded": float(np.median(
            afaf.samples["energy_error"][0][afaf.status[0] == "bounded"])),
        "det": det, "status": afaf.status[0], "norm": np.linalg.norm(omega, axis=(-2, -1)),
    }
    values = [-0.8, -0.5, 0.0, 0.5, 0.8]
    iso = run(sweep_config(internal="af-is", kinetic={"I": 1.0, "A": 0.0, "B": 0.0},
                           dt=sizes.dt, steps=steps, samples=sizes.samples,
                           scan={"kinetic.internal": ["af-is", "is-af"], "kinetic.A": values}))
    rows = []
    for point in iso.points:
        parameters = point.parameter_dict
        model, a = parameters["kinetic.internal"], parameters["kinetic.A"]
        p = point.index
        ok = iso.status[p] != "failed"
        measured = _with_trials(fraction_at(iso, p, sizes.horizon), int(ok.sum()))
        spin = affine_spin_of_velocity(iso.samples["omega_hat"][p, :, 0], 1.0, a)
        rule = np.linalg.det(spin) > 0
        prediction = sl2_isotropic_fraction(1.0, a)
        rows.append({"model": model, "I": 1.0, "A": a, "predicted": prediction,
                     "measured": measured, "z": _z(measured, prediction),
                     "rule_agreement": float(np.mean(rule == (iso.status[p] == "bounded"))),
                     "failed": int(np.sum(~ok))})
    out["isotropic"] = rows
    return out


def sl3_study(run: Runner, sizes: Sizes = Sizes()) -> dict:
    """Study 3 of docs/studies.md: af-af, af-is and is-af geodesics on SL(3) for several (I, A).

    The bounded fraction judged at horizons T/8, T/4, T/2, T (exit times of one run to T);
    fraction * T staying roughly constant shows the 1/T decay (no interior). Per-sample check on
    ``check_samples`` samples: the sweep's classification equals that of scipy's
    exp(t S/(I + A)) at the same step times.
    """
    steps = int(round(sizes.sl3_horizon / sizes.dt))
    models = [("af-af", 0.0, 1.0), ("af-is", 1.0, 0.5), ("af-is", 1.0, -0.5), ("is-af", 1.0, -0.5),
              ("is-af", 1.0, -0.8)][: sizes.sl3_models]
    times = sizes.dt * np.arange(0, steps + 1)
    out: dict = {"horizon": sizes.sl3_horizon, "samples": sizes.sl3_samples, "models": []}
    for model, i, a in models:
        kinetic = {"A": a if model != "af-af" else 1.0, "B": 0.0}
        if model != "af-af":
            kinetic["I"] = i
        result = run(sweep_config(n=3, internal=model, kinetic=kinetic, dt=sizes.dt, steps=steps,
                                  samples=sizes.sl3_samples))
        ok = result.status[0] != "failed"
        horizons = [sizes.sl3_horizon / 8, sizes.sl3_horizon / 4, sizes.sl3_horizon / 2,
                    sizes.sl3_horizon]
        fractions = [_with_trials(fraction_at(result, 0, h), int(ok.sum())) for h in horizons]
        count = min(sizes.check_samples, sizes.sl3_samples)
        omega = result.samples["omega_hat"][0, :count, 0]
        inertia_i = 0.0 if model == "af-af" else i
        generator = affine_spin_of_velocity(omega, inertia_i, kinetic["A"]) / (inertia_i
                                                                               + kinetic["A"])
        spread = exp_spread(generator, times)
        independent = spread < result.spec.bound
        sweep_bounded = result.status[0, :count] == "bounded"
        eig = np.linalg.eigvals(affine_spin_of_velocity(
            result.samples["omega_hat"][0, :, 0], inertia_i, kinetic["A"]))
        real = np.max(np.abs(eig.real), axis=-1) / np.max(np.abs(eig), axis=-1)
        out["models"].append({
            "model": model, "I": inertia_i, "A": kinetic["A"], "fractions": fractions,
            "rule_agreement": float(np.mean(independent == sweep_bounded)),
            "checked": count, "failed": int(np.sum(~ok)),
            "max_relative_real_part_of_bounded": float(np.max(
                real[result.status[0] == "bounded"], initial=0.0)),
        })
    return out


def gl2_study(run: Runner, sizes: Sizes = Sizes(), depth: float = 1.0, width: float = 1.0,
              scale: float = 1.0) -> dict:
    """Study 4 of docs/studies.md: geodesics on GL(2) (unbounded dilatation), then V(det phi).

    1. af-af (A = 1, B = 0.5), no potential: bounded fraction at T/4, T/2, T (-> 0 like 1/T);
       ln det phi(T) = T Tr(Omega_hat) exactly.
    2. af-af + (81) V = k/2 (ln det)^2: every volume bounded; bounded fraction = the SL(2) one.
    3. af-is (I = 1, A in {-0.5, 0.5}, B in {0, 1, 3}) + a well V = D (1 - exp(-(ln det)^2/(2w^2)))
       of depth D: volume bounded iff the dilatational energy (I + A + 2B)(Tr Omega)^2/4 < D;
       bounded fraction = P(E_dil < D) * P(SL(2) elliptic).
    """
    out: dict = {"depth": depth, "width": width, "scale": scale}
    steps = int(round(sizes.horizon / sizes.dt))
    free = run(sweep_config(group="GL+", internal="af-af", kinetic={"A": 1.0, "B": 0.5},
                            dt=sizes.dt, steps=steps, samples=sizes.samples))
    ok = free.status[0] != "failed"
    trace = np.trace(free.samples["omega_hat"][0, :, 0], axis1=-2, axis2=-1)
    log_det_end = np.log(np.where(trace > 0, free.samples["max_det"][0],
                                  free.samples["min_det"][0]))
    followed = free.samples["followed_time"][0]
    out["geodesic"] = {
        "fractions": [_with_trials(fraction_at(free, 0, sizes.horizon * f), int(ok.sum()))
                      for f in (0.25, 0.5, 1.0)],
        # det phi(t) = exp(t Tr Omega_hat): extreme at the end of the followed time
        "log_det_error": float(np.max(np.abs(log_det_end - followed * trace)[ok])),
        "failed": int(np.sum(~ok)),
    }
    well_steps = int(round(sizes.horizon / sizes.well_dt))
    harmonic = run(sweep_config(group="GL+", internal="af-af", kinetic={"A": 1.0, "B": 0.5},
                                potentials=[{"kind": "dilatation", "stiffness": 1.0}],
                                dt=sizes.well_dt, steps=well_steps, samples=sizes.samples))
    ok = harmonic.status[0] != "failed"
    summary = harmonic.summary["points"][0]
    omega = harmonic.samples["omega_hat"][0, :, 0]
    traceless = omega - np.trace(omega, axis1=-2, axis2=-1)[:, None, None] / 2 * np.eye(2)
    out["harmonic"] = {
        "fraction_volume_bounded": summary["fraction_volume_bounded"],
        "measured": _with_trials(fraction_at(harmonic, 0, sizes.horizon), int(ok.sum())),
        "predicted": sl2_isotropic_fraction(0.0, 1.0),
        "rule_agreement": float(np.mean((np.linalg.det(traceless) > 0)
                                        == (harmonic.status[0] == "bounded"))),
        "failed": int(np.sum(~ok)),
        "energy_error_median": summary["energy_error_median"],
    }
    out["harmonic"]["z"] = _z(out["harmonic"]["measured"], out["harmonic"]["predicted"])
    expr = f"{depth!r}*(1 - exp(-log(det)**2/(2*{width!r}**2)))"
    well = run(sweep_config(group="GL+", internal="af-is", kinetic={"I": 1.0, "A": 0.5, "B": 0.0},
                            potentials=[{"kind": "dilatation", "expr": expr}],
                            dt=sizes.well_dt, steps=well_steps, samples=sizes.samples,
                            velocity_scale=scale,
                            scan={"kinetic.A": [-0.5, 0.5], "kinetic.B": [0.0, 1.0, 3.0]}))
    rows = []
    for point in well.points:
        a, b = point.parameter_dict["kinetic.A"], point.parameter_dict["kinetic.B"]
        p = point.index
        ok = well.status[p] != "failed"
        omega = well.samples["omega_hat"][p, :, 0]
        energy = (1.0 + a + 2 * b) * np.trace(omega, axis1=-2, axis2=-1) ** 2 / 4.0
        log_det = np.maximum(np.log(well.samples["max_det"][p]),
                             -np.log(well.samples["min_det"][p]))
        below = energy < depth
        traceless = omega - np.trace(omega, axis1=-2, axis2=-1)[:, None, None] / 2 * np.eye(2)
        elliptic = np.linalg.det(affine_spin_of_velocity(traceless, 1.0, a)) > 0
        turning = width * np.sqrt(-2.0 * np.log1p(-np.minimum(energy, depth * (1 - 1e-15))
                                                  / depth))
        predicted_volume = dilatation_fraction(1.0, a, b, depth, scale)
        predicted = predicted_volume * sl2_isotropic_fraction(1.0, a)
        measured = _with_trials(fraction_at(well, p, sizes.horizon), int(ok.sum()))
        rows.append({
            "A": a, "B": b, "predicted_volume": predicted_volume,
            "fraction_volume_bounded": well.summary["points"][p]["fraction_volume_bounded"],
            "predicted": predicted, "measured": measured, "z": _z(measured, predicted),
            # below the threshold: max |ln det| never exceeds the turning point of V(q) = E
            "below_threshold_max_excess": float(np.max(
                (log_det - turning)[below & ok], initial=-np.inf)),
            "below_threshold_volume_bounded": float(np.mean(log_det[below & ok] < np.log(
                well.spec.bound))) if np.any(below & ok) else math.nan,
            # judged on elliptic shapes (the others reach the bound through the shape first)
            "above_threshold_volume_escaped": float(np.mean(log_det[~below & ok & elliptic]
                                                            >= np.log(well.spec.bound)))
            if np.any(~below & ok & elliptic) else math.nan,
            "elliptic": elliptic,
            "rule_agreement": float(np.mean((below & elliptic) == (well.status[p] == "bounded"))),
            "failed": int(np.sum(~ok)),
            "energy": energy, "log_det": log_det,
        })
    out["well"] = rows
    return out


BINARY_CASES = {
    # the binary affine term (78): f = (1/2) (ln det Gamma)^2, a function of the M_a (79)
    "binary": [{"kind": "pair", "expr": "0.5*log(det)**2"}],
    "binary+dilatation": [{"kind": "pair", "expr": "0.5*log(det)**2"},
                          {"kind": "dilatation", "stiffness": 1.0}],
    # the harmonic M_a term of potentials.HarmonicInvariants: a finite barrier to det Gamma = 0
    "harmonic-M": [{"kind": "harmonic-invariants", "stiffness": 0.5}],
}
#: One-body isochoric shape term (n = 2): Tr G / det phi >= 2, = 2 iff phi is conformal; it is
#: invariant under phi -> s phi, so it holds the shape without touching the volume.
SHAPE_POTENTIAL = {"kind": "one-body", "expr": "0.5*(trG/det - 2)"}


def binary_study(run: Runner, sizes: Sizes = Sizes(), scale: float = 0.3,
                 cases: Sequence[str] = ("binary", "binary+dilatation")) -> dict:
    """Study 5 of docs/studies.md: two af-is bodies (I = 2, A = 0.5, B = 0.3) on GL(2) with a
    binary affine potential (78) and the volume-neutral shape term :data:`SHAPE_POTENTIAL`,
    without and with (81) V = (1/2)(ln det phi_K)^2 per body (:data:`BINARY_CASES`).

    Reported per case: the fraction of samples whose relative volume det Gamma (79) stays in
    (1/bound, bound) and the per-sample energy bound |ln det Gamma| <= sqrt(2 E) (for the
    (1/2)(ln det Gamma)^2 term and positive kinetic energy); the fraction whose single volumes
    det phi_K stay in (1/bound, bound) (without (81), sum_K ln det phi_K grows like
    t Tr(Sigma_1 + Sigma_2)/(I + A + nB): only samples with a small Tr Sigma stay inside up to
    T); the bounded fraction (singular values); failures.
    """
    out: dict = {"scale": scale}
    steps = int(round(sizes.horizon / sizes.well_dt))
    kinetic = {"I": 2.0, "A": 0.5, "B": 0.3}
    for name in cases:
        result = run(sweep_config(group="GL+", internal="af-is", kinetic=kinetic, bodies=2,
                                  potentials=[*BINARY_CASES[name], SHAPE_POTENTIAL],
                                  dt=sizes.well_dt, steps=steps, samples=sizes.samples,
                                  velocity_scale=scale))
        ok = result.status[0] != "failed"
        followed = result.samples["followed_time"][0] >= sizes.horizon * (1 - 1e-12)
        bound = result.spec.bound
        relative = result.samples["max_relative_volume"][0]
        single = np.maximum(result.samples["max_det"][0], 1.0 / result.samples["min_det"][0])
        energy = result.samples["initial_energy"][0]
        decided = ok & (followed | (single >= bound))
        half = _with_trials(fraction_at(result, 0, sizes.horizon / 2), int(ok.sum()))
        out[name] = {
            "relative_volume_bounded": float(np.mean(relative[ok] < bound)) if ok.any()
            else math.nan,
            # for f = (1/2)(ln det Gamma)^2 and positive kinetic energy: |ln det Gamma| <= sqrt(2E)
            "energy_bound_holds": bool(np.all(np.log(relative[ok]) <= np.sqrt(2 * energy[ok])
                                              * (1 + 1e-9) + 1e-12)) if name != "harmonic-M"
            else None,
            "max_log_relative_volume": float(np.max(np.log(relative[ok]), initial=0.0)),
            "single_volume_bounded": binomial_summary(int(np.sum(decided & (single < bound))),
                                                      int(np.sum(decided))),
            "undecided": int(np.sum(ok & ~decided)),
            "max_log_volume": float(np.max(np.log(single[ok]), initial=0.0)),
            "bounded_half_horizon": half,
            "bounded": _with_trials(fraction_at(result, 0, sizes.horizon), int(ok.sum())),
            "failed": int(np.sum(~ok)),
            "failures": result.summary["points"][0]["failures"],
            "energy_error_median": result.summary["points"][0]["energy_error_median"],
            "log_relative": np.log(relative), "log_single": np.log(single),
        }
    return out


# --------------------------------------------------------------------------- plots and main
def _strip(data):
    """The JSON-able numbers of a study (per-sample arrays dropped)."""
    if isinstance(data, dict):
        return {k: _strip(v) for k, v in data.items() if not isinstance(v, np.ndarray)}
    if isinstance(data, list):
        return [_strip(v) for v in data]
    if isinstance(data, float) and not math.isfinite(data):
        return None
    if isinstance(data, np.generic):
        return data.item()
    return data


def plot_studies(results: dict, folder) -> list:
    """PNG figures of the studies into ``folder`` (small files, 100 dpi)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []

    sl2 = results["sl2"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    afaf = sl2["af-af"]
    det, bounded = afaf["det"], afaf["status"] == "bounded"
    bins = np.linspace(-4, 3, 71)
    left.hist([det[bounded], det[~bounded]], bins=bins, stacked=True,
              label=["bounded", "unbounded"], color=["tab:blue", "tab:red"])
    left.axvline(0.0, color="k", lw=0.8)
    left.set_xlabel(r"det $\hat\Omega$ (af-af on SL(2))")
    left.set_ylabel("samples")
    left.legend(frameon=False)
    left.set_title(f"bounded iff det > 0: agreement {afaf['rule_agreement']:.4f}")
    grid = np.linspace(-0.95, 0.95, 200)
    right.plot(grid, [sl2_isotropic_fraction(1.0, a) for a in grid], "k-",
               label=r"$1-\rho/\sqrt{1+\rho^2}$, $\rho=(I+A)/(I-A)$")
    for model, marker, shift in (("af-is", "o", -0.012), ("is-af", "s", 0.012)):
        rows = [r for r in sl2["isotropic"] if r["model"] == model]
        right.errorbar([r["A"] + shift for r in rows], [r["measured"]["fraction"] for r in rows],
                       yerr=[2 * r["measured"]["error"] for r in rows], fmt=marker, ms=4,
                       label=f"{model} (I = 1), 2$\\sigma$")
    right.axhline(sl2_isotropic_fraction(0.0, 1.0), color="gray", ls=":", lw=0.8)
    right.set_xlabel("A / I")
    right.set_ylabel("bounded fraction")
    right.set_title("SL(2) geodesics")
    right.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    paths.append(folder / "sweep_sl2.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    sl3 = results["sl3"]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for row in sl3["models"]:
        kept = [f for f in row["fractions"] if f["fraction"] > 0]
        label = f"{row['model']} I={row['I']:g} A={row['A']:g}"
        if len(kept) < len(row["fractions"]):
            label += f" (0 bounded from T = {row['fractions'][len(kept)]['horizon']:g})"
        ax.errorbar([f["horizon"] for f in kept], [f["fraction"] for f in kept],
                    yerr=[f["error"] for f in kept], marker="o", ms=4, capsize=2, label=label)
    hs = np.array([f["horizon"] for f in sl3["models"][0]["fractions"]])
    first = sl3["models"][0]["fractions"][0]["fraction"]
    ax.plot(hs, first * hs[0] / hs, "k--", lw=0.8, label="1/T")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("horizon T")
    ax.set_ylabel("fraction bounded up to T")
    ax.set_title("SL(3) geodesics: no open bounded set")
    ax.legend(frameon=False, fontsize=7)
    fig.tight_layout()
    paths.append(folder / "sweep_sl3.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    gl2 = results["gl2"]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for row in gl2["well"]:
        if row["A"] != -0.5:
            continue
        keep = row["elliptic"]
        ax.plot(row["energy"][keep] / gl2["depth"], row["log_det"][keep], ".", ms=2,
                label=f"af-is I=1 A=-0.5 B={row['B']:g} (elliptic shapes)")
    e = np.linspace(0, 0.99999, 400)
    ax.plot(e, gl2["width"] * np.sqrt(-2 * np.log1p(-e)), "k-", lw=0.8,
            label="turning point of V(ln det) = E")
    ax.axvline(1.0, color="k", ls=":", lw=0.8)
    ax.axhline(np.log(1000.0), color="gray", ls="--", lw=0.8, label="ln(bound)")
    ax.set_xlim(0, 3)
    ax.set_ylim(0, 30)
    ax.set_xlabel(r"dilatational energy / well depth D")
    ax.set_ylabel(r"max$_t$ |ln det $\varphi$|")
    ax.set_title("GL(2) with a finite well V(det)")
    ax.legend(frameon=False, fontsize=7, markerscale=4)
    fig.tight_layout()
    paths.append(folder / "sweep_gl2_well.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    binary = results["binary"]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    bins = np.linspace(0, 30, 61)
    for name, colour in (("binary", "tab:red"), ("binary+dilatation", "tab:blue")):
        if name not in binary:
            continue
        ax.hist(binary[name]["log_single"], bins=bins, histtype="step", color=colour,
                label=f"{name}: max |ln det phi_K|")
        ax.hist(binary[name]["log_relative"], bins=bins, histtype="stepfilled", alpha=0.3,
                color=colour, label=f"{name}: max |ln det Gamma|")
    ax.axvline(np.log(1000.0), color="gray", ls="--", lw=0.8)
    ax.set_xlabel("max over t of |ln det|: single volumes phi_K, relative volume Gamma")
    ax.set_yscale("log")
    ax.set_ylabel("samples")
    ax.set_title("two af-is bodies, binary affine potential (78)")
    ax.legend(frameon=False, fontsize=7)
    fig.tight_layout()
    paths.append(folder / "sweep_binary.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    import argparse
    import time

    from affinebody._checks import enable_x64
    from affinebody.sweep import dask_client

    parser = argparse.ArgumentParser(description="Run the studies of docs/studies.md.")
    parser.add_argument("--out", default="docs", help="docs folder (figures go to OUT/figures)")
    parser.add_argument("--workers", type=int, default=None, help="local Dask workers")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler address")
    parser.add_argument("--samples", type=int, default=Sizes.samples)
    args = parser.parse_args(argv)
    enable_x64()
    sizes = Sizes(samples=args.samples, sl3_samples=max(1, args.samples // 2))
    clock = time.perf_counter()
    with dask_client(args.scheduler, args.workers) as client:
        run = client_runner(client)
        results = {}
        studies = (("sl2", sl2_study), ("sl3", sl3_study), ("gl2", gl2_study),
                   ("binary", lambda r, z: binary_study(r, z, cases=tuple(BINARY_CASES))))
        for name, study in studies:
            start = time.perf_counter()
            results[name] = study(run, sizes)
            results[name]["seconds"] = time.perf_counter() - start
            print(f"{name}: {results[name]['seconds']:.1f} s", flush=True)
    paths = plot_studies(results, Path(args.out) / "figures")
    numbers = _strip(results)
    numbers["total_seconds"] = time.perf_counter() - clock
    (Path(args.out) / "figures" / "studies.json").write_text(json.dumps(numbers, indent=1))
    print(json.dumps(numbers, indent=1))
    for path in paths:
        print(path)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())


__all__ = [
    "Runner", "inline_runner", "client_runner", "sweep_config", "sl2_isotropic_fraction",
    "affine_spin_of_velocity", "exp_spread", "dilatation_fraction", "fraction_at", "Sizes",
    "sl2_study", "sl3_study", "gl2_study", "BINARY_CASES", "SHAPE_POTENTIAL", "binary_study",
    "plot_studies", "main"
]
