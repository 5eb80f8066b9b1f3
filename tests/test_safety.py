"""The brake family, the oracle and the verified backup (qpctl.safety, issue 22 items 2 and 3).

References: a rollout integrated here (RK4 on Pinocchio's ABA written out, the torque held over each
step, the clearance by python-fcl on capsules posed here), and a bound on the deceleration the drives
allow for a state the oracle must not certify."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

from qpctl import LawGains, Obstacle, WaypointPath, planar_arm
from qpctl.controllers.qp import QPConfig, QPController
from qpctl.geometry.distance import DistanceEngine
from qpctl.safety import BackupGuard, certify, rollout
from qpctl.safety.oracle import REST_SPEED, REST_TIME, brake_torque
from qpctl.simulation import Simulator

DT = 2e-3


def arm(rate: float = 3000.0):
    return planar_arm(tau_max=1500.0).with_limits(tau_rate_max=rate)


def controller(obstacles: list[Obstacle], rate: float = 3000.0) -> QPController:
    path = WaypointPath([[-1.0, -2.0], [1.0, -1.5]], duration=2.0)
    return QPController(arm(rate), path, obstacles, LawGains(d_influence=0.3, d_safe=0.05), QPConfig())


def reference_rollout(robot, obstacles, q, v, tau_prev, gain, steps):
    """Least clearance [m] and time to rest of the brake, integrated here."""
    model, data = robot.model, robot.model.createData()
    engine = DistanceEngine([c.radius for c in robot.capsules], obstacles, broadphase=False)
    tau, worst, still = np.asarray(tau_prev, float), np.inf, 0.0
    for k in range(steps):
        pin.forwardKinematics(model, data, q)
        seg = np.array([[data.oMi[c.joint_id].act(c.p0), data.oMi[c.joint_id].act(c.p1)] for c in robot.capsules])
        engine.update(seg, 0.0)
        worst = min(worst, engine.min_distance())
        still = still + DT if np.all(np.abs(v) <= REST_SPEED) else 0.0
        if still >= REST_TIME:
            return worst, k * DT
        tau = brake_torque(robot, data, q, v, tau, gain, DT)

        def f(qq, vv, tau=tau):
            return pin.aba(model, data, qq, vv, tau)

        k1q, k1v = v, f(q, v)
        k2q, k2v = v + DT / 2 * k1v, f(q + DT / 2 * k1q, v + DT / 2 * k1v)
        k3q, k3v = v + DT / 2 * k2v, f(q + DT / 2 * k2q, v + DT / 2 * k2v)
        k4q, k4v = v + DT * k3v, f(q + DT * k3q, v + DT * k3v)
        q, v = q + DT / 6 * (k1q + 2 * k2q + 2 * k3q + k4q), v + DT / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return worst, np.inf


def test_rollout_equals_an_independent_integration():
    """From a moving state near a box, the oracle's rollout (the built-in simulator) and the one
    integrated here agree on the least clearance (1e-6 m: the simulator's closed-form box against
    python-fcl's GJK) and the time to rest (exactly, in steps)."""
    obstacles = [Obstacle("box", [-0.4, -1.3], size=[0.2, 0.2, 0.2])]
    ctrl = controller(obstacles)
    q, v = np.array([np.pi, np.pi / 2, 0.0]), np.array([0.8, -0.5, 1.0])
    tau_prev = pin.computeGeneralizedGravity(ctrl.robot.model, ctrl.robot.model.createData(), q)
    sim = Simulator(ctrl, dt=DT, duration=DT)
    for gain in (25.0,):
        c = rollout(sim, q, v, tau_prev, 0.0, gain, horizon=3.0)
        worst, t_rest = reference_rollout(ctrl.robot, obstacles, q.copy(), v.copy(), tau_prev, gain, 1500)
        assert c.min_clearance == pytest.approx(worst, abs=1e-6)
        assert c.t_rest == pytest.approx(t_rest, abs=1e-12)
        assert np.isfinite(c.t_rest)


def test_oracle_certifies_rest_and_refuses_what_no_drive_can_stop():
    """At rest 0.5 m from a sphere: certified (a brake, at rest, clearance kept). A link tip 2 cm from a
    sphere closing at 8 m/s: to stop within 2 cm needs 1600 m/s², more than the drives give that point
    along x (Σ|nᵀJ M⁻¹|ᵢ(τ_max − |gᵢ|), computed here), so no brake that keeps the tip's course stops in
    time: not certified, every brake of the family collides."""
    robot = arm()
    q = np.array([np.pi, np.pi / 2, 0.0])
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    tip = data.oMi[3].act(robot.capsules[2].p1)  # link 3's far end, (−1, −2)
    far = controller([Obstacle("sphere", tip[:2] + [0.5 + 0.05 + 0.1, 0.0], radius=0.1)])
    c = certify(far, q, np.zeros(3), np.full(3, np.nan), 0.0, DT)
    assert c.viable and c.min_clearance > 0.4
    # closing on a sphere just beyond the tip along −x: the tip moves along −x when joint 1 turns
    pin.computeJointJacobians(robot.model, data, q)
    J = pin.getFrameJacobian(robot.model, data, robot.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)[:2]
    v = np.linalg.lstsq(J, np.array([-8.0, 0.0]), rcond=None)[0]
    near = controller([Obstacle("sphere", tip[:2] + [-(0.05 + 0.02 + 0.1), 0.0], radius=0.1)])
    M = pin.crba(robot.model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    g = pin.computeGeneralizedGravity(robot.model, data, q)
    row = np.array([1.0, 0.0]) @ J @ np.linalg.inv(M)
    assert float(np.abs(row) @ (robot.tau_max - np.abs(g))) < 8.0**2 / (2 * 0.02)
    c = certify(near, q, v, np.full(3, np.nan), 0.0, DT)
    assert not c.viable and c.min_clearance < 0


class Pusher:
    """A stand-in controller: holds gravity, then (from ``t_push``) pushes joint 1 as hard as it may."""

    def __init__(self, inner: QPController, t_push: float) -> None:
        self.inner, self.t_push = inner, t_push
        self.robot, self.obstacles = inner.robot, inner.obstacles

    def reset(self) -> None:
        pass

    def warmup(self) -> float:
        return 0.0

    def step(self, q, v, t):
        data = self.robot.model.createData()
        tau = pin.computeGeneralizedGravity(self.robot.model, data, q)
        if t >= self.t_push:
            tau = tau + np.array([-self.robot.tau_max[0], 0.0, 0.0])

        return SimpleNamespace(tau=tau, info={})


def pushed_arm(t_push: float) -> tuple[Any, np.ndarray, Any, BackupGuard]:
    """The arm at q = (π, π/2, 0) with a sphere 0.1 m beyond its tip's capsule, behind the guard, and the
    stand-in controller that pushes it from ``t_push`` [s]: (robot, q, the inner controller, the guard)."""
    robot = arm()
    q = np.array([np.pi, np.pi / 2, 0.0])
    data = robot.model.createData()
    pin.forwardKinematics(robot.model, data, q)
    tip = data.oMi[3].act(robot.capsules[2].p1)
    inner = controller([Obstacle("sphere", tip[:2] + [-(0.05 + 0.04 + 0.1), 0.0], radius=0.1)])
    guard = BackupGuard(Pusher(inner, t_push=t_push), dt=DT)  # type: ignore[arg-type]
    guard._limit = None  # the stand-in has no torque limit to tell
    return robot, q, inner, guard


def test_backup_guard_applies_the_stored_brake_when_the_proposal_cannot_stop():
    """A stand-in controller holds the arm, then pushes it into an obstacle: the held ticks are verified
    and applied as proposed; once the push's successor has no verified brake, the guard applies the
    stored brake's torque (from the state and the torque applied last) and says so."""
    robot, q, _, guard = pushed_arm(2 * DT)
    v, tau_prev = np.zeros(3), np.full(3, np.nan)
    for k in range(2):
        out = guard.step(q, v, k * DT)
        assert "backup" not in out.info and guard._gain is not None
        tau_prev = out.tau
    v = np.array([0.3, -0.3, 0.3])  # moving: the brake's torque is beyond the rate window of the held one
    out = guard.step(q, v, 2 * DT)
    assert out.info.get("backup") == guard._gain
    data = robot.model.createData()
    want = brake_torque(robot, data, q, v, tau_prev, guard._gain, DT)
    assert np.array_equal(out.tau, want)
    assert not np.allclose(want, brake_torque(robot, data, q, v, np.full(3, np.nan), guard._gain, DT))
    assert guard.stats == {**guard.stats, "checked": 3, "backup": 1}


def test_collisions_at_rest_counts_the_contacts_a_stop_cannot_avoid():
    """Issue 22, item 4, in the metrics: a run whose clearance crosses below 0 three times — with the
    arm at rest, moving, at rest again but only barely moving (0.5 rad/s on one joint) — counts one
    contact at rest."""
    from qpctl.simulation.metrics import compute_metrics
    from qpctl.simulation.trajectory import Trajectory

    T, n = 12, 3
    clearance = np.array([0.1, -0.01, -0.02, 0.1, 0.1, -0.01, 0.1, 0.1, -0.01, 0.2, 0.2, 0.2])
    v = np.zeros((T, n))
    v[5] = [0.0, 0.3, 0.0]
    v[8] = [0.5, 0.0, 0.0]
    z = np.zeros((T, 2))
    traj = Trajectory(np.arange(T) * 1e-3, np.zeros((T, n)), v, np.zeros((T, n)), z, z, z, z, clearance,
                      np.zeros((T, n)), np.zeros(T), np.zeros(T, bool), [{} for _ in range(T)])
    m = compute_metrics(traj)
    assert m["collided"] and m["collisions_at_rest"] == 1


def test_contact_onsets_are_the_ticks_a_contact_begins():
    """The ticks where the clearance goes below 0 from ≥ 0 (written out here), a run that starts in
    contact beginning one at tick 0; a contact that lasts counts once, a touch at exactly 0 none."""
    from qpctl.simulation.metrics import contact_onsets

    clearance = np.array([-0.1, -0.1, 0.0, 0.1, -0.01, -0.02, 0.1, 0.0, -1e-9, 0.2])
    assert contact_onsets(clearance).tolist() == [0, 4, 8]
    assert contact_onsets(np.full(5, 0.1)).size == 0


@pytest.mark.parametrize("override,key", [("controller.backup=1", "controller.backup"),
                                          ("controller.backup_margin=-0.01", "controller.backup_margin"),
                                          ("controller.backup_check_distance=nan", "controller.backup_check_distance"),
                                          ('controller.backup_check_distance="far"', "controller.backup_check_distance")])
def test_backup_keys_are_validated(override, key):
    from qpctl import ConfigError, Scenario

    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[override])
    assert exc.value.key == key


def test_backup_key_builds_the_guard_and_the_metrics_count_it():
    """``controller.backup = true`` puts the scenario's controller behind the guard at the run's sim.dt
    with its keys; on the paper's first 60 ms (at rest, far from the obstacles: every proposal verified)
    the torques are bit-identical to the run without it, every tick is checked and none is on the brake."""
    from qpctl import Scenario
    from qpctl.run import simulate

    sets = ["sim.duration=0.06", "controller.kind=\"qp\""]
    plain = simulate(Scenario.load("paper", overrides=sets))
    sc = Scenario.load("paper", overrides=[*sets, "controller.backup=true", "controller.backup_margin=0.01"])
    guard = sc.build_controller()
    assert isinstance(guard, BackupGuard) and guard.margin == 0.01 and guard.dt == sc.data["sim"]["dt"]
    assert np.isinf(guard.check_distance)
    run = simulate(sc)
    assert np.array_equal(run.trajectory.tau, plain.trajectory.tau)
    m = run.metrics
    assert m["backup_checked_ticks"] == m["ticks"] and m["backup_ticks"] == 0 and m["backup_unverified_ticks"] == 0
    assert m["backup_check_us_median"] > 0 and "backup_ticks" not in plain.metrics


def test_backup_guard_verifies_the_state_itself_when_nothing_is_stored():
    """The first tick pushes at once (nothing stored yet): the push's successor has no verified brake,
    so the guard rolls the brakes out from the state itself (at rest, no torque applied before: no rate
    window) and applies the first verified one's torque; with a check distance shorter than the
    clearance the same push is applied unchecked."""
    robot, q, inner, guard = pushed_arm(0.0)
    v, none = np.zeros(3), np.full(3, np.nan)
    out = guard.step(q, v, 0.0)
    assert out.info["backup_checked"] and out.info.get("backup") == guard._gain is not None
    assert np.array_equal(out.tau, brake_torque(robot, robot.model.createData(), q, v, none, guard._gain, DT))
    assert guard.stats["unverified"] == 0 and guard.stats["backup"] == 1
    far = BackupGuard(Pusher(inner, t_push=0.0), dt=DT, check_distance=0.01)  # type: ignore[arg-type]
    out = far.step(q, v, 0.0)
    assert not out.info["backup_checked"] and "backup" not in out.info
    assert np.array_equal(out.tau, Pusher(inner, 0.0).step(q, v, 0.0).tau)


def closing_tip() -> tuple[Any, ...]:
    """The pushed arm (held until t = 1 s) with its tip closing on the sphere at 0.5 rad/s, gravity held:
    (robot, q, q̇, data, the holding torque, the guard, and the Simulator-based rollouts of κ = 4 and
    κ = 25 from the successor of one held step)."""
    robot, q, inner, guard = pushed_arm(1.0)  # the stand-in holds gravity until t = 1 s
    v = np.array([-0.5, 0.0, 0.0])  # the tip closing on the sphere
    data = robot.model.createData()
    hold = pin.computeGeneralizedGravity(robot.model, data, q)
    sim = Simulator(inner, dt=DT, duration=DT)
    sim.reset(q, v)
    sim.apply(hold)
    sim.step(0.0)
    q1, v1 = (x.copy() for x in sim.read())
    soft, firm = (rollout(sim, q1, v1, hold, DT, g, stop_below=0.0) for g in (4.0, 25.0))
    guard.settle = False  # rollouts to rest, as the oracle's: the step counts below are theirs
    return robot, q, v, data, hold, guard, soft, firm


def test_backup_guard_tries_only_as_many_gains_as_told():
    """``tries``: the gains tried from the proposal's successor, the stored one first. With a soft
    stored brake (κ = 4) that the successor's rollout refutes while κ = 25 verifies it (both checked
    here on the Simulator-based rollout), one try falls back to the stored brake and the whole family
    applies the proposal and stores 25."""
    robot, q, v, data, hold, guard, soft, firm = closing_tip()
    assert not soft.viable and firm.viable
    for tries, falls_back in ((1, True), (np.inf, False)):
        guard._gain, guard._tau_prev, guard.tries, guard._on_brake = 4.0, hold.copy(), tries, False
        out = guard.step(q, v, 0.0)
        assert ("backup" in out.info) is falls_back
        if falls_back:
            assert guard._gain == 4.0 and np.array_equal(out.tau, brake_torque(robot, data, q, v, hold, 4.0, DT))
        else:
            assert guard._gain == 25.0 and np.array_equal(out.tau, hold)


def test_backup_guard_tries_fewer_gains_while_it_brakes():
    """``tries_on_brake`` (default 2): while the last tick applied the stored brake, a check tries that
    many gains, the stored one first. From the closing tip, whose successor the stored soft brake (κ = 4)
    does not verify and κ = 25 (the guard's first other gain) does — both on the Simulator-based
    rollout —, the guard applies the proposal and stores 25 when the last tick applied a proposal, and
    while braking with 2 tries or the whole family (inf); with 1 try it keeps braking with κ = 4 after
    one refuted rollout, and does so on the next tick too."""
    robot, q, v, data, hold, guard, soft, firm = closing_tip()
    assert not soft.viable and firm.viable and guard.gains[0] == 25.0
    assert guard.tries_on_brake == 2
    cases = ((False, 1, True), (True, 2, True), (True, np.inf, True), (True, 1, False))
    for on_brake, tries_on_brake, applied in cases:
        guard._gain, guard._tau_prev, guard._on_brake = 4.0, hold.copy(), on_brake
        guard.tries_on_brake = tries_on_brake
        out = guard.step(q, v, 0.0)
        if applied:
            assert "backup" not in out.info and guard._gain == 25.0 and np.array_equal(out.tau, hold)
            assert guard.stats["check_steps"][-1] == soft.steps + firm.steps
            guard._gain, guard.tries_on_brake = 4.0, 1  # the last tick applied the proposal: the whole family
            assert "backup" not in guard.step(q, v, 0.0).info and guard._gain == 25.0
        else:
            assert out.info["backup"] == 4.0 and np.array_equal(out.tau, brake_torque(robot, data, q, v, hold, 4.0, DT))
            assert guard.stats["check_steps"][-1] == soft.steps  # one rollout, refuted
            again = guard.step(q, v, 0.0)  # braking: the next check again tries κ = 4 alone
            assert again.info["backup"] == 4.0 and guard.stats["check_steps"][-1] == soft.steps


@pytest.mark.parametrize("value", ["0", "1.5", "nan"])
def test_backup_tries_on_brake_is_a_whole_number_or_inf(value):
    from qpctl import ConfigError, Scenario

    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[f"controller.backup_tries_on_brake={value}"])
    assert exc.value.key == "controller.backup_tries_on_brake"
    on = ["controller.backup=true"]
    assert Scenario.load("paper", overrides=on).build_controller().tries_on_brake == 2
    assert Scenario.load("paper", overrides=[*on, "controller.backup_tries_on_brake=1"]).build_controller().tries_on_brake == 1
    assert Scenario.load("paper", overrides=[*on, "controller.backup_tries_on_brake=inf"]).build_controller().tries_on_brake == np.inf


