"""qpctl sweep (issue 14): specs, run ids, the engine's backends, the Parquet store, resuming, summaries.

The sweeps here are small (16 one-second canopy runs, a few planar ones) but real: real processes, a
real local Ray instance, real Parquet files. The resume tests start ``qpctl sweep`` as a subprocess,
SIGKILL it (with its workers, and Ray's processes) once a few runs are written, run the same command
again and compare the dataset with an uninterrupted sweep's, run for run, timing columns aside.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from qpctl.errors import ConfigError
from qpctl.sweep.backends import LocalBackend, WorkerDied, make_backend
from qpctl.sweep.driver import run_sweep
from qpctl.sweep.engine import execute, map_ordered
from qpctl.sweep.runner import TIMING_COLUMNS, execute_run
from qpctl.sweep.spec import RunParams, SweepSpec, packaged_specs
from qpctl.sweep.store import read_dataset
from qpctl.sweep.summary import summarize

SPEC = """
name = "resume_test"
seed = 3
controllers = ["paper", "hsu", "qp"]
solvers = ["daqp", "proxqp"]

[set]
"sim.duration" = 1.0

[grid]
"controller.v_ref" = [0.1, 0.3]

[[families]]
kind = "canopy"
count = 2
seed = 100
"""
TOTAL = 2 * 2 * 4  # scenes × v_ref × (paper, hsu, qp-daqp, qp-proxqp)


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("spec") / "resume_test.toml"
    path.write_text(SPEC)
    return path


@pytest.fixture(scope="module")
def reference(spec_file, tmp_path_factory):
    """The uninterrupted sweep: local backend, two processes."""
    out = tmp_path_factory.mktemp("reference")
    report = run_sweep(spec_file, out, jobs=2, progress=False)
    assert (report.total, report.ran, report.skipped, report.failed) == (TOTAL, TOTAL, 0, 0)
    return read_dataset(out)


def _deterministic(table):
    return table.select([c for c in table.column_names if c not in TIMING_COLUMNS])


def assert_same_results(a, b):
    """Same runs, parameters, statuses and counts exactly; float metrics equal to 1e-9 relative.

    Not bit for bit: a proxqp run's last digits can differ from one process to another (seen: a least
    clearance 0.0995740374063869 against …639134 for the same parameters, each run alone in a fresh
    process), so the floats are compared to a tolerance far below any metric's meaning. The task
    slack's largest norm is compared to 1e-8 absolute as well: on these runs it is proxqp's residue at
    its eps_abs of 1e-9 (2.0570e-9 against 2.0566e-9 for the same run after other runs in the same
    process, with the code of stop 35 as with stop 36's), not a quantity its last digits mean."""
    import numpy as np
    import pyarrow as pa

    a, b = _deterministic(a), _deterministic(b)
    assert a.column_names == b.column_names and a.num_rows == b.num_rows
    for name in a.column_names:
        x, y = a.column(name), b.column(name)
        if pa.types.is_floating(x.type):
            xs, ys = x.to_numpy(zero_copy_only=False), y.to_numpy(zero_copy_only=False)
            assert np.array_equal(np.isnan(xs), np.isnan(ys)), name
            atol = 1e-8 if name == "qp_slack_max" else 1e-12
            assert np.allclose(xs, ys, rtol=1e-9, atol=atol, equal_nan=True), name
        else:
            assert x.to_pylist() == y.to_pylist(), name


# -- specs ----------------------------------------------------------------------------------------
def test_packaged_specs_load_and_expand():
    assert {"canopy_small", "canopy_1k"} <= set(packaged_specs())
    small = SweepSpec.load("canopy_small").runs()
    assert 24 <= len(small) <= 60
    assert {(r.controller, r.solver) for r in small} >= {("paper", "closed-form"), ("qp", "daqp")}
    big = SweepSpec.load("canopy_1k").runs()
    assert len(big) == 1000
    assert len({r.run_id for r in big}) == 1000  # ids are unique …
    assert [r.run_id for r in SweepSpec.load("canopy_1k").runs()] == [r.run_id for r in big]  # … and stable


def test_run_id_is_a_hash_of_the_parameters():
    run = SweepSpec.load("canopy_small").runs()[0]
    assert RunParams.from_json(run.to_json()) == run
    changed = RunParams(**{**run.__dict__, "repetition": run.repetition + 1})
    assert changed.run_id != run.run_id


def test_random_draws_are_seeded_and_shared_by_the_laws():
    spec = SweepSpec.load("canopy_1k")
    runs = spec.runs()
    first = [dict(r.overrides)["controller.kn"] for r in runs if r.scene_seed == 200 and r.repetition == 0
             and dict(r.overrides)["controller.v_ref"] == 0.1]
    assert len(first) == 5 and len(set(first)) == 1  # every law meets the same draw
    assert 5.0 <= first[0] <= 20.0
    assert len({dict(r.overrides)["controller.kn"] for r in runs}) == 200  # one draw per scene × v_ref × rep


@pytest.mark.parametrize(("text", "key"), [
    ('bogus = 1\n[[families]]\nkind = "canopy"', "bogus"),
    ('[[families]]\nkind = "canopy"\ncolour = "red"', "families[0].colour"),
    ('[[families]]\nkind = "forest"', "families[0].kind"),
    ('[grid]\n"controller.v_reff" = [0.1]\n[[families]]\nkind = "canopy"', "grid.controller.v_reff"),
    ('[random]\n"controller.kn" = [5.0]\n[[families]]\nkind = "canopy"', "random.controller.kn"),
    ('solvers = ["nosuch"]\n[[families]]\nkind = "canopy"', "solvers"),
    ('controllers = ["pid"]\n[[families]]\nkind = "canopy"', "controllers"),
    ('repetitions = 0\n[[families]]\nkind = "canopy"', "repetitions"),
    ('[[families]]\nkind = "scenario"', "families[0].scenario"),
    ('[[families]]\nkind = "planar"\nduration = 0.5', "families[0].duration"),
    ("seed = 1", "families"),
])
def test_bad_spec_names_the_key(tmp_path, text, key):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        SweepSpec.load(path)
    assert info.value.key == key and key in str(info.value)


def test_cli_bad_spec_is_one_line_and_nonzero(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('[grid]\n"controller.nope" = [1.0]\n[[families]]\nkind = "canopy"\n')
    proc = subprocess.run([sys.executable, "-m", "qpctl.cli", "sweep", str(path), "--out", str(tmp_path / "o")],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "grid.controller.nope" in lines[0] and "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "qpctl.cli", "sweep", "no_such_spec"], check=False,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "canopy_small" in proc.stderr  # the packaged specs are listed


# -- the engine -----------------------------------------------------------------------------------
def _square_or_die(x: int) -> int:
    if x == 3:
        os._exit(9)  # the worker process dies, as if killed
    if x == 5:
        raise ValueError("five is not allowed")
    return x * x


def test_engine_survives_a_raising_item_and_a_dying_worker():
    items = [(i,) for i in range(8)]
    outcomes = {o.index: o for o in execute(_square_or_die, items, LocalBackend(2), progress=False)}
    assert sorted(outcomes) == list(range(8))
    assert isinstance(outcomes[3].error, WorkerDied)
    assert isinstance(outcomes[5].error, ValueError) and "five is not allowed" in outcomes[5].message
    assert {i: o.value for i, o in outcomes.items() if o.ok} == {i: i * i for i in (0, 1, 2, 4, 6, 7)}


def test_map_ordered_keeps_order_and_raises_the_first_error():
    assert map_ordered(pow, [(2, k) for k in range(6)], LocalBackend(2), progress=False) == [2**k for k in range(6)]
    with pytest.raises(ValueError, match="five"):
        map_ordered(_square_or_die, [(5,)], LocalBackend(1), progress=False)


def test_unknown_backend_and_address_without_ray_are_config_errors():
    with pytest.raises(ConfigError, match="backend"):
        make_backend("slurm")
    with pytest.raises(ConfigError, match="address"):
        make_backend("local", address="auto")


# -- runs and the store ---------------------------------------------------------------------------
def test_a_run_is_a_pure_function_of_its_parameters(reference):
    row = reference.to_pylist()[0]
    again = execute_run(RunParams.from_json(row["params"]))  # re-run alone, from the row's own record
    for key in ("status", "collided", "ticks", "success"):
        assert again[key] == row[key], key
    for key in ("min_clearance", "rms_tracking_error", "max_abs_torque"):
        assert again[key] == pytest.approx(row[key], rel=1e-9), key
    assert RunParams.from_json(row["params"]).run_id == row["run_id"]


def test_failed_runs_are_recorded_and_the_sweep_goes_on(tmp_path):
    spec = tmp_path / "fail.toml"
    spec.write_text('controllers = ["hsu"]\n[set]\n"sim.duration" = 0.2\n'
                    '[grid]\n"controller.d_safe" = [0.05, 0.9]\n'  # 0.9 m > d_influence: that run cannot start
                    '[[families]]\nkind = "planar"\ncount = 2\n')
    report = run_sweep(spec, tmp_path / "out", jobs=1, progress=False)
    assert (report.ran, report.failed) == (4, 2)
    rows = read_dataset(tmp_path / "out").to_pylist()
    bad = [r for r in rows if r["status"] == "failed"]
    assert len(bad) == 2 and all(r["controller.d_safe"] == 0.9 for r in bad)
    assert all("ConfigError" in r["error"] and "d_safe" in r["error"] for r in bad)
    assert all(r["status"] == "ok" and r["ticks"] == 201 for r in rows if r["controller.d_safe"] == 0.05)
    again = run_sweep(spec, tmp_path / "out", jobs=1, progress=False)  # finished runs, failed included, skipped
    assert (again.ran, again.skipped) == (0, 4)


def test_a_finished_sweep_is_compacted_and_read_once(tmp_path):
    import pyarrow.parquet as pq

    spec = tmp_path / "c.toml"
    spec.write_text('controllers = ["hsu"]\n[set]\n"sim.duration" = 0.1\n[[families]]\nkind = "planar"\ncount = 3\n')
    first = run_sweep(spec, tmp_path / "out", jobs=1, progress=False, limit=2)
    runs = tmp_path / "out" / "runs"
    assert first.ran == 2 and len(list(runs.glob("*.parquet"))) == 2  # not finished: one file per run
    run_sweep(spec, tmp_path / "out", jobs=1, progress=False)
    files = list(runs.glob("*.parquet"))
    assert [p.name[:5] for p in files] == ["part-"]  # finished: one part file
    table = read_dataset(tmp_path / "out")
    assert table.num_rows == 3
    # a compaction killed before it removed the one-row files: each row is still read once
    row = table.slice(0, 1)
    pq.write_table(row, runs / f"{row.column('run_id')[0].as_py()}.parquet")
    again = read_dataset(tmp_path / "out")
    assert again.num_rows == 3 and again.column("run_id").to_pylist() == table.column("run_id").to_pylist()
    assert run_sweep(spec, tmp_path / "out", jobs=1, progress=False).ran == 0


def test_a_folder_holds_one_sweep(spec_file, tmp_path):
    other = tmp_path / "other.toml"
    other.write_text(SPEC.replace("seed = 3", "seed = 4"))
    run_sweep(spec_file, tmp_path / "out", jobs=1, progress=False, limit=1)
    with pytest.raises(ConfigError, match="another sweep"):
        run_sweep(other, tmp_path / "out", jobs=1, progress=False)


# -- resuming after SIGKILL, both backends, against the uninterrupted sweep ------------------------
def _sweep_cmd(spec: Path, out: Path, backend: str) -> list[str]:
    return [sys.executable, "-m", "qpctl.cli", "sweep", str(spec), "--out", str(out), "--backend", backend,
            "--jobs", "2", "--quiet", "--no-summary"]


def _kill_halfway(cmd: list[str], runs: Path, at_least: int, timeout: float = 300.0) -> int:
    """Start ``cmd`` in its own session, SIGKILL its whole process group once ``at_least`` rows exist.
    (``timeout``: the workers may compile every kernel first where the cache is stale — two at once took
    more than 120 s here after a kernel module changed; the sweep itself takes about 10 s.)"""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < timeout:
            if runs.is_dir() and len(list(runs.glob("*.parquet"))) >= at_least:
                break
            assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    return len(list(runs.glob("*.parquet")))


@pytest.mark.parametrize("backend", ["local", "ray"])
def test_sigkill_then_rerun_equals_an_uninterrupted_sweep(spec_file, reference, tmp_path, backend):
    out = tmp_path / backend
    written = _kill_halfway(_sweep_cmd(spec_file, out, backend), out / "runs", at_least=3)
    assert 3 <= written < TOTAL, f"the kill came too late to test anything ({written} of {TOTAL} done)"
    proc = subprocess.run(_sweep_cmd(spec_file, out, backend), check=False, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"{written} already done" in proc.stdout
    resumed = read_dataset(out)
    assert [p.name[:5] for p in (out / "runs").glob("*.parquet")] == ["part-"]  # finished: compacted
    assert resumed.num_rows == TOTAL and resumed.column("status").to_pylist() == ["ok"] * TOTAL
    assert_same_results(resumed, reference)  # same results, run for run
    assert set(resumed.column("worker").to_pylist()) != set(reference.column("worker").to_pylist())


# -- summaries ------------------------------------------------------------------------------------
def test_summary_tables_and_plots(reference, spec_file, tmp_path):
    out = tmp_path / "s"
    run_sweep(spec_file, out, jobs=2, progress=False)
    written = summarize(out)
    names = {p.name for p in written}
    assert {"summary.md", "summary.csv", "clearance_cdf.png", "success_vs_controller_v_ref.png"} <= names
    for p in written:
        assert p.stat().st_size > 0
    import csv

    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert {(r["controller"], r["solver"]) for r in rows} == {("paper", "closed-form"), ("hsu", "closed-form"),
                                                              ("qp", "daqp"), ("qp", "proxqp")}
    data = reference.to_pylist()
    for r in rows:
        mine = [d for d in data if d["controller"] == r["controller"] and d["solver"] == r["solver"]]
        assert int(r["runs"]) == len(mine) == 4
        assert float(r["success_rate"]) == pytest.approx(sum(d["success"] for d in mine) / 4)
        assert int(r["collisions"]) == sum(d["collided"] for d in mine)
    md = (out / "summary.md").read_text()
    assert "| canopy | qp | daqp | 4 |" in md
    proc = subprocess.run([sys.executable, "-m", "qpctl.cli", "sweep", "--summarize", str(tmp_path / "nothing")],
                          check=False, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "no finished runs" in proc.stderr
