"""Sweeps on Dask: classification against closed forms, failures recorded, determinism across
worker counts (2-worker cluster, 1-worker cluster started by the CLI, no Dask), float64 workers.

One local cluster of 2 workers serves the module. The sweep config is geodesic af-af motion on
GL(2) (72), whose solution phi(t) = exp(t Omega_hat) is known exactly
(docs/theory/exact-flows.md), plus the potential 0 * sqrt(det phi - 0.9): zero force while
det phi > 0.9, NaN below, so exactly the samples with T Tr(Omega_hat) < ln 0.9
(det phi(t) = exp(t Tr Omega_hat)) blow up.
"""

import dataclasses
import json
import math
import textwrap

import click
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.linalg import expm
from scipy.stats import binomtest

from affinebody.cli.sweep import sweep
from affinebody.config import ConfigError, build, check_config, parse_config
from affinebody.sweep import (
    STATUS_CODES,
    SweepSpec,
    Task,
    _execute,
    binomial_summary,
    dask_client,
    draw_initial_state,
    run_sweep,
    scan_points,
)

DT, STEPS, SAMPLES, BATCH = 0.1, 20, 20, 8
MIXED = textwrap.dedent(f'''
    [system]
    n = 2
    group = "GL+"
    bodies = 1
    [body]
    mass = 1.0
    [kinetic]
    internal = "af-af"
    A = 1.0
    B = 0.5
    [[potential]]
    kind = "dilatation"
    expr = "0*sqrt(det - 0.9)"
    [initial]
    x = [[0.0, 0.0]]
    [run]
    dt = {DT}
    steps = {STEPS}
    [sweep]
    samples = {SAMPLES}
    seed = 7
    initial_velocity = "normal"
    velocity_scale = 1.2
    bound = 50.0
    batch = {BATCH}
    scan = {{ "kinetic.A" = [1.0, 2.0, 0.0] }}
''')
#: MIXED without its refused point (kinetic.A = 0 for af-af), which ``affinebody sweep``
#: refuses as a whole: the same points 0 and 1, the same samples
RUNNABLE = MIXED.replace("[1.0, 2.0, 0.0]", "[1.0, 2.0]")
CLI = click.Group("affinebody", commands={"sweep": sweep})


def load(text):
    return check_config(parse_config(text))


@pytest.fixture(scope="module")
def client():
    with dask_client(workers=2) as c:
        yield c


@pytest.fixture(scope="module")
def two_workers(client, tmp_path_factory):
    folder = tmp_path_factory.mktemp("sweep2")
    return run_sweep(load(MIXED), client=client, output=folder)


def expected(omega, bound):
    """The driver's loop on the closed form phi(t_k) = expm(t_k Omega), det = exp(t_k Tr Omega):
    (failing step or None, exit step or -1, spreads and ln det at the followed steps)."""
    trace = np.trace(omega)
    fail_step, exit_step, spreads, log_det = None, -1, [1.0], [0.0]
    for k in range(1, STEPS + 1):
        t = k * DT
        if t * trace < math.log(0.9):
            fail_step = k
            break
        sigma = np.linalg.svd(expm(t * omega), compute_uv=False)
        spreads.append(max(sigma[0], 1 / sigma[-1]))
        log_det.append(t * trace)
        if spreads[-1] >= bound and exit_step < 0:
            exit_step = k
        if spreads[-1] >= bound**2:  # followed no further
            break
    return fail_step, exit_step, np.array(spreads), np.array(log_det)