def test_backup_guard_spends_at_most_its_check_steps_on_a_proposal():
    """``check_steps``: the rollout steps one check may spend on the proposal's successor, all gains
    together. With the stored soft brake (κ = 4) refuted from the successor after n₄ steps and κ = 25
    at rest after n₂₅ (both counted on the Simulator-based rollout), n₄ + n₂₅ + 1 steps (the rest is
    seen on the step after the last one integrated) apply the proposal and store 25; one step fewer
    falls back to the stored brake and says the steps ran out; so does a limit within the first
    rollout; the default (inf) spends n₄ + n₂₅."""
    robot, q, v, data, hold, guard, soft, firm = closing_tip()
    assert not soft.viable and firm.viable and 0 < soft.steps < firm.steps
    n4, n25 = soft.steps, firm.steps
    for steps, applied in ((np.inf, True), (n4 + n25 + 1, True), (n4 + n25, False), (n4 // 2, False)):
        guard._gain, guard._tau_prev, guard.check_steps, guard._on_brake = 4.0, hold.copy(), steps, False
        out = guard.step(q, v, 0.0)
        spent = guard.stats["check_steps"][-1]
        assert spent <= steps
        if applied:
            assert guard._gain == 25.0 and np.array_equal(out.tau, hold) and "backup_out_of_steps" not in out.info
            assert spent == n4 + n25
        else:
            assert out.info["backup"] == 4.0 and out.info["backup_out_of_steps"]
            assert np.array_equal(out.tau, brake_torque(robot, data, q, v, hold, 4.0, DT))
            assert spent == (n4 + n25 if steps > n4 else steps)
    assert guard.stats["out_of_steps"] == 2 and guard.stats["unverified"] == 0


def test_check_steps_bound_the_states_own_check_too():
    """``check_steps`` bounds the whole check, step 3 included. Nothing stored and a proposal pushing the
    tip into the sphere (1,000 N·m on the first joint): every brake from its successor is refuted, and
    the state's own κ = 25 verifies (step 3) — S steps in all. S + 1 steps give the same verdict in S;
    S − 1 and S // 2 end step 3's rollout: the tick is unverified, says the steps ran out, spends at most
    its steps and keeps the arm on its stop (the family's first brake from this state)."""
    robot, q, v, data, hold, guard, _, _ = closing_tip()
    push = hold - np.array([1000.0, 0.0, 0.0])
    spent = {}
    for steps in (np.inf, None, "S-1", "S//2"):
        budget = {None: spent.get(np.inf, 0) + 1, "S-1": spent.get(np.inf, 0) - 1,
                  "S//2": spent.get(np.inf, 0) // 2}.get(steps, steps)
        guard._reset_backup()
        guard._tau_prev, guard.check_steps = hold.copy(), budget
        info: dict = {}
        out = guard.check(q, v, push, 0.0, info)
        spent[steps] = guard.stats["check_steps"][-1]
        assert spent[steps] <= budget
        if steps in (np.inf, None):
            assert info.get("backup") == 25.0 and "backup_out_of_steps" not in info
            assert spent[steps] == spent[np.inf] > 1000
            assert np.array_equal(out, brake_torque(robot, data, q, v, hold, 25.0, DT))
        else:
            assert info.get("backup_unverified") and info.get("backup_out_of_steps") and "backup" not in info
            assert info["backup_stop"] == guard.gains[0] and guard._gain is None
            assert np.array_equal(out, brake_torque(robot, data, q, v, hold, guard.gains[0], DT))


def test_settled_rollouts_spend_fewer_steps_and_pass_their_budget_on():
    """With ``settle`` (the default) the same check applies the proposal and stores 25 in fewer steps
    than the rollouts to rest (n₄ + n₂₅ on the Simulator-based rollout), and a step budget of exactly
    what it spent still applies it: a settled stop's rest may lie beyond the budget's horizon (the rest
    is bounded within the guard's horizon, not the budget's)."""
    _, q, v, _, hold, guard, soft, firm = closing_tip()
    guard.settle = True
    guard._gain, guard._tau_prev, guard._on_brake = 4.0, hold.copy(), False
    out = guard.step(q, v, 0.0)
    spent = guard.stats["check_steps"][-1]
    assert guard._gain == 25.0 and np.array_equal(out.tau, hold)
    assert spent < soft.steps + firm.steps
    guard._gain, guard._tau_prev, guard.check_steps = 4.0, hold.copy(), spent + 1
    out = guard.step(q, v, 0.0)
    assert guard._gain == 25.0 and "backup_out_of_steps" not in out.info and guard.stats["check_steps"][-1] == spent


@pytest.mark.parametrize("value", ["0", "2.5", "-1", "nan"])
def test_backup_check_steps_is_a_whole_number_or_inf(value):
    from qpctl import ConfigError, Scenario

    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[f"controller.backup_check_steps={value}"])
    assert exc.value.key == "controller.backup_check_steps"
    sc = Scenario.load("paper", overrides=["controller.backup=true", "controller.backup_check_steps=300"])
    assert sc.build_controller().check_steps == 300


@pytest.mark.parametrize("value", ["0", "2.5", "-1", "nan"])
def test_backup_check_evaluations_is_a_whole_number_or_inf(value):
    from qpctl import ConfigError, Scenario

    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[f"controller.backup_check_evaluations={value}"])
    assert exc.value.key == "controller.backup_check_evaluations"
    on = ["controller.backup=true"]
    assert Scenario.load("paper", overrides=on).build_controller().check_evaluations == np.inf
    sc = Scenario.load("paper", overrides=[*on, "controller.backup_check_evaluations=40"])
    assert sc.build_controller().check_evaluations == 40


def test_backup_carry_is_a_scenario_key():
    from qpctl import ConfigError, Scenario

    on = ["controller.backup=true"]
    assert Scenario.load("paper", overrides=on).build_controller().carry is True
    assert Scenario.load("paper", overrides=[*on, "controller.backup_carry=false"]).build_controller().carry is False
    with pytest.raises(ConfigError) as exc:
        Scenario.load("paper", overrides=[*on, 'controller.backup_carry="later"'])
    assert exc.value.key == "controller.backup_carry"
