"""The command line: errors are one line on stderr with exit status 2; `simulate` writes the
DESIGN.md §4 outputs, consistent with each other and with an independent recomputation; a failing
run leaves no output folder behind."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from qpctl import SimulationError
from qpctl.cli import main

ARRAYS_TxN = ("q", "v", "tau", "e_null")
ARRAYS_TxM = ("x", "x_ref", "xd_ref", "xdd_ref")
ARRAYS_T = ("t", "clearance", "tick_us")
METRIC_KEYS = ("scenario", "controller", "solver", "gravity", "rms_tracking_error", "max_tracking_error",
               "final_tracking_error", "max_abs_torque", "max_abs_torque_rate", "min_clearance", "collided",
               "final_null_space_error", "tick_us_median", "tick_us_p99", "tick_us_max")


def _assert_one_line_error(err: str, *needles: str) -> None:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith("qpctl: error:")
    for needle in needles:
        assert needle in lines[0]


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "paper"
    assert main(["simulate", "paper", "--out", str(out), "--set", "sim.duration=0.2", "--quiet"]) == 0
    return out


def test_simulate_writes_trajectory_with_design_arrays(paper_run, thin_rod):
    with np.load(paper_run / "trajectory.npz") as data:
        arrays = {k: data[k] for k in data.files}
    T, n, m = 201, 3, 2  # 0.2 s at 1 ms, both ends included
    for name in ARRAYS_T:
        assert arrays[name].shape == (T,), name
    for name in ARRAYS_TxN:
        assert arrays[name].shape == (T, n), name
    for name in ARRAYS_TxM:
        assert arrays[name].shape == (T, m), name
    np.testing.assert_allclose(arrays["t"], np.arange(T) * 1e-3, atol=1e-12)
    np.testing.assert_allclose(arrays["q"][0], [np.pi, np.pi / 2, 0.0])
    # x is the tip of the recorded configuration (independent thin-rod kinematics).
    for k in (0, 100, 200):
        np.testing.assert_allclose(arrays["x"][k], thin_rod.ee(arrays["q"][k]), atol=1e-12)
    assert np.all(np.isfinite(arrays["clearance"])) and np.all(arrays["tick_us"] > 0)


def test_simulate_writes_metrics_consistent_with_trajectory(paper_run):
    text = (paper_run / "metrics.json").read_text()

    def no_constants(name: str) -> None:
        raise AssertionError(f"metrics.json contains {name}, which is not JSON")

    metrics = json.loads(text, parse_constant=no_constants)
    for key in METRIC_KEYS:
        assert key in metrics, key
    assert metrics["scenario"] == "paper" and metrics["controller"] == "paper"
    np.testing.assert_allclose(metrics["gravity"], [0.0, -9.81, 0.0])
    with np.load(paper_run / "trajectory.npz") as d:
        err = np.linalg.norm(d["x_ref"] - d["x"], axis=1)
        assert metrics["max_tracking_error"] == pytest.approx(err.max())
        assert metrics["final_tracking_error"] == pytest.approx(err[-1])
        assert metrics["rms_tracking_error"] == pytest.approx(np.sqrt(np.mean(err**2)))
        assert metrics["max_abs_torque"] == pytest.approx(np.abs(d["tau"]).max())
        assert metrics["max_abs_torque_rate"] == pytest.approx((np.abs(np.diff(d["tau"], axis=0)) / 1e-3).max())
        assert metrics["min_clearance"] == pytest.approx(d["clearance"].min())
        assert metrics["collided"] == bool(d["clearance"].min() < 0)
        assert metrics["final_null_space_error"] == pytest.approx(np.linalg.norm(d["e_null"][-1]))
        assert metrics["tick_us_max"] == pytest.approx(d["tick_us"].max())
        assert metrics["tick_us_median"] <= metrics["tick_us_p99"] <= metrics["tick_us_max"]


def test_simulate_writes_png_figures(paper_run):
    pngs = sorted(paper_run.glob("*.png"))
    assert len(pngs) >= 3
    for png in pngs:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Nothing else lingers beside the outputs (no temporary folders).
    assert not [p for p in paper_run.parent.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("args, needles", [
    (["simulate", "paper", "--set", "controller.foo=1"], ["controller.foo"]),
    (["simulate", "paper", "--set", "sim.dt=-1"], ["sim.dt"]),
    (["simulate", "no-such-scenario"], ["no-such-scenario"]),
])
def test_errors_are_one_line_with_status_2(args, needles, capsys, tmp_path):
    out = tmp_path / "out"
    assert main([*args, "--out", str(out), "--quiet"]) == 2
    _assert_one_line_error(capsys.readouterr().err, *needles)
    assert not out.exists()


def test_bad_file_via_cli(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text('[path]\nwaypoints = [[1.0, -1.5]]\nduration = 1.0\n[sim]\ndt = "fast"\n')
    assert main(["simulate", str(bad), "--out", str(tmp_path / "out")]) == 2
    _assert_one_line_error(capsys.readouterr().err, str(bad), "sim.dt")


def test_installed_console_script_reports_errors_without_traceback(tmp_path):
    exe = Path(sys.executable).parent / "qpctl"
    assert exe.is_file(), "the package's console script is installed in the environment"
    out = tmp_path / "out"
    proc = subprocess.run([str(exe), "simulate", "paper", "--set", "robot.nonsense=1", "--out", str(out)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2
    _assert_one_line_error(proc.stderr, "robot.nonsense")
    assert proc.stdout == ""
    assert not out.exists()


def test_failing_simulation_leaves_no_output(tmp_path, monkeypatch, capsys):
    from qpctl.simulation.simulator import Simulator

    def diverge(self, q0, v0=None):
        raise SimulationError("state diverged at t = 0.1000 s")

    monkeypatch.setattr(Simulator, "run", diverge)
    out = tmp_path / "out"
    assert main(["simulate", "paper", "--out", str(out), "--quiet"]) == 2
    _assert_one_line_error(capsys.readouterr().err, "diverged")
    assert list(tmp_path.iterdir()) == []


def test_failure_while_writing_leaves_no_half_written_folder(tmp_path, monkeypatch, capsys):
    """The npz and json are written, then the figures fail: neither the folder nor a temp folder remains."""
    import qpctl.plots

    def broken(*_args, **_kwargs):
        raise SimulationError("figure writer failed")

    monkeypatch.setattr(qpctl.plots, "write_figures", broken)
    out = tmp_path / "out"
    assert main(["simulate", "paper", "--out", str(out), "--set", "sim.duration=0.01", "--quiet"]) == 2
    _assert_one_line_error(capsys.readouterr().err, "figure writer failed")
    assert list(tmp_path.iterdir()) == []


def test_solvers_lists_every_installed_solver_and_marks_the_default(capsys):
    from qpctl.controllers.qp import QPConfig
    from qpctl.scenario import SCHEMA
    from qpctl.solvers import available_solvers

    assert main(["solvers"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split()[0] for line in lines] == available_solvers()
    default = [line.split()[0] for line in lines if line.endswith("(default)")]
    assert default == [QPConfig().solver] == [SCHEMA["controller"]["solver"][1]]


def test_unwritable_output_is_a_one_line_error(tmp_path, capsys):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where the output's parent folder should be")
    out = blocker / "run"
    assert main(["simulate", "paper", "--out", str(out), "--set", "sim.duration=0.01", "--quiet"]) == 2
    _assert_one_line_error(capsys.readouterr().err, "blocker")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]


HOSTILE = ["0", "-1", "1e308", "nan", "inf", "-inf", "[]", "[0]", "[1,2]", "[[1,2,3]]", '"x"', '""', "true", "1.5",
           "[1e9,1e9,1e9]", "[0,0,0,0]", "[[0,0],[0,0]]", '[["a","b"]]', "{}", "-0.0", "3"]


def test_no_override_a_user_can_write_is_an_internal_error(tmp_path, capsys):
    """Seeded random --set overrides of every scenario key with hostile values (wrong types, empty,
    infinite, NaN, huge, wrong lengths) on three packaged scenarios: exit 0 or 2, never 3 (issue 12),
    and a failure is one line. Includes the two this found: a 2-vector gravity and a 1e308 s run."""
    import random

    from qpctl.scenario import SCHEMA

    keys = [f"{sec}.{k}" for sec, tab in SCHEMA.items() if isinstance(tab, dict) for k in tab]
    rng = random.Random(12)
    cases = [("paper", ["robot.gravity=[1,2]"]), ("panda_harvest", ["sim.duration=1e308"])]
    cases += [(rng.choice(["paper", "panda_harvest", "panda_canopy"]),
               [f"{rng.choice(keys)}={rng.choice(HOSTILE)}" for _ in range(rng.randint(1, 2))]) for _ in range(150)]
    codes = {}
    for scen, sets in cases:
        args = ["simulate", scen, "--quiet", "--no-figures", "--out", str(tmp_path / "run"), "--set", "sim.duration=0.02"]
        for s in sets:
            args += ["--set", s]
        code = main(args)
        err = capsys.readouterr().err
        assert code in (0, 2), (scen, sets, err)
        if code == 2:
            _assert_one_line_error(err)
        codes[code] = codes.get(code, 0) + 1
    assert codes.get(2, 0) > 100 and codes.get(0, 0) >= 3, codes  # most are refused, a few run


def test_simulate_under_pybullet_and_its_notes(tmp_path, capsys):
    """``--sim pybullet`` runs and records the simulator; PyBullet's integrator is said not to be RK4."""
    pytest.importorskip("pybullet")
    out = tmp_path / "pb"
    assert main(["simulate", "paper", "--sim", "pybullet", "--out", str(out), "--set", "sim.duration=0.05",
                 "--quiet", "--no-figures"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["simulator"] == "pybullet"
    assert any("semi-implicit Euler" in n for n in metrics["simulator_notes"])
    assert "pybullet: PyBullet integrates with semi-implicit Euler" in capsys.readouterr().out


def test_pybullet_import_prints_nothing():
    """PyBullet's C module prints its build time to stdout on import; the adapter keeps it out of
    ``qpctl simulate``'s output (a fresh interpreter, where the import really happens)."""
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", "import qpctl.adapters.pybullet; print('ok')"],
                          capture_output=True, text=True, timeout=120, check=True)
    assert proc.stdout == "ok\n", proc.stdout
