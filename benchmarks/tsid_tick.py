"""TSID's C++ torque QP tick beside qpctl's QP tick, in one process, on the same states (issue 23).

    /tmp/tsidenv/bin/python benchmarks/tsid_tick.py [--states 2500] [--stride 2] [--no-joint-bounds]

TSID is not a dependency of qpctl: this script runs in a scratch environment that holds qpctl and
TSID 1.10 built from its sdists against the installed Pinocchio (TSID's binary wheel, built against
another Pinocchio, fails with a MemoryError in ``RobotWrapper(model, ...)`` under pin 4.1; libtsid
1.10.0 has no wheel for Linux x86_64 at all). The environment was made so (≈ 5 min on 2 cores)::

    /work/main/.venv/bin/python -m venv /tmp/tsidenv
    /tmp/tsidenv/bin/pip install pin==4.1.0
    /tmp/tsidenv/bin/pip install -e /work/main
    # the build requirements of libtsid and tsid, against the installed pin (kept at 4.1.0)
    # (/tmp/tsidenv/pins.txt: pin==4.1.0, libpinocchio==4.1.0, eigenpy==3.13.0, coal==3.0.3,
    # libcoal==3.0.3, cmeel-boost==1.90.0, numpy==2.4.6, one a line)
    /tmp/tsidenv/bin/pip install -c /tmp/tsidenv/pins.txt "cmeel[build]" "eiquadprog[build]==1.3.2" \\
        "libpinocchio[build]==4.1.0" "pin[build]==4.1.0" scipy
    # the two sdists, libtsid-1.10.0.tar.gz and tsid-1.10.0.tar.gz, fetched by the URLs that PyPI's
    # simple index lists for them (pip download would build them, dependencies too, to read their metadata)
    tar xzf libtsid-1.10.0.tar.gz && tar xzf tsid-1.10.0.tar.gz
    export CMEEL_JOBS=2 CMAKE_BUILD_PARALLEL_LEVEL=2 PATH=/tmp/tsidenv/bin:$PATH
    pip install --no-build-isolation --no-deps ./libtsid-1.10.0   # the C++ library, ≈ 2 min
    pip install --no-build-isolation --no-deps ./tsid-1.10.0      # its Python bindings, ≈ 2 min

Run from /work/main (so that ``benchmarks`` and the packaged scenarios are found). It runs qpctl's
``panda_spheres`` once in closed loop under the QP, keeps every ``--stride``-th visited state (at most
``--states``), and on each times three things with ``time.perf_counter`` around the call:

* ``floor``: ``pin.computeAllTerms(model, data, q, v)``, the rigid-body terms every torque tick needs;
* ``qpctl``: ``ctrl.step(q, v, t)`` of the scenario's QP controller (with its obstacles, joint,
  torque and torque-rate limits);
* ``tsid``: the reference update (x_d, ẋ_d, ẍ_d at t into the task's TrajectorySample, then
  ``setReference``) and ``formulation.computeProblemData(t, q, v)``, ``solver.solve(hqp)``,
  ``formulation.getActuatorForces(sol)``; ``tsid_core`` is the same tick without the reference update.
  The path is evaluated at each state before the timing starts (qpctl's WaypointPath is Python, ≈ 5 µs a
  call, where qpctl's own tick evaluates it in its compiled kernel): a TSID user has the reference at hand.

TSID's problem is the closest one without obstacles: ``InverseDynamicsFormulationAccForce`` on the
fixed-base Panda (``RobotWrapper(model, FIXED_BASE_SYSTEM)``: the ``(model, bool)`` constructor takes
the model for a floating base, nv − 6 actuators); a ``TaskSE3Equality`` on qpctl's task frame, position
rows only (mask 1,1,1,0,0,0, world-aligned), Kp = 100, Kd = 20, following qpctl's path x_d(t), weight 1
at priority 1; a ``TaskJointPosture`` to the home pose (Kp 25, Kd 10, qpctl's PostureTask gains), weight
1e-3 at priority 1; ``TaskActuationBounds`` ±τ_max and ``TaskJointPosVelAccBounds`` (joint position,
speed and acceleration limits, dt = the scenario's; left out with ``--no-joint-bounds``) as
constraints (priority 0); solved by eiquadprog-fast (``SolverHQuadProgFast``: the 1.10 bindings do not
expose ``SolverHQPFactory``).

The timing is the bench's own (:func:`qpctl.bench.timing.time_on_states`, with its
:class:`~qpctl.bench.timing.PinocchioFloor`): blocks of 25 states, the three in a rotating order, the
garbage collector off, each block opened by an untimed tick that replays the previous state (its time
is the "cold" tick). TSID's ``solve_us`` stage is its three calls without the reference update. Then an
untimed pass over the same states checks both controllers' answers. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time
from importlib.metadata import version
from typing import Any

import numpy as np
import pinocchio as pin
import tsid

from qpctl import Scenario
from qpctl.bench.timing import FLOOR, FloorOutput, PinocchioFloor, StateSequence, summary, time_on_states
from qpctl.run import simulate

KP, KD = 100.0, 20.0  # the task's gains (panda_spheres' controller.kp, kv)
POSTURE_KP, POSTURE_KD, POSTURE_WEIGHT = 25.0, 10.0, 1e-3


class TsidTick:
    """TSID's torque QP on qpctl's robot, following qpctl's path (module docstring)."""

    def __init__(self, ctrl: Any, dt: float, joint_bounds: bool = True) -> None:
        rm = ctrl.robot
        self.path = ctrl.path
        self.robot = tsid.RobotWrapper(rm.model, tsid.FIXED_BASE_SYSTEM, False)
        self.formulation = inv = tsid.InverseDynamicsFormulationAccForce("tsid", self.robot, False)
        q0, v0 = rm.q_home.astype(float), np.zeros(rm.nv)
        inv.computeProblemData(0.0, q0, v0)
        self.ee = tsid.TaskSE3Equality("ee", self.robot, rm.ee_frame)
        self.ee.setKp(KP * np.ones(6))
        self.ee.setKd(KD * np.ones(6))
        self.ee.setMask(np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]))
        self.ee.useLocalFrame(False)  # errors and their derivatives along the world axes, as qpctl's
        inv.addMotionTask(self.ee, 1.0, 1, 0.0)
        self.posture = tsid.TaskJointPosture("posture", self.robot)
        self.posture.setKp(POSTURE_KP * np.ones(rm.nv))
        self.posture.setKd(POSTURE_KD * np.ones(rm.nv))
        home = tsid.TrajectorySample(rm.nq, rm.nv)
        home.value(q0)
        home.derivative(v0)
        home.second_derivative(v0)
        self.posture.setReference(home)
        inv.addMotionTask(self.posture, POSTURE_WEIGHT, 1, 0.0)
        self.actuation = tsid.TaskActuationBounds("torque", self.robot)
        self.actuation.setBounds(-rm.tau_max, rm.tau_max)
        inv.addActuationTask(self.actuation, 1.0, 0, 0.0)
        self.joint_bounds = joint_bounds
        if joint_bounds:
            self.bounds = tsid.TaskJointPosVelAccBounds("joints", self.robot, dt, False)
            self.bounds.setPositionBounds(rm.q_min, rm.q_max)
            self.bounds.setVelocityBounds(rm.v_max)
            if rm.qdd_max is not None and np.all(np.isfinite(rm.qdd_max)):
                self.bounds.setAccelerationBounds(rm.qdd_max)
            inv.addMotionTask(self.bounds, 1.0, 0, 0.0)
        self.sample = tsid.TrajectorySample(12, 6)
        self.rotation = np.eye(3)  # masked out: any orientation
        self.solver = tsid.SolverHQuadProgFast("eiquadprog-fast")
        self.solver.resize(inv.nVar, inv.nEq, inv.nIn)
        self.sol: Any = None
        self.refs: dict[float, tuple[Any, np.ndarray, np.ndarray]] = {}  # t → reference(t), made before timing

    def reference(self, t: float) -> tuple[Any, np.ndarray, np.ndarray]:
        """The path at t [s] as TSID's SE3 sample parts: the placement, its velocity and acceleration (6)."""
        ref = self.path(t)
        z = np.zeros(3)
        return pin.SE3(self.rotation, ref.x), np.concatenate([ref.xd, z]), np.concatenate([ref.xdd, z])

    def set_reference(self, ref: tuple[Any, np.ndarray, np.ndarray]) -> None:
        self.sample.value(ref[0])
        self.sample.derivative(ref[1])
        self.sample.second_derivative(ref[2])
        self.ee.setReference(self.sample)

    def solve(self, q: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
        hqp = self.formulation.computeProblemData(t, q, v)
        self.sol = self.solver.solve(hqp)
        return self.formulation.getActuatorForces(self.sol)

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> FloorOutput:
        """One tick as the bench's timing loop steps a controller: the reference at t (from
        :attr:`refs`, made before the timing), then :meth:`solve`; ``info["solve_us"]`` the latter alone."""
        s = time.perf_counter()
        self.set_reference(self.refs[t])
        m = time.perf_counter()
        self.solve(q, v, t)
        e = time.perf_counter()
        return FloorOutput((e - s) * 1e6, {"solve_us": (e - m) * 1e6})

    def reset(self) -> None:
        """Nothing to forget: eiquadprog-fast starts every solve cold."""

    def task_residual(self) -> float:
        """‖achieved − desired‖ of the position rows' acceleration [m/s²] at the last solution."""
        dv = self.formulation.getAccelerations(self.sol)
        return float(np.linalg.norm(self.ee.getAcceleration(dv) - self.ee.getDesiredAcceleration))


def _stats(samples: np.ndarray) -> dict[str, float]:
    st = summary(samples)
    return {"median_us": round(st["median"], 2), "p99_us": round(st["p99"], 2)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--states", type=int, default=2500, help="states replayed (at most)")
    ap.add_argument("--stride", type=int, default=2, help="every stride-th visited state")
    ap.add_argument("--no-joint-bounds", action="store_true", help="TSID without TaskJointPosVelAccBounds")
    args = ap.parse_args(argv)

    scen = Scenario.load("panda_spheres")
    traj = simulate(scen, kind="qp").trajectory
    idx = np.arange(0, len(traj.t), args.stride)[:args.states]
    states = StateSequence(np.asarray(traj.t)[idx], np.ascontiguousarray(traj.q[idx]), np.ascontiguousarray(traj.v[idx]))
    n = len(states)

    ctrl = scen.build_controller("qp")
    tk = TsidTick(ctrl, float(scen.data["sim"]["dt"]), joint_bounds=not args.no_joint_bounds)
    tk.refs = {float(t): tk.reference(float(t)) for t in states.t}
    times = time_on_states({FLOOR: PinocchioFloor(ctrl.robot), "qpctl": ctrl, "tsid": tk}, states)

    stats = {name: _stats(tt.wall) for name, tt in times.items()}
    stats["tsid_core"] = _stats(times["tsid"].stages["solve_us"])
    base = stats[FLOOR]["median_us"]

    # untimed: what each answered on the same states
    tau_q, tau_t, residual = np.zeros((n, ctrl.robot.nv)), np.zeros((n, ctrl.robot.nv)), np.zeros(n)
    qp_status: dict[str, int] = {}
    tsid_status: dict[int, int] = {}
    ctrl.reset()
    for k in range(n):
        q, v, t = states.q[k], states.v[k], float(states.t[k])
        out = ctrl.step(q, v, t)
        tau_q[k] = out.tau
        qp_status[out.status.value] = qp_status.get(out.status.value, 0) + 1
        tk.set_reference(tk.refs[t])
        tau_t[k] = tk.solve(q, v, t)
        tsid_status[tk.sol.status] = tsid_status.get(tk.sol.status, 0) + 1
        residual[k] = tk.task_residual()
    diff = np.linalg.norm(tau_t - tau_q, axis=1)
    print(json.dumps({
        "ticks": n, "stride": args.stride, "tsid_version": version("tsid"), "pin_version": pin.__version__,
        "qpctl_solver": ctrl.solver, "tsid_joint_bounds": tk.joint_bounds,
        **{name: s | {"ratio_to_floor": round(s["median_us"] / base, 2)} for name, s in stats.items()},
        "ratio_tsid_to_qpctl": round(stats["tsid"]["median_us"] / stats["qpctl"]["median_us"], 3),
        "cold_median_us": {name: round(summary(tt.cold)["median"], 2) for name, tt in times.items()},
        "checks": {
            "tsid_tau_finite": bool(np.all(np.isfinite(tau_t))),
            "tsid_status": {str(s): c for s, c in sorted(tsid_status.items())},  # 0: HQP_STATUS_OPTIMAL
            "tsid_ee_acc_residual_median": float(np.median(residual)),  # [m/s²], 0 where the task is met
            "tsid_ee_acc_residual_p99": float(np.percentile(residual, 99)),
            "qpctl_status": qp_status,
            "tau_diff_median_Nm": round(float(np.median(diff)), 3),  # ‖τ_tsid − τ_qpctl‖, not the same QP
        },
    }))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
