"""The paper reproduction's machinery (reproduction.reproduce) end to end, on a shortened scenario.

The full reproduction (5 s runs, `make demo`) takes minutes; here every run lasts 0.3 s, which is
enough to check that each run writes its standard outputs, that report.md has the tables of
DESIGN.md §4 for every law and every reference velocity of the sweep, a verdict per claim, and
that the figures are written. The numbers themselves are not checked: at 0.3 s no law has met an
obstacle yet.
"""

from __future__ import annotations

import json
import re

import pytest

from qpctl.scenario import Scenario
from reproduction import reproduce
from reproduction.reproduce import LAWS, VREF_LETTERS, VREF_SWEEP, RunSpec, build_scenario, plan

SHORT = ["sim.duration=0.3"]


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """One shortened reproduction (one moved-obstacle layout, QP included when it imports)."""
    out = tmp_path_factory.mktemp("paper")
    argv = ["--out", str(out), "--jitter", "1", "--run-figures", "main", "--quiet", "--jobs", "2"]
    for item in SHORT:
        argv += ["--set", item]
    assert reproduce.main(argv) == 0
    return out


def laws_run() -> list[str]:
    return [law for law in LAWS if law != "qp" or reproduce.qp_available()[0]]


def table(text: str, heading: str) -> list[str]:
    """The rows of the Markdown table under the heading that starts with ``heading``."""
    section = text.split(heading, 1)[1]
    rows = re.findall(r"^\|.*\|$", section.split("\n## ", 1)[0], flags=re.MULTILINE)
    return rows[2:]  # header and separator dropped


def test_report_has_every_law_and_metric(short_run):
    text = (short_run / "report.md").read_text()
    rows = table(text, "## (a)")
    assert [r.split("|")[1].strip() for r in rows] == laws_run()
    header = text.split("## (a)", 1)[1]
    for name in ("rms e", "max e", "final e", "max abs τ", "max abs τ̇", "min clearance", "collided",
                 "final ‖e_N‖", "tick median"):
        assert name in header.split("\n|---", 1)[0], name


def test_sweep_table_has_four_velocities_for_every_law(short_run):
    text = (short_run / "report.md").read_text()
    header = text.split("## (b)", 1)[1].split("\n|---", 1)[0]
    for law in laws_run():
        assert f"{law} min clearance" in header and f"{law} collided" in header
    rows = table(text, "## (b)")
    assert len(rows) == 4
    for row, letter, v in zip(rows, VREF_LETTERS, VREF_SWEEP):
        assert row.startswith(f"| {letter} = {v:g} |")
        assert "| – |" not in row  # every law ran at every velocity
    assert list(VREF_SWEEP) == sorted(VREF_SWEEP) and len(set(VREF_SWEEP)) == 4


def test_each_claim_has_numbers_and_a_verdict(short_run):
    rows = table((short_run / "report.md").read_text(), "## (c)")
    assert len(rows) == 3
    for i, row in enumerate(rows, start=1):
        assert row.startswith(f"| {i}. ")
        assert re.search(r"\*\*(reproduced|partly|not reproduced)\*\*", row), row


def test_every_run_writes_its_standard_outputs(short_run):
    summary = json.loads((short_run / "summary.json").read_text())
    names = {s["run"] for s in summary if not s["skipped"]}
    assert set(laws_run()) <= names
    for name in names:
        run = short_run / name
        assert (run / "trajectory.npz").is_file() and (run / "metrics.json").is_file(), name
    for law in laws_run():  # --run-figures main: the main runs have their own figures and replay too
        assert (short_run / law / "torques.png").is_file() and (short_run / law / "replay.html").is_file()
    assert not (short_run / "jitter1-paper" / "replay.html").exists()  # nor the others
    assert "](paper/replay.html)" in (short_run / "report.md").read_text()


def test_figures_are_written_and_small(short_run):
    for name in ("fig_torques.png", "fig_configurations.png", "fig_vref.png"):
        path = short_run / name
        assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
        assert path.stat().st_size < 150_000, (name, path.stat().st_size)
        assert f"]({name})" in (short_run / "report.md").read_text()


def test_plan_reuses_the_nominal_velocity_and_moves_obstacles_within_the_radius():
    base = Scenario.load("paper", SHORT)
    specs = plan(base, laws=["paper", "hsu"], jitter=2, seed=0)
    nominal = base.data["controller"]["v_ref"]
    assert nominal in VREF_SWEEP  # the scenario's v_ref is one of a < b < c < d
    assert not any(s.group == "sweep" and s.v_ref == nominal for s in specs)
    assert len({s.name for s in specs}) == len(specs)
    moved = [s for s in specs if s.group == "jitter"]
    assert len(moved) == 4
    for spec in moved:
        scen = build_scenario("paper", SHORT, spec)
        for o, o0 in zip(scen.data["obstacles"], base.data["obstacles"]):
            shift = ((o["position"][0] - o0["position"][0]) ** 2 + (o["position"][1] - o0["position"][1]) ** 2) ** 0.5
            assert 0 < shift <= reproduce.JITTER_RADIUS + 1e-12


def test_unavailable_qp_is_skipped_with_a_note(tmp_path, monkeypatch):
    """If the QP controller cannot be imported, its rows are skipped and the report says why."""
    monkeypatch.setattr(reproduce, "qp_available", lambda: (False, "No module named 'qpctl.controllers.qp'"))
    out = tmp_path / "noqp"
    argv = ["--out", str(out), "--jitter", "0", "--run-figures", "none", "--quiet", "--jobs", "1",
            "--set", "sim.duration=0.05"]
    assert reproduce.main(argv) == 0
    text = (out / "report.md").read_text()
    assert "qp rows skipped" in text
    assert [r.split("|")[1].strip() for r in table(text, "## (a)")] == ["paper", "hsu"]


def test_run_one_reports_an_import_error_of_the_qp_as_skipped(tmp_path, monkeypatch):
    import qpctl.run

    def broken(*args, **kwargs):
        raise ImportError("qp is being written")

    monkeypatch.setattr(qpctl.run, "simulate", broken)
    summary = reproduce.run_one("paper", SHORT, RunSpec("qp", "qp", "main"), tmp_path)
    assert summary.skipped and "qp is being written" in summary.skipped
    with pytest.raises(ImportError):
        reproduce.run_one("paper", SHORT, RunSpec("paper", "paper", "main"), tmp_path)
