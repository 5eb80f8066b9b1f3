"""The replay page (qpctl.replay): what `qpctl simulate` writes beside a run, read back two ways.

* The recording inside the page (viser's scene serializer: zstd-compressed msgpack, base64 in the
  HTML) is decoded here and its scene state at each frame compared with the run's own arrays: the
  task-point marker with the recorded x (the controller's), the link colours with the clearance
  the simulator recorded (a compiled kernel; the page measures per link with python-fcl), the
  moving obstacle with its motion law.
* Headless Chromium (Debian's package; .ci/run installs it — no Chromium is a failure, not a skip)
  opens the file from disk, paused at a time between two frames: no console error, no request
  leaving the file, a scene drawn, and the magenta marker on the task point where a pinhole
  projection of the recorded x (computed here from the page's camera) puts it, not where the
  task point was at the start. The same for an obstacle that moves.

Targets: panda_canopy (qp, meshes), the paper arm (capsules only), a scene with a moving obstacle.
Runs are short (0.6–1.2 s), so the whole module takes a few tens of seconds.
"""

from __future__ import annotations

import base64
import io
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from qpctl.cli import main
from qpctl.errors import ReplayError
from qpctl.replay import from_run_dir, write_run_replay
from qpctl.replay.browser import Browser
from qpctl.replay.frames import display_ticks, sample
from qpctl.replay.visuals import CONTACT, NEUTRAL, SAFE, clearance_colour, obstacle_mesh
from qpctl.scenario import Scenario, packaged_scenarios
from qpctl.simulation.trajectory import Trajectory

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

MAX_BYTES = 5_000_000

MOVING = """
name = "moving"
[robot]
kind = "planar3"
radius = 0.05
q0 = [3.14159265358979, 1.5707963267949, 0.0]
[path]
waypoints = [[1.0, -1.5]]
duration = 4.0
[[obstacles]]
name = "drifter"          # below the arm, beyond d_influence, crossing the view at 0.6 m/s with a sway
shape = "sphere"
position = [0.0, -2.5]
radius = 0.1
velocity = [0.6, 0.0, 0.0]
amplitude = [0.0, 0.05, 0.0]
frequency = 0.5
[[obstacles]]
name = "branch"
shape = "sphere"
position = [0.6, -0.7]
radius = 0.08
[controller]
kind = "qp"
v_ref = 1.0
d_influence = 0.3
d_safe = 0.05
[sim]
duration = 1.2
"""

RUNS = {  # name: (simulate arguments, time to show [s])
    "panda": (["panda_canopy", "--controller", "qp", "--set", "sim.duration=0.6"], 0.55),
    "paper": (["paper", "--controller", "hsu", "--set", "sim.duration=1.2"], 1.15),
    "moving": (["MOVING"], 1.15),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("replay")
    (root / "moving.toml").write_text(MOVING)
    out = {}
    for name, (args, _) in RUNS.items():
        args = [str(root / "moving.toml") if a == "MOVING" else a for a in args]
        out[name] = root / name
        assert main(["simulate", *args, "--out", str(out[name]), "--quiet", "--no-figures"]) == 0
    return out


@pytest.fixture(scope="module")
def browser():
    with Browser() as b:  # no Chromium: ReplayError, a failure (.ci/run installs it)
        yield b


# -- reading the page back ------------------------------------------------------------------------
def page_config(html: str) -> dict:
    return json.loads(re.search(r"window\.__QPCTL_REPLAY__=(\{.*?\});</script>", html).group(1))


def recording(html: str) -> dict:
    """viser's recording inside the page: [8-byte size][zstd([8-byte length][msgpack][buffers])]."""
    import msgspec
    import zstandard

    raw = base64.b64decode(re.search(r'window\.__VISER_EMBED_DATA__="([^"]*)"', html).group(1))
    inner = zstandard.ZstdDecompressor().decompress(raw[8:], max_output_size=int.from_bytes(raw[:8], "little"))
    n = int.from_bytes(inner[:8], "little")
    return msgspec.msgpack.decode(inner[8:8 + n])


def state_at(messages: list, name: str, key: str, t: float, field: str | None = None):
    """The last value of ``key`` sent to node ``name`` at or before ``t`` (what the player shows)."""
    value = None
    for when, m in messages:
        if when > t + 1e-9:
            break
        if m.get("name") != name:
            continue
        if field is None and key in m:
            value = m[key]
        elif field is not None and key in m and field in m[key]:
            value = m[key][field]
    return value


def project(point: np.ndarray, camera: dict, canvas: dict) -> np.ndarray:
    """Pixel (u, v) of a world point for a pinhole camera at ``position`` looking at ``look_at`` with
    ``up``, vertical field of view ``fov`` [deg], drawn into the canvas rectangle (three.js's camera)."""
    pos, target, up = (np.asarray(camera[k], float) for k in ("position", "look_at", "up"))
    back = (pos - target) / np.linalg.norm(pos - target)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    d = np.asarray(point, float) - pos
    x, y, z = d @ right, d @ true_up, d @ back
    f = 1.0 / np.tan(np.radians(camera["fov"]) / 2)
    aspect = canvas["width"] / canvas["height"]
    ndc = np.array([f * x / (-z) / aspect, f * y / (-z)])
    return np.array([canvas["x"] + (ndc[0] + 1) / 2 * canvas["width"], canvas["y"] + (1 - ndc[1]) / 2 * canvas["height"]])


def pixels(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), int)


