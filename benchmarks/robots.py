"""The serial arms of example-robot-data with their own collision model: fitted capsules, SRDF pairs, a QP reach.

    python -m benchmarks.robots [--out results/robots]        (make robots)

For each arm: ``qpctl fit-capsules`` on its URDF (capsules file in OUT), the SRDF found beside the
URDF (or none), then the QP on a reach among obstacles built from the arm's own size: the task point
moves in 2 s along a straight line between two seeded random configurations' task points (both
held against gravity within 0.8 × the torque limits, with the arm's capsules clear of each other
and of the floor z = 0, the task point above it),
holds 0.5 s, past a sphere beside the line's middle (away from the base) and a capsule "branch"
across the line below it — each placed so that the task point's path stays clear of it while the
arm passes within the influence distance. Writes ``robots.md`` (the table of docs/robots.md) and ``robots.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from qpctl import Scenario
from qpctl.errors import ConfigError
from qpctl.geometry.self_collision import fcl_self_distances, self_collision_pairs
from qpctl.robot.capsules import fit_robot, write_capsules
from qpctl.run import simulate
from qpctl.scenario import arm_reach

# (label, file below example-robot-data's robots/, task frame, robot.srdf); not ur3.urdf: an empty
# <robot> (xacro's output without its macros), no link to run
ARMS: list[tuple[str, str, str, str]] = [
    ("Panda", "panda_description/urdf/panda.urdf", "panda_hand_tcp", ""),
    ("UR3", "ur_description/urdf/ur3_robot.urdf", "tool0", ""),
    ("UR3 joint-limited", "ur_description/urdf/ur3_joint_limited_robot.urdf", "tool0", ""),
    ("UR3 + gripper", "ur_description/urdf/ur3_gripper.urdf", "tool0", ""),
    ("UR5", "ur_description/urdf/ur5_robot.urdf", "tool0", ""),
    ("UR5 + gripper", "ur_description/urdf/ur5_gripper.urdf", "tool0", ""),
    ("UR5 joint-limited", "ur_description/urdf/ur5_joint_limited_robot.urdf", "tool0", ""),
    ("UR10", "ur_description/urdf/ur10_robot.urdf", "tool0", ""),
    ("UR10 joint-limited", "ur_description/urdf/ur10_joint_limited_robot.urdf", "tool0", ""),
    ("xArm7", "xarm_description/urdf/xarm7.urdf", "link_eef", ""),
    ("Z1", "z1_description/urdf/z1.urdf", "gripperStator", ""),
    ("SO-100", "so_arm_description/urdf/so100.urdf", "jaw", ""),
    ("SO-101", "so_arm_description/urdf/so101.urdf", "gripper_frame_link", ""),
    ("Talos left arm", "talos_data/robots/talos_left_arm.urdf", "arm_left_7_link", ""),
    ("Kinova Gen2 (j2s6s200)", "kinova_description/robots/kinova.urdf", "j2s6s200_end_effector", ""),
]
D_SAFE = 0.02  # [m]
HOLD = 0.8  # a drawn configuration's gravity torque stays within this share of each joint's torque limit


def _clear(robot: Any, q: np.ndarray, pairs: Any, data: Any) -> bool:
    """The arm holds q against gravity within HOLD × its torque limits (Talos's arm, 22.3 N·m at its
    shoulder, cannot hold every pose its joint limits allow), the capsules of ``pairs`` apart by d_safe,
    the links past the first joint above the floor, the task point too."""
    if np.any(np.abs(pin.computeGeneralizedGravity(robot.model, data, q)) > HOLD * robot.tau_max):
        return False
    pin.framesForwardKinematics(robot.model, data, q)
    if data.oMf[robot.ee_frame_id].translation[2] < 0.05:
        return False
    for c in robot.capsules:  # the links past the first joint above the floor (the base stands on it)
        if robot.model.parents[c.joint_id] > 0 and \
                min(data.oMi[c.joint_id].act(c.p0)[2], data.oMi[c.joint_id].act(c.p1)[2]) < c.radius:
            return False
    return not pairs or bool(np.min(fcl_self_distances(robot, q, pairs)) > D_SAFE)


def reach_scene(robot: Any, seed: int = 0) -> dict[str, Any]:
    """q0, the waypoint and the obstacles of the reach (module docstring), as scenario tables."""
    rng = np.random.default_rng(seed)
    centre, reach = arm_reach(robot) or (np.zeros(3), 1.0)
    lo = np.where(np.isfinite(robot.q_min), robot.q_min, -np.pi)
    hi = np.where(np.isfinite(robot.q_max), robot.q_max, np.pi)
    pairs = self_collision_pairs(robot, D_SAFE).pairs
    data = robot.model.createData()
    ee_radius = max((c.radius for c in robot.capsules if c.joint_id == robot.model.frames[robot.ee_frame_id].parentJoint),
                    default=0.05)

    def draw(near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        for _ in range(20000):
            q = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo)) if near is None else \
                np.clip(near + rng.uniform(-0.8, 0.8, len(near)), lo, hi)
            qc = robot.configuration(q)  # angles (one per degree of freedom) → Pinocchio's configuration
            if _clear(robot, qc, pairs, data):
                pin.framesForwardKinematics(robot.model, data, qc)
                return q, data.oMf[robot.ee_frame_id].translation.copy()
        raise RuntimeError(f"no clear configuration of {robot.name} in 20000 draws")

    q0, x0 = draw()
    for _ in range(500):
        _, x1 = draw(q0)
        if 0.25 * reach < np.linalg.norm(x1 - x0) < 0.7 * reach and x1[2] > 0.15 * reach:
            break
    mid, along = 0.5 * (x0 + x1), (x1 - x0) / np.linalg.norm(x1 - x0)
    size = 0.04 * reach
    gap = ee_radius + D_SAFE + 0.03 * reach  # the task point's path stays this far from each obstacle's surface
    across = np.cross(along, [0.0, 0.0, 1.0])
    across = across / np.linalg.norm(across) if np.linalg.norm(across) > 1e-6 else np.array([1.0, 0.0, 0.0])
    side = across if float(across @ (mid - centre)) > 0 else -across  # beside the line, away from the base
    beside = mid + (size + gap) * side
    below = mid - np.array([0.0, 0.0, 0.5 * size + 2 * gap])
    obstacles = [
        {"name": "leaf", "shape": "sphere", "position": beside.tolist(), "radius": size},
        {"name": "branch", "shape": "capsule", "position": below.tolist(), "axis": across.tolist(),
         "length": 0.25 * reach, "radius": 0.5 * size},
    ]
    return {"q0": q0.tolist(), "waypoint": x1.tolist(), "obstacles": obstacles, "reach": reach,
            "centre": centre.tolist()}


def run_arm(label: str, rel: str, ee: str, srdf: str, out: Path) -> dict[str, Any]:
    row: dict[str, Any] = {"robot": label, "urdf": rel}
    uri = f"package://example-robot-data/robots/{rel}"
    start = time.perf_counter()
    try:
        _, fits = fit_robot(uri)
    except ConfigError as exc:
        return {**row, "error": str(exc)}
    caps = out / f"{Path(rel).stem}_capsules.toml"
    write_capsules(fits, caps, robot=Path(rel).stem, source=uri, command=f"qpctl fit-capsules {uri}")
    row.update(fit_s=time.perf_counter() - start, capsules=sum(len(f.capsules) for f in fits), links=len(fits),
               worst_ratio=max(f.ratio for f in fits), worst_link=max(fits, key=lambda f: f.ratio).link,
               outside_mm=max(0.0, max(f.max_outside for f in fits)) * 1e3)
    raw: dict[str, Any] = {
        "name": f"reach-{Path(rel).stem}",
        "robot": {"kind": "urdf", "urdf": uri, "ee_frame": ee, "capsules": str(caps), "srdf": srdf},
        "path": {"waypoints": [[0.0, 0.0, 0.0]], "durations": [2.0]},
        "controller": {"kind": "qp", "v_ref": 0.3, "d_influence": 0.15, "d_safe": D_SAFE},
        "sim": {"dt": 1e-3, "duration": 2.5},
    }
    try:
        robot = Scenario.from_dict(raw, overrides=["sim.duration=0.01"]).build_robot()
    except ConfigError as exc:
        return {**row, "error": str(exc)}
    for seed in range(50):  # the first seeded scene whose obstacles clear the arm at the start
        try:
            scene = reach_scene(robot, seed)
        except RuntimeError as exc:
            return {**row, "error": str(exc)}
        raw["robot"]["q0"] = scene["q0"]
        raw["path"]["waypoints"] = [scene["waypoint"]]
        raw["obstacles"] = scene["obstacles"]
        try:
            scenario = Scenario.from_dict(raw, source=label)
            break
        except ConfigError as exc:
            if not (exc.key or "").startswith("obstacles"):
                raise
    row["seed"] = seed
    robot = scenario.build_robot()
    sel = self_collision_pairs(robot, D_SAFE)
    result = simulate(scenario, progress=False)
    m = result.metrics
    row.update(nv=robot.nv, srdf=robot.srdf.name if robot.srdf else "none", self_pairs=len(sel.pairs),
               all_pairs=len(sel.pairs) + len(sel.excluded), reach=scene["reach"],
               collided=bool(m["collided"]), min_clearance=m["min_clearance"],
               min_self_clearance=m.get("min_self_clearance"), max_tracking_error=m["max_tracking_error"],
               final_tracking_error=m["final_tracking_error"], tick_us_median=m["tick_us_median"],
               statuses=m.get("qp_status_counts"))
    return row


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| robot | joints | capsules (links) | worst capsule / hull | SRDF | self pairs kept | collided | "
            "min clearance [m] | min self clearance [m] | max / final tracking error [m] | tick median [µs] |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['robot']} | — | {r.get('capsules', '—')} ({r.get('links', '—')}) | "
                         f"{r['worst_ratio']:.2f} ({r['worst_link']}) | — | — | not run: {r['error']} | | | | |"
                         if "worst_ratio" in r else f"| {r['robot']} | — | — | — | — | — | not run: {r['error']} | | | | |")
            continue
        selfc = "—" if r["min_self_clearance"] is None else f"{r['min_self_clearance']:.3f}"
        lines.append(f"| {r['robot']} | {r['nv']} | {r['capsules']} ({r['links']}) | {r['worst_ratio']:.2f} "
                     f"({r['worst_link']}) | {r['srdf']} | {r['self_pairs']} of {r['all_pairs']} | "
                     f"{'**yes**' if r['collided'] else 'no'} | {r['min_clearance']:.3f} | {selfc} | "
                     f"{r['max_tracking_error']:.1e} / {r['final_tracking_error']:.1e} | {r['tick_us_median']:.0f} |")
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--out", default="results/robots")
    ap.add_argument("--only", help="run only the robots whose label contains this text")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for label, rel, ee, srdf in ARMS:
        if args.only and args.only.lower() not in label.lower():
            continue
        row = run_arm(label, rel, ee, srdf, out)
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in row.items()}, flush=True)
        rows.append(row)
    (out / "robots.json").write_text(json.dumps(rows, indent=1, default=str))
    (out / "robots.md").write_text(table(rows))
    print(f"-> {out / 'robots.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
