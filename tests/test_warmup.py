"""``warmup()`` covers every entry point of the tick: in a fresh interpreter, after it, no controller
path compiles (or loads) another kernel signature.

The child process runs :func:`qpctl.warmup.warmup`, notes every compiled kernel's signatures (every
module of :mod:`qpctl.kernels`), then steps each controller through each of its paths — the closed
forms with closed-form shapes and with python-fcl's, the QP on DAQP's C API (task hard first, and
relaxed), the QP under a tick budget, on another solver, with a custom task (the Python formulation),
with J̇e_N, a failing QP (the fallback's record), and the world clearance — and reports any kernel
whose signatures changed. A miss here means a control loop would compile in its first ticks.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

CHILD = textwrap.dedent("""
    import importlib, json, pkgutil
    import numpy as np
    import qpctl.kernels
    from qpctl import LawGains, Obstacle, QPConfig, QPController, WaypointPath, planar_arm, panda
    from qpctl.controllers.closed_form import HsuController, PaperController
    from qpctl.tasks import AccelerationTask, EndEffectorTask, PostureTask
    from qpctl.tick import WorldClearance
    from qpctl.warmup import warmup

    warmup()
    modules = [importlib.import_module("qpctl.kernels." + m.name) for m in pkgutil.iter_modules(qpctl.kernels.__path__)]
    kernels = {f"{mod.__name__}.{name}": k for mod in modules for name, k in vars(mod).items() if hasattr(k, "signatures")}
    before = {name: len(k.signatures) for name, k in kernels.items()}

    class MyTask(PostureTask):
        pass

    robot = planar_arm(tau_max=500.0)
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=1.0)
    spheres = [Obstacle("sphere", np.array([-0.7, -1.5, 0.0]), radius=0.1),
               Obstacle("capsule", np.array([-1.3, -1.2, 0.0]), radius=0.05, length=0.4)]
    boxes = spheres + [Obstacle("box", np.array([0.5, -0.5, 0.0]), size=np.array([0.1, 0.1, 0.1])),
                       Obstacle("cylinder", np.array([0.2, -1.9, 0.0]), radius=0.05, length=0.3)]
    gains = LawGains(d_influence=0.5, d_safe=0.05)
    q0, v0 = robot.q_home.astype(float), np.array([0.1, -0.2, 0.3])
    ctrls = [PaperController(robot, path, spheres, gains), PaperController(robot, path, boxes, gains),
             HsuController(robot, path, boxes, gains, broadphase=True),
             PaperController(robot, path, spheres, LawGains(d_influence=0.5, d_safe=0.05, jdot_en=True)),
             QPController(robot, path, spheres, gains), QPController(robot, path, boxes, gains),
             QPController(robot, path, spheres, gains, QPConfig(task_relaxation="always")),
             QPController(robot, path, spheres, gains, QPConfig(task_relaxation="on_failure")),
             QPController(robot, path, boxes, gains, QPConfig(tick_budget_us=5000.0)),
             QPController(robot, path, spheres, gains, QPConfig(solver="proxqp")),
             QPController(robot, path, spheres, gains, QPConfig(posture_weight=1.0), broadphase=True),
             QPController(robot, path, spheres, gains, tasks=[AccelerationTask(), EndEffectorTask(), MyTask(robot.q_home)]),
             QPController(panda(), WaypointPath([[0.4, 0.0, 0.5], [0.5, 0.1, 0.4]], duration=1.0), [], gains)]
    for ctrl in ctrls:
        q = ctrl.robot.q_home.astype(float)
        for k in range(3):
            ctrl.step(q, v0[:ctrl.n] if ctrl.n == 3 else np.zeros(ctrl.n), 0.1 + 1e-3 * k)
    # a QP whose budget is spent before the solve, every tick: the fallback chain writes the record
    bad = QPController(robot, path, spheres, gains, QPConfig(tick_budget_us=1e-3))
    for k in range(3):
        bad.step(q0, v0, 0.1 + 1e-3 * k)
    WorldClearance(robot, boxes)(q0, 0.1)
    after = {name: len(k.signatures) for name, k in kernels.items()}
    print(json.dumps({"new": {n: after[n] - before[n] for n in kernels if after[n] != before[n]},
                      "entry": sorted(n for n in kernels if n.startswith("qpctl.kernels.tick.")),
                      "fallback": bad.last.info.get("fallback")}))