def magenta(img: np.ndarray) -> np.ndarray:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > 150) & (b > 150) & (g < 0.55 * np.minimum(r, b))


def brown(img: np.ndarray) -> np.ndarray:
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (r > g + 12) & (g > b + 6) & (r < 235) & (r > 35)


def near(mask: np.ndarray, uv: np.ndarray, radius: int) -> int:
    u, v = round(float(uv[0])), round(float(uv[1]))
    return int(mask[max(v - radius, 0):v + radius + 1, max(u - radius, 0):u + radius + 1].sum())


def planar_x(traj: Trajectory, k: int) -> np.ndarray:
    x = np.zeros(3)
    x[: traj.x.shape[1]] = traj.x[k]
    return x


# -- the file -------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(RUNS))
def test_simulate_writes_a_self_contained_replay(runs, name):
    page = runs[name] / "replay.html"
    html = page.read_text()
    assert page.stat().st_size <= MAX_BYTES
    assert "http://" not in html and "https://" not in html
    cfg = page_config(html)
    traj = Trajectory.load(runs[name] / "trajectory.npz")
    times, ticks = display_ticks(traj.t)
    assert cfg["frameTimes"] == pytest.approx(times.tolist()) and cfg["frameTicks"] == ticks.tolist()
    rec = recording(html)
    assert rec["durationSeconds"] == pytest.approx(times[-1] + 1 / 30)  # the last frame, held one frame
    # the scenario beside the run reads back as the one that ran, with the law it ran with
    ran = tomllib.loads((runs[name] / "scenario.toml").read_text())
    assert ran["controller"]["kind"] == {"panda": "qp", "paper": "hsu", "moving": "qp"}[name]


def test_panda_is_drawn_with_its_meshes_and_the_paper_arm_with_capsules(runs):
    kinds = {}
    for name in ("panda", "paper"):
        msgs = recording((runs[name] / "replay.html").read_text())["messages"]
        kinds[name] = sorted({m["name"].split("/")[-1] for _, m in msgs
                              if m["type"] == "MeshMessage" and m["name"].startswith("/robot/")})
    assert any("panda_link3" in n for n in kinds["panda"]) and any("panda_hand" in n for n in kinds["panda"])
    assert sum(n.startswith("capsule") or "capsule" in n for n in kinds["panda"]) == 7  # hidden, measured on
    assert kinds["paper"] == ["00_capsule_0_link1", "01_capsule_1_link2", "02_capsule_2_link3"]


@pytest.mark.parametrize("name", list(RUNS))
def test_recording_shows_the_recorded_run_frame_by_frame(runs, name):
    """Scene state read back at each frame: the marker at the recorded x, each link's colour from
    its clearance; the least of the links' clearances (python-fcl) is the simulator's record."""
    html = (runs[name] / "replay.html").read_text()
    msgs = recording(html)["messages"]
    cfg = page_config(html)
    inp = from_run_dir(runs[name])
    traj = inp.trajectory
    robot = inp.robot
    links = {m["name"] for _, m in msgs if m["type"] == "MeshMessage" and "capsule" in m["name"]}
    joints = tuple(sorted({c.joint_id for c in robot.capsules}))
    frames = sample(robot, inp.obstacles, traj.t, traj.q, joints, cutoff=np.inf)
    for k, (t, tick) in enumerate(zip(cfg["frameTimes"], cfg["frameTicks"])):
        marker = state_at(msgs, "/task_point", "position", t)
        np.testing.assert_allclose(marker, planar_x(traj, tick), atol=2e-6)  # float32 on the wire
        least = frames.link_clearance[k].min()
        assert least == pytest.approx(traj.clearance[tick], abs=1e-6)
        for i in range(len(robot.capsules)):
            node = next(n for n in links if f"capsule_{i}_" in n or f"capsule{i}_" in n)
            colour = state_at(msgs, node, "updates", t, "color")
            created = next(m["props"]["color"] for _, m in msgs if m.get("name") == node and "props" in m)
            expect = clearance_colour(float(frames.link_clearance[k, i]), inp.d_safe, inp.d_influence)
            assert tuple(colour if colour is not None else created) == expect, (k, i)