def test_classification_failures_and_volumes_match_the_closed_form(two_workers):
    result = two_workers
    assert [p.error is None for p in result.points] == [True, True, False]
    assert all("kinetic.A must be nonzero" in f for f in result.failure[2])
    assert list(result.status[2]) == ["failed"] * SAMPLES
    kinds = set()
    for k in range(SAMPLES):
        omega = result.samples["omega_hat"][0, k, 0]
        fail_step, exit_step, spreads, log_det = expected(omega, 50.0)
        status, failure = result.status[0, k], result.failure[0, k]
        followed = result.samples["followed_time"][0, k]
        if fail_step is not None:
            assert (status, failure) == ("failed", "non-finite state")
            assert followed == pytest.approx((fail_step - 1) * DT, abs=1e-12)
        elif exit_step < 0:
            assert status == "bounded"
            assert followed == pytest.approx(STEPS * DT, abs=1e-12)
        else:
            assert status == "unbounded"
            assert result.samples["exit_time"][0, k] == pytest.approx(exit_step * DT, abs=1e-12)
        kinds.add(status)
        if status != "failed":
            # exact geodesic flow: energy kept to round-off (impossible in float32)
            assert result.samples["energy_error"][0, k] < 1e-12
            assert result.samples["max_spread"][0, k] == pytest.approx(spreads.max(), rel=1e-9)
            np.testing.assert_allclose(np.log([result.samples["min_det"][0, k],
                                               result.samples["max_det"][0, k]]),
                                       [log_det.min(), log_det.max()], atol=1e-11)
            assert result.samples["max_relative_volume"][0, k] == 1.0  # one body
    assert kinds == {"bounded", "unbounded", "failed"}
    # af-af geodesics do not depend on A (phi0 exp(t Omega_hat)): points 0 and 1 agree
    np.testing.assert_array_equal(result.status[0], result.status[1])
    np.testing.assert_array_equal(result.samples["exit_time"][0], result.samples["exit_time"][1])
    summary = result.summary["points"][0]
    bounded = int(np.sum(result.status[0] == "bounded"))
    classified = int(np.sum(result.status[0] != "failed"))
    assert summary["fraction_bounded"] == bounded / classified
    assert summary["failures"] == {"non-finite state": SAMPLES - classified}


def test_each_point_follows_its_own_horizon_and_the_summary_claims_one_only_if_shared(
        two_workers, tmp_path):
    """A scan of run.dt: point p is followed for STEPS * dt_p (its bounded samples to exactly
    that time), so summary.json may not give one horizon (it gave the base config's); a
    refused point runs nothing and has none. Without such a scan every point shares one."""
    assert two_workers.summary["horizon"] == pytest.approx(STEPS * DT, rel=1e-15)
    assert [p["horizon"] for p in two_workers.summary["points"]][:2] == [STEPS * DT] * 2
    assert math.isnan(two_workers.summary["points"][2]["horizon"])  # kinetic.A = 0: refused
    text = MIXED.replace('scan = { "kinetic.A" = [1.0, 2.0, 0.0] }',
                         'scan = { "run.dt" = [0.1, 0.05] }').replace("samples = 20", "samples = 8")
    result = run_sweep(load(text), workers=0, output=tmp_path)
    for point, dt in zip(result.summary["points"], (0.1, 0.05), strict=True):
        assert point["horizon"] == pytest.approx(STEPS * dt, rel=1e-15)
        bounded = result.status[point["index"]] == "bounded"
        np.testing.assert_allclose(result.samples["followed_time"][point["index"]][bounded],
                                   STEPS * dt, rtol=1e-12)
    assert json.loads((tmp_path / "summary.json").read_text())["horizon"] is None