""")


def test_warmup_leaves_nothing_to_compile():
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=600,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["new"] == {}, f"kernel signatures compiled after warmup(): {out['new']}"
    assert "qpctl.kernels.tick.tick_qp_native_hard_first" in out["entry"]  # the scan saw the entry points
    assert out["fallback"], "the failing QP did not take the fallback chain: its path went untested"


def test_an_edit_to_any_kernel_module_clears_the_cached_kernels(tmp_path, monkeypatch):
    """numba invalidates a cached kernel only when its own file changes; qpctl.kernels clears the
    folder's cache when the digest of all its modules changes (an edit to a stage reaches the entry
    points that call it). On a folder of fake cache files: a foreign stamp clears the kernels' files
    (not others), writes the current digest, and a second call finds nothing to do."""
    from qpctl import kernels

    for name in ("rigid.rigid_terms-10.py311.nbi", "rigid.rigid_terms-10.py311.1.nbc",
                 "tick.state-70.py311.nbi", "other_package.f-3.py311.nbi", "notes.txt"):
        (tmp_path / name).write_text("x")
    (tmp_path / "qpctl-kernels.sha256").write_text("a digest of other sources")
    monkeypatch.setattr(kernels, "_cache_path", lambda: str(tmp_path))
    assert kernels.invalidate_stale_cache()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "other_package.f-3.py311.nbi",
                                                         "qpctl-kernels.sha256"]
    assert (tmp_path / "qpctl-kernels.sha256").read_text() == kernels.sources_digest()
    (tmp_path / "rigid.rigid_terms-10.py311.nbi").write_text("cached under the current digest")
    assert not kernels.invalidate_stale_cache()
    assert (tmp_path / "rigid.rigid_terms-10.py311.nbi").exists()


def test_the_real_cache_carries_the_current_digest():
    """After ``import qpctl.kernels`` the stamp beside numba's cache of the kernels is this source's."""
    from qpctl import kernels

    path = kernels._cache_path()
    assert path is not None
    with open(os.path.join(path, "qpctl-kernels.sha256"), encoding="ascii") as fh:
        assert fh.read().strip() == kernels.sources_digest()


GUARD_CHILD = textwrap.dedent("""
    import importlib, json, pkgutil, sys
    sys.path.insert(0, TESTS)
    import numpy as np
    import pinocchio as pin
    import qpctl.kernels
    from qpctl.safety import BackupGuard
    from qpctl.safety.walk import Walk
    from qpctl.simulation import Simulator
    from qpctl.tick import WorldClearance
    from test_retreat import DT, Q, Hold, Push, arm, closing_sphere, swing

    walked = []
    attempt = Walk.attempt
    def counted(self, *args):
        out = attempt(self, *args)
        walked.append(out[0])
        return out
    Walk.attempt = counted

    robot = arm()
    swung = BackupGuard(Push(robot, [swing(robot)], Q, stiffness=4.0), DT)
    drift = BackupGuard(Hold(robot, [closing_sphere(robot)]), DT)
    for guard in (swung, drift):
        guard.warmup()
    WorldClearance(robot, [swing(robot)], self_pairs=[(0, 2)])(Q, 0.0)  # the simulator's recorded clearance
    modules = [importlib.import_module("qpctl.kernels." + m.name) for m in pkgutil.iter_modules(qpctl.kernels.__path__)]
    kernels = {f"{mod.__name__}.{name}": k for mod in modules for name, k in vars(mod).items() if hasattr(k, "signatures")}
    before = {name: len(k.signatures) for name, k in kernels.items()}
    walked.clear()
    Simulator(swung, dt=DT, duration=2.0).run(Q + np.array([0.0, 0.0, 0.6]))
    Simulator(drift, dt=DT, duration=3.0).run(Q)
    after = {name: len(k.signatures) for name, k in kernels.items()}
    stats = {key: swung.stats[key] + drift.stats[key] for key in ("backup", "retreats_found", "proposal_retreats_found")}
    print(json.dumps({"new": {n: after[n] - before[n] for n in kernels if after[n] != before[n]}, "stats": stats,
                      "walks": sum(walked)}))
""")


def test_the_guards_warmup_leaves_nothing_to_compile():
    """:meth:`BackupGuard.warmup` covers every kernel the check calls from Python: in a fresh interpreter,
    after two guards' warmups (a swaying and a drifting sphere on the planar arm; the simulator's own
    clearance with its self pairs evaluated once), their runs — the stored
    brake applied, retreats found and walked, stops settled, rests tested against the sweep and the drift —
    load no further kernel signature (each a numba cache load of ~5 ms in the middle of a control loop)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    tests = os.path.dirname(os.path.abspath(__file__))
    proc = subprocess.run([sys.executable, "-c", f"TESTS = {tests!r}\n" + GUARD_CHILD], env=env,
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["stats"]["backup"] > 0 and out["stats"]["retreats_found"] + out["stats"]["proposal_retreats_found"] > 0
    assert out["walks"] > 0  # the paths the runs were to take
    assert out["new"] == {}, f"kernel signatures loaded after the guards' warmup(): {out['new']}"