def test_moving_obstacle_moves_as_its_motion_law_says(runs):
    html = (runs["moving"] / "replay.html").read_text()
    msgs, cfg = recording(html)["messages"], page_config(html)
    traj = Trajectory.load(runs["moving"] / "trajectory.npz")
    p0, v, a, f = np.array([0.0, -2.5, 0.0]), np.array([0.6, 0, 0]), np.array([0, 0.05, 0]), 0.5
    for t, tick in zip(cfg["frameTimes"], cfg["frameTicks"]):
        tt = traj.t[tick]
        np.testing.assert_allclose(state_at(msgs, "/obstacles/00_drifter", "position", t),
                                   p0 + v * tt + a * np.sin(2 * np.pi * f * tt), atol=1e-6)
    assert not [m for _, m in msgs if m.get("name") == "/obstacles/01_branch" and m["type"] == "SetPositionMessage"
                and _ > 0]  # the still one is not moved


# -- in a browser ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(RUNS))
def test_chromium_draws_the_robot_at_the_recorded_pose(runs, browser, name):
    page = runs[name] / "replay.html"
    cfg = page_config(page.read_text())
    traj = Trajectory.load(runs[name] / "trajectory.npz")
    times = np.asarray(cfg["frameTimes"])
    k = int(np.searchsorted(times, RUNS[name][1], side="right")) - 1
    at = 0.5 * (times[k] + times[k + 1])  # between two frames: frame k shows
    shot = browser.render(page, at=at, width=1100, height=700, params={"notices": "0"})
    assert shot.errors == [] and shot.requests == []
    assert shot.state["frame"] == k and shot.state["tick"] == cfg["frameTicks"][k]
    img = pixels(shot.png)
    c = shot.state["canvas"]
    inside = np.zeros(img.shape[:2], bool)  # the 3D view (the panel beside it has a magenta legend dot)
    inside[int(c["y"]):int(c["y"] + c["height"]), int(c["x"]):int(c["x"] + c["width"])] = True
    assert len(np.unique(img[inside] // 16, axis=0)) > 40  # not a blank canvas
    mask = magenta(img) & inside
    here = project(planar_x(traj, cfg["frameTicks"][k]), cfg["camera"], c)
    start = project(planar_x(traj, 0), cfg["camera"], c)
    assert np.linalg.norm(here - start) > 24  # the two places are told apart
    vs, us = np.nonzero(mask)
    assert len(us) > 12, "no magenta marker drawn"
    centroid = np.array([us.mean(), vs.mean()])
    assert np.linalg.norm(centroid - here) < 6, (centroid, here)
    assert near(mask, start, 4) == 0
    if name == "moving":  # the drifting obstacle is drawn where it has drifted to, not where it began
        p = lambda tt: np.array([0.6 * tt, -2.5 + 0.05 * np.sin(np.pi * tt), 0.0])
        now, before = project(p(traj.t[cfg["frameTicks"][k]]), cfg["camera"], c), project(p(0.0), cfg["camera"], c)
        assert np.linalg.norm(now - before) > 40
        assert near(brown(img) & inside, now, 4) >= 60 and near(brown(img) & inside, before, 4) == 0


# -- the parts ------------------------------------------------------------------------------------
def test_display_ticks_show_the_last_sample_at_or_before_each_frame():
    t = np.arange(0, 1234) * 1e-3  # 1.233 s at 1 ms
    times, ticks = display_ticks(t, 30.0)
    assert times[0] == 0 and times[-1] == pytest.approx(t[-1]) and np.all(np.diff(times) > 0)
    np.testing.assert_allclose(times[:-1], np.arange(len(times) - 1) / 30.0)
    for tau, i in zip(times, ticks):
        assert i == max(j for j in range(len(t)) if t[j] <= tau + 1e-12)


def test_clearance_colour_scale():
    d_safe, d_inf = 0.03, 0.2
    assert clearance_colour(0.25, d_safe, d_inf) == NEUTRAL and clearance_colour(d_inf, d_safe, d_inf) == NEUTRAL
    assert clearance_colour(0.03, d_safe, d_inf) == SAFE and clearance_colour(0.01, d_safe, d_inf) == SAFE
    assert clearance_colour(-0.001, d_safe, d_inf) == CONTACT
    ramp = [clearance_colour(d, d_safe, d_inf) for d in np.linspace(0.1999, 0.0301, 40)]
    greens = [c[1] for c in ramp]
    assert greens == sorted(greens, reverse=True) and greens[0] > 180 and greens[-1] < 60  # yellow → red
    assert len(set(ramp)) == 8


def test_obstacle_meshes_have_their_shapes_size():
    from qpctl.geometry.obstacles import Obstacle

    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    cases = [(Obstacle("sphere", np.zeros(3), radius=0.1), lambda v: np.linalg.norm(v, axis=1).max(), 0.1),
             (Obstacle("box", np.zeros(3), size=np.array([0.2, 0.4, 0.6])), lambda v: np.ptp(v, axis=0).tolist(),
              [0.2, 0.4, 0.6]),
             (Obstacle("capsule", np.zeros(3), radius=0.05, length=0.4, axis=axis), lambda v: (v @ axis).max(), 0.25),
             (Obstacle("cylinder", np.zeros(3), radius=0.05, length=0.4, axis=axis), lambda v: (v @ axis).max(), 0.2)]
    for obs, measure, expect in cases:
        v = obstacle_mesh(obs).vertices.astype(float)
        assert measure(v) == pytest.approx(expect, abs=2e-3), obs.shape
        if obs.shape in ("capsule", "cylinder"):
            radial = v - np.outer(v @ axis, axis)
            assert np.linalg.norm(radial, axis=1).max() == pytest.approx(0.05, abs=1e-3)


def test_panda_meshes_are_the_urdf_meshes():
    """Each visual mesh as Pinocchio/coal loads it has the area and bounds of the file as trimesh
    (with pycollada) reads it."""
    import trimesh

    from qpctl.replay.visuals import robot_visuals
    from qpctl.robot.model import panda

    parts, drawn = robot_visuals(panda())
    assert drawn == "meshes" and len(parts) == 11
    urdf = Path(panda().urdf).read_text()
    for part in parts[:3]:
        stem = part.name.rsplit("_", 1)[0].replace("panda_", "")
        rel = re.search(rf"meshes/visual/{stem}\.dae", urdf).group(0)
        mesh = trimesh.load(Path(panda().urdf).parents[1] / rel, force="mesh", process=False)
        v, f = part.mesh.vertices.astype(float), part.mesh.faces
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
        assert area == pytest.approx(mesh.area, rel=1e-4), part.name
        np.testing.assert_allclose(v.min(axis=0), mesh.bounds[0], atol=1e-5)
        np.testing.assert_allclose(v.max(axis=0), mesh.bounds[1], atol=1e-5)


@pytest.mark.parametrize("name", packaged_scenarios())
def test_scenario_toml_reads_back_to_the_same_scenario(name):
    scen = Scenario.load(name)
    back = Scenario.from_dict(tomllib.loads(scen.to_toml(controller={"kind": "hsu"})), source="back")
    expect = json.loads(json.dumps(scen.data))
    expect["controller"]["kind"] = "hsu"
    assert json.loads(json.dumps(back.data)) == expect


def test_qp_status_is_recorded_per_tick(runs):
    with np.load(runs["panda"] / "trajectory.npz") as d:
        status, fallback, t = d["qp_status"], d["qp_fallback"], d["t"]
    metrics = json.loads((runs["panda"] / "metrics.json").read_text())
    assert status.shape == fallback.shape == t.shape
    assert int(np.count_nonzero(fallback != "")) == sum(metrics["qp_fallbacks"].values())
    from qpctl.outcome import SolveStatus

    assert set(status.tolist()) <= {s.value for s in SolveStatus}


def test_depth_map_points_are_drawn_by_snapshot(runs, tmp_path):
    """The hook for a depth map: map_points (and map_stamps) in trajectory.npz become point clouds,
    each snapshot replacing the one before at its stamp."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(runs["paper"], run)
    with np.load(run / "trajectory.npz") as d:
        arrays = {k: d[k] for k in d.files}
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3))
    np.savez_compressed(run / "trajectory.npz", **arrays, map_points=pts, map_stamps=np.repeat([0.0, 0.5], 25))
    write_run_replay(str(run))
    msgs = recording((run / "replay.html").read_text())["messages"]
    clouds = [(t, m) for t, m in msgs if m["type"] == "PointCloudMessage"]
    assert [(round(t, 6), m["name"]) for t, m in clouds] == [(0.0, "/map/0000"), (pytest.approx(0.5), "/map/0001")]
    assert any(m["type"] == "RemoveSceneNodeMessage" and m["name"] == "/map/0000" for _, m in msgs)
    np.savez_compressed(run / "trajectory.npz", **arrays, map_points=pts, map_stamps=np.zeros(7))
    with pytest.raises(ReplayError, match="map_stamps"):
        from_run_dir(run)


# -- the command line -----------------------------------------------------------------------------
def test_replay_command_rewrites_the_page_and_refuses_a_folder_without_a_scenario(runs, tmp_path, capsys):
    import shutil

    run = tmp_path / "old"
    shutil.copytree(runs["paper"], run)
    (run / "replay.html").unlink()
    assert main(["replay", str(run)]) == 0
    assert (run / "replay.html").stat().st_size > 100_000
    (run / "scenario.toml").unlink()
    capsys.readouterr()
    assert main(["replay", str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scenario.toml" in err[0] and err[0].startswith("qpctl: error:")
    assert main(["replay", str(tmp_path / "nowhere")]) == 2
    assert main(["replay", str(runs["paper"]), "--at", "1.0"]) == 2
    assert main(["replay", str(runs["paper"]), "--fps", "0"]) == 2


def test_no_replay_skips_the_page(tmp_path):
    out = tmp_path / "run"
    assert main(["simulate", "paper", "--set", "sim.duration=0.05", "--out", str(out), "--quiet", "--no-replay"]) == 0
    assert (out / "scenario.toml").is_file() and not (out / "replay.html").exists()


def test_urdf_meshes_are_cached_until_a_mesh_file_changes(tmp_path, monkeypatch):
    from qpctl.replay import visuals
    from qpctl.robot.model import panda

    monkeypatch.setenv("QPCTL_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(visuals, "_VISUALS", {})
    robot = panda()
    fresh, _ = visuals.robot_visuals(robot)
    [cached_file] = tmp_path.glob("replay-visuals-*.npz")
    monkeypatch.setattr(visuals, "_VISUALS", {})
    again, _ = visuals.robot_visuals(robot)  # from the file
    for a, b in zip(fresh, again, strict=True):
        assert a.name == b.name and a.joint_id == b.joint_id and a.link == b.link
        np.testing.assert_array_equal(a.placement.homogeneous, b.placement.homogeneous)
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
    with np.load(cached_file) as d:
        arrays = {k: d[k] for k in d.files}
    arrays["mtimes"] = arrays["mtimes"] - 1  # as if a mesh file had been replaced since
    np.savez(cached_file, **arrays)
    assert visuals._load(cached_file) is None


def test_a_scene_with_a_box_and_one_without_obstacles(tmp_path):
    """Shapes beyond spheres (a box, drawn at its size) and an empty scene (no clearance colours) both
    give a page."""
    from qpctl.replay import from_result, write_replay
    from qpctl.run import simulate

    base = tomllib.loads(MOVING)
    base["sim"]["duration"] = 0.2
    base["obstacles"] = [{"name": "crate", "shape": "box", "position": [0.0, -2.6, 0.0], "size": [0.3, 0.2, 0.2]}]
    for obstacles in (base["obstacles"], []):
        run = simulate(Scenario.from_dict({**base, "obstacles": obstacles}, source="test"))
        stats = write_replay(from_result(run), tmp_path / "replay.html")
        msgs = recording((tmp_path / "replay.html").read_text())["messages"]
        meshes = [m["name"] for _, m in msgs if m["type"] == "MeshMessage" and m["name"].startswith("/obstacles/")]
        assert meshes == (["/obstacles/00_crate"] if obstacles else []) and stats.frames == 7
        colours = [m for _, m in msgs if m["type"] == "SceneNodeUpdateMessage" and "color" in m.get("updates", {})]
        assert colours == []  # the box is beyond d_influence, and nothing is near in an empty scene