def test_one_worker_and_two_workers_give_identical_results(two_workers, tmp_path):
    out = tmp_path / "one"
    config = tmp_path / "mixed.toml"
    config.write_text(RUNNABLE)
    result = CliRunner().invoke(CLI, ["sweep", str(config), "--workers", "1", "-o", str(out),
                                      "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)  # stdout is exactly one JSON object
    assert summary["workers"] == 1 and two_workers.summary["workers"] == 2
    assert summary["scheduler"].startswith("tcp://")  # the local cluster it started, not null
    for name in ("fraction_bounded", "samples"):
        assert summary[name] == two_workers.summary[name]
    assert summary["total_samples"] == two_workers.summary["total_samples"] - SAMPLES
    assert summary["failed"] == two_workers.summary["failed"] - SAMPLES  # less the refused
    rows = {}
    for path in (out / "tasks").glob("point-*.json"):
        data = json.loads(path.read_text())
        for row in data["rows"]:
            rows[data["point"], row["sample"]] = row
    assert len(rows) == 2 * SAMPLES
    for (p, k), row in rows.items():
        assert row["status"] == two_workers.status[p, k]
        for name in ("exit_time", "followed_time", "max_spread", "energy_error", "final_energy",
                     "min_det", "max_det"):
            a, b = row[name], two_workers.samples[name][p, k]
            a = math.nan if a is None else a
            assert np.array_equal(a, b, equal_nan=True), (name, p, k, a, b)  # bit for bit
        np.testing.assert_array_equal(row["omega_hat"], two_workers.samples["omega_hat"][p, k])


def test_draws_of_many_numbers_go_beside_the_task_file_bit_for_bit(tmp_path, monkeypatch):
    """A task whose drawn velocities exceed TASK_JSON_DRAWS numbers (here every task: the
    limit set to 0) writes them to TASK.npz, named in the JSON's "draws", not as JSON text
    (GBs for a batch of 10^5 bodies); they are the sweep's draws bit for bit, the rows keep
    everything else, and a later sweep into the folder leaves no stale side file."""
    import affinebody.sweep as sweep_module

    monkeypatch.setattr(sweep_module, "TASK_JSON_DRAWS", 0)
    text = MIXED.replace("samples = 20", "samples = 8")
    result = run_sweep(load(text), workers=0, output=tmp_path)
    files = sorted((tmp_path / "tasks").glob("*.json"))
    assert files and len(list((tmp_path / "tasks").glob("*.npz"))) == len(files)
    for path in files:
        data = json.loads(path.read_text())
        assert "omega_hat" not in data["rows"][0] and "status" in data["rows"][0]
        draws = np.load(tmp_path / "tasks" / data["draws"])
        first, stop = data["samples"]
        np.testing.assert_array_equal(draws["omega_hat"],
                                      result.samples["omega_hat"][data["point"], first:stop])
        np.testing.assert_array_equal(draws["velocity"],
                                      result.samples["velocity"][data["point"], first:stop])
    monkeypatch.setattr(sweep_module, "TASK_JSON_DRAWS", 10**9)
    run_sweep(load(text), workers=0, output=tmp_path)
    assert not list((tmp_path / "tasks").glob("*.npz"))
    row = json.loads(files[0].read_text())["rows"][0]
    assert np.shape(row["omega_hat"]) == (1, 2, 2)


def test_workers_compute_in_float64_with_one_thread(client, two_workers):
    tasks = sorted((two_workers.output / "tasks").glob("*.json"))
    assert len(tasks) == 2 * math.ceil(SAMPLES / BATCH)  # one file per task
    for path in tasks:
        worker = json.loads(path.read_text())["worker"]
        assert worker["x64"] is True and worker["dtype"] == "float64"
        assert "--xla_cpu_multi_thread_eigen=false" in worker["xla_flags"]
        assert worker["omp_threads"] == "1"

    def probe():
        return str(jnp.asarray(1.0).dtype), jax.config.jax_enable_x64

    assert set(client.run(probe).values()) == {("float64", True)}
    assert two_workers.samples["final_energy"].dtype == np.float64


def test_a_raising_task_is_recorded_not_fatal(client, two_workers):
    spec = SweepSpec.from_config(load(MIXED))
    good = scan_points(load(MIXED))[0].config_json
    # the good task has the shape of the module's tasks (BATCH): no new compilation
    tasks = [Task(0, 0, None, 0, 2, 2, spec), Task(1, 0, "{}", 0, 2, 2, spec),
             Task(2, 0, good, 0, 2, BATCH, spec)]
    seen = {}
    _execute(tasks, client, lambda task, result: seen.setdefault(task.point, result))
    assert seen[0]["message"][0].startswith("task error: TypeError")
    assert "system" in seen[1]["message"][0] and seen[1]["message"][0].startswith("config error")
    statuses = [STATUS_CODES[int(c)][0] for c in seen[2]["code"]]
    assert statuses == list(two_workers.status[0, :2])


def test_cli_on_a_running_cluster_prints_one_json_object(client, two_workers, tmp_path):
    config = tmp_path / "mixed.toml"
    config.write_text(RUNNABLE)
    address = client.scheduler.address
    result = CliRunner().invoke(CLI, ["sweep", str(config), "--scheduler", address, "--json",
                                      "--samples", str(SAMPLES), "-o", str(tmp_path / "o")])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["fraction_bounded"] == two_workers.summary["fraction_bounded"]
    # provenance: the cluster it ran on (not null), its workers (not its process ids)
    written = json.loads((tmp_path / "o" / "summary.json").read_text())
    for record in (summary, written):
        assert record["scheduler"] == address
        assert record["workers"] == len(client.scheduler_info()["workers"]) == 2
        assert 1 <= record["worker_processes"] <= 2
    assert [p["parameters"] for p in summary["points"]] == [{"kinetic.A": 1.0}, {"kinetic.A": 2.0}]
    assert [p["config_error"] for p in summary["points"]] == [None, None]
    text = CliRunner().invoke(CLI, ["sweep", str(config), "--scheduler", address,
                                    "--samples", str(BATCH), "-o", str(tmp_path / "t")])
    assert text.exit_code == 0 and "fraction bounded" in text.output
    assert f"on 2 worker(s) ({address})" in text.output
    bad = CliRunner().invoke(CLI, ["sweep", str(config), "--scheduler", address,
                                   "--workers", "2"])
    assert bad.exit_code != 0 and "--workers" in bad.output + bad.stderr


THERMAL = textwrap.dedent("""
    [system]
    n = 2
    group = "L"
    bodies = 2
    [body]
    mass = 1.0
    inertia = 1.0
    [kinetic]
    internal = "dalembert"
    [[potential]]
    kind = "one-body"
    expr = "0.5*trG"
    [initial]
    x = [[0.0, 0.0], [1.0, 0.0]]
    [run]
    dt = 0.05
    steps = 200
    every = 10
    [thermostat]
    kind = "bussi"
    temperature = 1.0
    tau = 0.5
    [sweep]
    samples = 6
    seed = 9
    batch = 4
    equilibration = 50
    initial_velocity = "normal"
""")


def test_thermostatted_samples_do_not_depend_on_workers_or_batching(client):
    """Sample k's thermostat noise comes from (seed, k) only: two workers with tasks of 4
    samples (the last padded) and this process with a single task of 6 give the same
    samples: the same draws bit for bit, the same averages to round-off (the workers' XLA
    runs single-threaded, this process's need not: the last bits of a sum may differ). The
    noise differs between samples. (Bussi on free translations: no heat reaches a momentum
    that is zero, so T_tr stays 0 and the internal energy holds all of K_bar.)"""
    on_dask = run_sweep(load(THERMAL), client=client)
    alone = run_sweep(load(THERMAL.replace("batch = 4", "batch = 6")), workers=0)
    assert on_dask.summary["ensemble"] == "NVT" and on_dask.summary["workers"] == 2
    assert set(on_dask.status.ravel()) == {"sampled"}
    for name in ("omega_hat", "velocity", "measurements", "followed_time"):
        assert np.array_equal(on_dask.samples[name], alone.samples[name]), name
    for name, values in on_dask.samples.items():
        np.testing.assert_allclose(values, alone.samples[name], rtol=1e-12, atol=0,
                                   err_msg=name)
    energies = on_dask.samples["mean_total_energy"]
    assert len(set(energies[0].tolist())) == 6  # independent samples
    # Bussi puts the kinetic energy of all N (n + n^2) momenta into the internal ones
    assert abs(np.mean(on_dask.samples["mean_internal_temperature"]) - 1.5) < 0.3
    assert np.all(on_dask.samples["mean_translational_temperature"] == 0.0)


# --------------------------------------------------------------------------- no cluster
def test_scan_points_expand_ranges_in_order_and_check_each_point():
    text = MIXED.replace('scan = { "kinetic.A" = [1.0, 2.0, 0.0] }',
                         'scan = { "kinetic.B" = { start = 0.5, stop = 2.0, num = 3 }, '
                         '"run.steps" = { start = 10, stop = 1000, num = 3, log = true } }')
    points = scan_points(load(text))
    assert [p.parameters for p in points] == [
        (("kinetic.B", b), ("run.steps", pytest.approx(s, rel=1e-12))) for b in (0.5, 1.25, 2.0)
        for s in (10.0, 100.0, 1000.0)]
    data = json.loads(points[4].config_json)
    assert data["kinetic"]["B"] == 1.25 and data["run"]["steps"] == 100
    assert isinstance(data["run"]["steps"], int)
    for scan, field in (('{ "kinetic.Q" = [1.0] }', 'sweep.scan."kinetic.Q"'),
                        ('{ "potential.3.expr" = ["det"] }', 'sweep.scan."potential.3.expr"'),
                        ('{ "kinetic.A" = [] }', 'sweep.scan."kinetic.A"'),
                        ('{ "run.dt" = { start = 0.0, stop = 1.0, num = 2, log = true } }',
                         'sweep.scan."run.dt"')):
        with pytest.raises(ConfigError) as info:
            scan_points(load(MIXED.replace('{ "kinetic.A" = [1.0, 2.0, 0.0] }', scan)))
        assert field in str(info.value) and "\n" not in str(info.value)
    mixed = scan_points(load(MIXED.replace("[1.0, 2.0, 0.0]", '["x", 1.0]')))
    assert mixed[0].error.startswith("config error: kinetic.A") and mixed[1].error is None
    # a scan none of whose points can run, or with a value that is not finite, is refused as
    # a whole (it ran, exit 0, with every sample failed or nan: found by fuzzing the CLI)
    for scan, text in (('["x"]', "every point of the scan is refused, e.g. kinetic.A = 'x'"),
                       ("[1.0, nan]", 'sweep.scan."kinetic.A": values must be finite (got nan)'),
                       ("{ start = 1.0, stop = inf, num = 3 }", "must be finite (got inf)")):
        with pytest.raises(ConfigError) as info:
            scan_points(load(MIXED.replace("[1.0, 2.0, 0.0]", scan)))
        assert text in str(info.value) and "\n" not in str(info.value), str(info.value)


@pytest.mark.parametrize(("old", "new", "field"), [
    ("samples = 20", "samples = 0", "sweep.samples"),
    ('initial_velocity = "normal"', 'initial_velocity = "uniform"', "sweep.initial_velocity"),
    ("bound = 50.0", "bound = 1.0", "sweep.bound"),
    ("seed = 7", "sed = 7", "sweep.sed"),
])
def test_bad_sweep_tables_are_refused_with_one_line(old, new, field):
    with pytest.raises(ConfigError) as info:
        load(MIXED.replace(old, new))
    assert field in str(info.value) and "\n" not in str(info.value)


def test_the_sweep_table_does_not_change_the_run_hash():
    plain = load(MIXED.split("[sweep]")[0])
    assert plain.sweep is None and load(MIXED).hash() == plain.hash()
    assert SweepSpec.from_config(plain) == SweepSpec()


AF_IS = (MIXED.replace('internal = "af-af"\nA = 1.0\nB = 0.5',
                      'internal = "af-is"\nI = 1.0\nA = 0.5')
         .replace("samples = 20", "samples = 4"))
assert 'internal = "af-is"' in AF_IS


@pytest.mark.parametrize(("scan", "line"), [
    ('{ "kinetic.A" = [-0.5, 5.0] }',
     'config error: sweep.scan."kinetic.A" = 5.0 (point 1): kinetic.I must be > |kinetic.A| '
     'for af-is to be positive definite (got I=1.0, A=5.0)'),
    ('{ "run.dt" = [0.25, -1.0] }', 'sweep.scan."run.dt" = -1.0 (point 1): run.dt must be > 0'),
    ('{ "run.steps" = [10.5, 20] }',
     'sweep.scan."run.steps" = 10.5 (point 0): run.steps must be an integer (got 10.5)'),
    ('{ "system.n" = [2, 3] }',
     'sweep.scan."system.n" = 3 (point 1): initial.x must have shape [1, 3]'),
    ('{ "kinetic.internal" = ["af-is", "dalembert"] }',
     'sweep.scan."kinetic.internal" = "dalembert" (point 1): kinetic.I is not a parameter of '
     "the internal model 'dalembert'"),
    # of two scanned keys the one refused on its own
    ('{ "run.dt" = [0.1, 0.2], "kinetic.A" = [0.5, 5.0] }',
     'config error: sweep.scan."kinetic.A" = 5.0 (point 1): kinetic.I must be'),
    # refused only when built, as `affinebody validate` builds (phi off GL+)
    ('{ "initial.phi.0.0.0" = [1.0, -1.0] }',
     'sweep.scan."initial.phi.0.0.0" = -1.0 (point 1): initial: state.phi of body 0 is not in '
     'GL+(n)'),
])
def test_a_refused_scan_point_stops_the_command_before_any_sample(scan, line, tmp_path):
    """Every point of a scan is checked as `affinebody validate` checks a config before any
    sample runs, and the first refused one ends the command in one line naming the scanned
    key, its value, the point and the problem, exit 1 (each such point ran: its samples
    recorded as failed with that reason, exit 0; found by a CLI audit). Nothing is written."""
    text = AF_IS.replace('{ "kinetic.A" = [1.0, 2.0, 0.0] }', scan).replace(
        "x = [[0.0, 0.0]]", "x = [[0.0, 0.0]]\nphi = [[[1.0, 0.0], [0.0, 1.0]]]")
    config = tmp_path / "bad.toml"
    config.write_text(text)
    result = CliRunner().invoke(CLI, ["sweep", str(config), "--workers", "0",
                                      "-o", str(tmp_path / "out")])
    assert result.exit_code == 1, result.output
    assert result.stdout == "" and result.stderr.count("\n") == 1, result.stderr
    assert result.stderr.startswith("config error: sweep.scan.")
    assert line in result.stderr, result.stderr
    assert not (tmp_path / "out").exists()  # refused before any task
    # from Python the point is recorded as failed samples, and the others run (as before)
    if "phi" not in scan:
        errors = [p.error for p in scan_points(load(text))]
        assert any(errors) and not all(errors) and "\n" not in "".join(filter(None, errors))


def test_a_scan_range_error_names_the_scanned_key_not_the_class(tmp_path):
    """pydantic's location of an error inside a {start, stop, num} range held the union
    member's class, "sweep.scan.ScanRange.num", and dropped the key "kinetic.A" (not a bare
    TOML key): the key is named, quoted as TOML writes it."""
    for scan, line in (
            ('{ "kinetic.A" = { start = 1.0, stop = 2.0, num = 0 } }',
             'config error: sweep.scan."kinetic.A".num must be >= 1 (got 0)'),
            ('{ "kinetic.A" = { start = 1.0, num = 2 } }',
             'config error: sweep.scan."kinetic.A".stop is required'),
            ('{ "kinetic.A" = { start = 1.0, stop = 2.0, num = 2, lg = true } }',
             'config error: sweep.scan."kinetic.A".lg: unknown key'),
            ('{ "kinetic.A" = [[1.0]] }',
             'config error: sweep.scan."kinetic.A".0 must be a number or a string')):
        with pytest.raises(ConfigError) as info:
            parse_config(MIXED.replace('{ "kinetic.A" = [1.0, 2.0, 0.0] }', scan))
        assert str(info.value).startswith(line) and "ScanRange" not in str(info.value), info.value
    path = tmp_path / "range.toml"
    path.write_text(MIXED.replace('{ "kinetic.A" = [1.0, 2.0, 0.0] }',
                                  '{ "kinetic.A" = { start = 1.0, stop = 2.0, num = 0 } }'))
    result = CliRunner().invoke(CLI, ["sweep", str(path), "--workers", "0"])
    assert result.exit_code == 1
    assert result.stderr == 'config error: sweep.scan."kinetic.A".num must be >= 1 (got 0)\n'


def test_a_sweep_whose_every_sample_failed_exits_3_and_keeps_its_results(tmp_path):
    """Failed samples are results of a sweep (exit 0), but a sweep none of whose samples
    could be measured exits 3 (a computation that stopped, cli.common), after its table
    and files, with one line on stderr (it exited 0). Here every sample's first step is
    NaN: the force of 0*sqrt(det - 1) at det = 1 is 0 * inf."""
    from affinebody.cli.common import EXIT_STOPPED
    from affinebody.cli.sweep import exit_code

    config = tmp_path / "nan.toml"
    config.write_text(AF_IS.replace("det - 0.9", "det - 1.0").replace(
        '{ "kinetic.A" = [1.0, 2.0, 0.0] }', '{ "kinetic.A" = [0.25, 0.5] }'))
    result = CliRunner().invoke(CLI, ["sweep", str(config), "--workers", "0",
                                      "-o", str(tmp_path / "out")])
    assert result.exit_code == EXIT_STOPPED == 3, result.output
    assert result.stderr == (f"error: all 8 samples of the sweep failed (non-finite state: 8 "
                             f"of 8); the results are in {tmp_path / 'out'}\n")
    assert "point 1: 4 failed: non-finite state" in result.stdout
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["failed"] == summary["total_samples"] == 8
    assert exit_code(summary) == EXIT_STOPPED
    # one sample measured is a result: exit 0, the failures in the table
    assert exit_code({**summary, "failed": 7}) == 0
    assert exit_code({**summary, "failed": 0}) == 0


def test_draws_are_seeded_projected_standard_normal_and_go_through_the_legendre_map(
        two_workers):
    """Drawn here on SL(2) with af-is (I = 2, A = 0.5), same seed and scale as the sweep on GL+:
    sample k's Omega_hat is the sl(2) projection of the sweep's gl(2) draw for sample k."""
    text = MIXED.replace('group = "GL+"', 'group = "SL"').replace(
        'internal = "af-af"\nA = 1.0', 'internal = "af-is"\nI = 2.0\nA = 0.5')
    text = text.split("[[potential]]")[0] + "[initial]" + text.split("[initial]")[1]
    built = build(load(text))
    system, state = built.system, built.state

    @jax.jit
    def draws(indices):
        def one(k):
            key = jax.random.fold_in(jax.random.key(7), k)
            return draw_initial_state(system, state, key, internal="normal", internal_scale=1.2,
                                      translational="normal", translational_scale=0.5)
        return jax.vmap(one)(indices)

    start, omega, v = draws(jnp.arange(4000))
    omega, v = np.asarray(omega)[:, 0], np.asarray(v)[:, 0]
    gl = two_workers.samples["omega_hat"][0, :, 0]
    projected = gl - np.trace(gl, axis1=1, axis2=2)[:, None, None] / 2 * np.eye(2)
    np.testing.assert_allclose(omega[:SAMPLES], projected, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(np.trace(omega, axis1=1, axis2=2), 0.0, atol=1e-13)
    # through af-is's Legendre map and back: xi = phi Omega_hat
    xi = system.kinetic.internal.inverse_legendre(start.phi, start.pi)
    np.testing.assert_allclose(xi[:, 0], np.asarray(start.phi)[:, 0] @ omega, atol=1e-14)
    # sl(2) projection of 1.2 Z: off-diagonals ~ N(0, 1.44), diagonal (z11 - z22) 0.6 ~ N(0, 0.72)
    s = 5 / math.sqrt(4000)
    assert abs(np.var(omega[:, 0, 1]) / 1.44 - 1) < s * math.sqrt(2)
    assert abs(np.var(omega[:, 0, 0]) / 0.72 - 1) < s * math.sqrt(2)
    assert abs(np.var(v) / 0.25 - 1) < s
    assert abs(np.corrcoef(omega[:, 0, 1], omega[:, 1, 0])[0, 1]) < s
    np.testing.assert_allclose(start.p, 1.0 * v[:, None], atol=1e-15)  # p = M v, M = 1
    # the same sample drawn alone or in a batch of 4000
    alone = draws(jnp.asarray([1234]))[1]
    np.testing.assert_allclose(np.asarray(alone)[0, 0], omega[1234], rtol=1e-15)


def test_binomial_summary_matches_scipy_wilson_interval():
    for k, m in ((0, 10), (3, 10), (293, 1000), (50, 50)):
        summary = binomial_summary(k, m)
        ci = binomtest(k, m).proportion_ci(confidence_level=0.95, method="wilson")
        np.testing.assert_allclose(summary["interval"], [ci.low, ci.high], atol=1e-9)
        assert summary["error"] == pytest.approx(math.sqrt(k / m * (1 - k / m) / m))


def test_a_sweep_whose_results_cannot_fit_in_memory_is_refused_before_any_task():
    """--samples 10^11 (found by fuzzing the CLI: it spent minutes making 10^9 task objects
    before failing) is refused at once with the estimate; the estimate is linear in the
    samples and at least the drawn velocities' float64 numbers."""
    from affinebody.sweep import results_bytes, run_sweep

    config = load(MIXED)
    with pytest.raises(ConfigError, match=r"--samples\) at \d+ scan point\(s\) needs about"):
        run_sweep(config, samples=10**11, workers=0)
    spec = SweepSpec.from_config(config)
    bigger = dataclasses.replace(spec, samples=2 * spec.samples)
    assert results_bytes(config, 3, bigger, 7) == pytest.approx(
        2 * results_bytes(config, 3, spec, 7), rel=1e-12)
    n, bodies = config.n, config.bodies_count
    assert results_bytes(config, 3, spec, 7) >= 3 * spec.samples * bodies * (n * n + n) * 8


def test_a_local_cluster_of_absurd_size_is_refused_before_starting_a_worker():
    """--workers 100000 started worker processes until it was killed (found by fuzzing the
    CLI), and --workers -1 was said to need >= 1 though 0 runs in this process: both refused in
    one line that gives the range."""
    for workers in (-1, 100_000):
        with pytest.raises(ConfigError, match=r"--workers must be 0 \(in this process"):
            with dask_client(workers=workers):
                pass


def test_a_sweep_without_its_draws_in_memory_gives_the_same_results(tmp_path, monkeypatch):
    """``keep_draws=False`` (what ``affinebody sweep`` runs: its task files hold the draws)
    gives the same per-sample results, statuses and summary as a sweep that keeps every
    body's drawn velocities, without holding them; so the command is not refused for the
    memory of draws it does not keep (here: a memory between the two estimates)."""
    from affinebody import config as config_module
    from affinebody.sweep import results_bytes, run_sweep

    bodies = 20  # MIXED's free bodies, without its guard that fails states with det < 0.9
    text = (MIXED.replace("bodies = 1", f"bodies = {bodies}")
            .replace("x = [[0.0, 0.0]]", f"x = {[[50.0 * k, 0.0] for k in range(bodies)]}")
            .replace('expr = "0*sqrt(det - 0.9)"', 'expr = "0*det"'))
    config = load(text)
    kept = run_sweep(config, workers=0)
    lean = run_sweep(config, workers=0, keep_draws=False)
    assert "omega_hat" not in lean.samples and "velocity" not in lean.samples
    assert kept.samples["omega_hat"].shape == (3, SAMPLES, bodies, 2, 2)
    for name, values in lean.samples.items():
        np.testing.assert_array_equal(values, kept.samples[name])
    np.testing.assert_array_equal(lean.status, kept.status)
    assert "unbounded" in set(kept.status.ravel())  # classified: a finite fraction
    assert lean.summary["fraction_bounded"] == kept.summary["fraction_bounded"]
    spec, columns = SweepSpec.from_config(config), len(lean.samples)
    lean_bytes = results_bytes(config, 3, spec, columns, keep_draws=False)
    kept_bytes = results_bytes(config, 3, spec, columns)
    assert kept_bytes > 2 * lean_bytes
    monkeypatch.setattr(config_module, "available_memory", lambda: (lean_bytes + kept_bytes) / 2)
    with pytest.raises(ConfigError, match="needs about"):
        run_sweep(config, workers=0)
    monkeypatch.setattr(config_module, "estimated_memory", lambda config: 0.0)  # one body's run
    path = tmp_path / "sweep.toml"
    path.write_text(text.replace("[1.0, 2.0, 0.0]", "[1.0, 2.0]"))  # the command refuses A = 0
    result = CliRunner().invoke(CLI, ["sweep", str(path), "--workers", "0", "-o",
                                      str(tmp_path / "out"), "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["fraction_bounded"] == kept.summary["fraction_bounded"]
