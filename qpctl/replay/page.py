"""Write ``replay.html``: one self-contained page, viser's recorded scene plus the run's figures.

The 3D scene is recorded with viser's scene serializer (``ViserServer.get_scene_serializer()``, one
``insert_sleep`` per display frame, ``as_html()``): the file holds viser's viewer and the recording,
base64-encoded, and plays it back offline with a play/pause button, a time slider, a speed selector
(0.5× to 8×) and a scene tree (to hide or show any part). Frames follow :mod:`qpctl.replay.frames`.

What the scene holds: the robot (its meshes, or its capsules; :mod:`qpctl.replay.visuals`), each
link coloured by its clearance from neutral at d_influence through yellow to red at d_safe; the
capsules the distances are measured on (hidden: show them in the scene tree); the obstacles, moving
as they moved; the reference path (green), the task point's trace (orange, growing) and a magenta
marker on the task point; the depth map's points where the run has them; a grid on the ground.

Around it the page adds (``overlay.js``, ``overlay.css`` beside this module): a panel with the run's
title, the colour scale, and the figure of :mod:`qpctl.replay.figures` with a cursor at the time
shown (click it to jump there). ``replay.html?t=2.5`` opens paused at 2.5 s; ``window.qpctlReplay``
reports what the page shows (``ready``, ``time``, ``frame``, ``tick``: the recorded sample drawn).
Nothing is fetched from the network: the file has no ``http://`` or ``https://`` in it.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import math
import re
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

import qpctl.replay.visuals as V
from qpctl.replay.figures import explain
from qpctl.replay.frames import DEFAULT_FPS, Frames, sample, task_point_positions
from qpctl.replay.record import ReplayInput

REPLAY_FILE = "replay.html"
_SKY = 2.0  # the hemisphere light's intensity


class Camera(NamedTuple):
    """Where the page's camera starts: ``position`` and ``look_at`` [m] (world), ``up`` (a world
    direction), ``fov`` the vertical field of view [deg]."""

    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov: float = 50.0


@dataclass(frozen=True)
class ReplayStats:
    """What :func:`write_replay` wrote: ``path``, its size [bytes], the frames and the seconds it took."""

    path: Path
    bytes: int
    frames: int
    seconds: float
    robot_drawn_as: str


def _up(robot_gravity: np.ndarray) -> np.ndarray:
    """The world axis most opposed to gravity (+z with none)."""
    g = np.asarray(robot_gravity, float)
    if not np.linalg.norm(g) > 0:
        return np.array([0.0, 0.0, 1.0])
    i = int(np.argmax(np.abs(g)))
    up = np.zeros(3)
    up[i] = -np.sign(g[i])
    return up


def default_camera(points: np.ndarray, up: np.ndarray, planar: bool) -> Camera:
    """A camera that frames ``points`` [m]: straight onto the plane of a planar arm (up: against
    gravity), else from the front-right and above."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.2)
    fov = 50.0
    dist = 1.35 * radius / math.tan(math.radians(fov) / 2)  # a margin for a view narrower than tall
    if planar:
        direction = np.array([0.0, 0.0, 1.0])
    else:
        side = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
        ahead = np.cross(side, up)
        direction = 0.85 * ahead - 0.75 * side + 0.45 * up
        direction /= np.linalg.norm(direction)
    pos = centre + dist * direction
    return Camera(tuple(pos.tolist()), tuple(centre.tolist()), tuple(up.tolist()), fov)  # type: ignore[arg-type]


def _quiet_server() -> Any:
    import viser

    with contextlib.redirect_stdout(io.StringIO()):  # viser prints its address on start
        return viser.ViserServer(host="127.0.0.1", port=0, verbose=False)


def _wxyz(R: np.ndarray) -> np.ndarray:
    return pin.Quaternion(np.asarray(R, float)).coeffs()[[3, 0, 1, 2]]


def _record(src: ReplayInput, frames: Frames, parts: list[V.LinkVisual], drawn_as: str, trace: np.ndarray,
            camera: Camera, planar: bool) -> str:
    """The viser recording of the scene (module docstring) as viser's standalone HTML."""
    server = _quiet_server()
    try:
        return _scene(server, src, frames, parts, drawn_as, trace, camera, planar)
    finally:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()


def _scene(server: Any, src: ReplayInput, frames: Frames, parts: list[V.LinkVisual], drawn_as: str,
           trace: np.ndarray, camera: Camera, planar: bool) -> str:
    robot, traj = src.robot, src.trajectory
    with server.atomic():  # no live client: queue every message without waking the server's loop
        scene = server.scene
        ser = server.get_scene_serializer()
        scene.set_up_direction(tuple(camera.up))  # type: ignore[arg-type]
        cam = server.initial_camera
        cam.position, cam.look_at, cam.up, cam.fov = camera.position, camera.look_at, camera.up, math.radians(camera.fov)
        # lights without an environment map or shadows: both render progressively (PMREM, shadow
        # accumulation), which takes a software renderer (a headless test, a laptop without GPU) a while
        scene.configure_environment_map(None)
        scene.configure_default_lights(cast_shadow=False)
        scene.add_light_hemisphere("/lights/sky", sky_color=(255, 255, 255), ground_color=(140, 128, 118),
                                   intensity=_SKY, position=tuple(np.asarray(camera.up, float)))
        extent = float(np.ptp(np.vstack([trace, frames.poses[:, :, :3].reshape(-1, 3)]), axis=0).max()) + 0.5
        grid: dict[str, Any] = {"width": 2 * extent, "height": 2 * extent, "cell_size": 0.1, "section_size": 0.5,
                                "cell_color": (225, 225, 225), "section_color": (190, 190, 190)}
        if planar:  # behind the arm, in its plane's normal
            depth = -max((c.radius for c in robot.capsules), default=0.05) - 0.02
            scene.add_grid("/grid", plane="xy", position=(0.0, 0.0, depth), **grid)  # type: ignore[arg-type]
        else:
            scene.add_grid("/grid", plane="xy", **grid)  # type: ignore[arg-type]
        # obstacles
        obstacle_nodes = []
        for j, obs in enumerate(src.obstacles):
            mesh = V.obstacle_mesh(obs)
            colour, opacity = V.obstacle_colour(obs)
            obstacle_nodes.append(scene.add_mesh_simple(
                f"/obstacles/{j:02d}_{obs.name or 'obstacle'}", mesh.vertices, mesh.faces, color=colour,
                opacity=None if opacity >= 1 else opacity, position=tuple(frames.obstacle_positions[0, j])))
        moving = [j for j, o in enumerate(src.obstacles) if o.moving]
        # the reference path and the depth map
        ref = _reference_points(robot, traj, trace)
        if len(ref) > 1:
            scene.add_line_segments("/reference", np.stack([ref[:-1], ref[1:]], axis=1).astype(np.float32),
                                    V.REFERENCE, thickness=2.5, thickness_units="screen")
        snapshots = _map_snapshots(src)
        # the robot: one frame per moving joint, its meshes (and hidden capsules) inside
        joint_nodes = {j: scene.add_frame(f"/robot/joint{j}", show_axes=False) for j in frames.joints}
        meshes: dict[int, list[Any]] = {}
        for n, part in enumerate(parts):
            parent = f"/robot/joint{part.joint_id}" if part.joint_id in joint_nodes else "/robot/base"
            handle = scene.add_mesh_simple(f"{parent}/{n:02d}_{part.name}", part.mesh.vertices, part.mesh.faces,
                                           color=V.NEUTRAL, position=tuple(part.placement.translation),
                                           wxyz=tuple(_wxyz(part.placement.rotation)))
            meshes.setdefault(part.link, []).append(handle)
        if drawn_as == "meshes":  # the capsules the distances are measured on, hidden
            for i, c in enumerate(robot.capsules):
                cap = V.capsule_mesh(c.p0, c.p1, c.radius)
                meshes.setdefault(i, []).append(scene.add_mesh_simple(
                    f"/robot/joint{c.joint_id}/capsule{i}_{c.name}", cap.vertices, cap.faces, color=V.NEUTRAL,
                    opacity=0.45, visible=False))
        reach = float(np.linalg.norm(np.subtract(camera.position, camera.look_at)))
        last = [c.radius for c in robot.capsules if c.joint_id == robot.model.frames[robot.ee_frame_id].parentJoint]
        outside = 1.3 * max(last) if drawn_as == "capsules" and last else 0.0  # not inside the drawn capsule
        marker = scene.add_icosphere("/task_point", radius=max(0.01 * reach, outside, 0.005), color=V.MARKER, subdivisions=2,
                                     position=tuple(frames.task_point[0]))
        # the frames
        shown: dict[int, V.Rgb] = {}
        elapsed = 0.0
        map_index = -1
        for k in range(len(frames.times)):
            if k:
                ser.insert_sleep(float(frames.times[k]) - elapsed)
                elapsed = float(frames.times[k])
            for n, j in enumerate(frames.joints):
                joint_nodes[j].position = frames.poses[k, n, :3]
                joint_nodes[j].wxyz = frames.poses[k, n, 3:]
            for j in moving:
                obstacle_nodes[j].position = frames.obstacle_positions[k, j]
            marker.position = frames.task_point[k]
            for link, handles in meshes.items():
                if link < 0:
                    continue
                colour = V.clearance_colour(float(frames.link_clearance[k, link]), src.d_safe, src.d_influence)
                if shown.get(link) != colour:
                    for h in handles:
                        h.color = colour
                    shown[link] = colour
            a, b = (int(frames.ticks[k - 1]) if k else 0), int(frames.ticks[k])
            if b > a:
                seg = trace[a:b + 1]
                scene.add_line_segments(f"/trace/{k:05d}", np.stack([seg[:-1], seg[1:]], axis=1).astype(np.float32),
                                        V.TRACE, thickness=4.5, thickness_units="screen")
            map_index = _show_map(scene, snapshots, float(frames.times[k]), map_index)
        if len(frames.times) > 1:  # the last frame is shown for one frame's time before the replay loops
            ser.insert_sleep(float(frames.times[-1] - frames.times[-2]))
    return str(ser.as_html())


def _reference_points(robot: Any, traj: Any, trace: np.ndarray) -> np.ndarray:
    """(T, 3) the reference path in the world: x_ref on the task's axes, the task point's own
    coordinate on the others (the path does not constrain them)."""
    ref = trace.copy()
    axes = list(robot.task_axes)
    x_ref = np.asarray(traj.x_ref, float)
    ref[:, axes] = x_ref[:, : len(axes)]
    return ref


def _map_snapshots(src: ReplayInput) -> list[tuple[float, np.ndarray]]:
    """(stamp [s], points) of each depth-map snapshot; one at t = 0 without stamps."""
    if src.map_points is None or not len(src.map_points):
        return []
    if src.map_stamps is None:
        return [(0.0, src.map_points)]
    stamps = np.asarray(src.map_stamps, float)
    return [(float(s), src.map_points[stamps == s]) for s in np.unique(stamps)]


def _show_map(scene: Any, snapshots: list[tuple[float, np.ndarray]], t: float, current: int) -> int:
    """Show the latest snapshot stamped at or before ``t`` (hiding the one before); its index."""
    latest = current
    while latest + 1 < len(snapshots) and snapshots[latest + 1][0] <= t + 1e-9:
        latest += 1
    if latest != current:
        if current >= 0:
            scene.remove_by_name(f"/map/{current:04d}")
        scene.add_point_cloud(f"/map/{latest:04d}", snapshots[latest][1].astype(np.float32), (90, 110, 200),
                              point_size=0.01, point_shape="circle")
    return latest


_FAVICON = re.compile(r'(<link\s+rel="icon"\s+href=")data:image/svg\+xml,([^"]*)(")')


def _offline(html: str) -> str:
    """viser's page without the one ``http://`` it carries: its icon's SVG namespace, re-encoded in
    base64 (a namespace, not a resource; but a page that names no URL at all is simpler to check)."""
    from urllib.parse import unquote

    def b64(m: re.Match[str]) -> str:
        svg = unquote(m.group(2)).encode()
        return m.group(1) + "data:image/svg+xml;base64," + base64.b64encode(svg).decode() + m.group(3)

    return _FAVICON.sub(b64, html, count=1)


def _asset(name: str) -> str:
    return (resources.files("qpctl.replay") / name).read_text()


def _inject(html: str, config: dict[str, Any]) -> str:
    """The page's own panel and controls (``overlay.css``, ``overlay.js``) and its data, before ``</head>``."""
    data = json.dumps(config, separators=(",", ":")).replace("</", "<\\/")
    block = (f"<style>{_asset('overlay.css')}</style>"
             f"<script>window.__QPCTL_REPLAY__={data};</script>"
             f"<script>{_asset('overlay.js')}</script>")
    at = html.index("</head>")
    title = re.sub(r"<title>.*?</title>", f"<title>{_escape(config['title'])} — qpctl replay</title>", html[:at], count=1)
    return title + block + html[at:]


def _hex(rgb: V.Rgb) -> str:
    return "#" + "".join(f"{c:02x}" for c in rgb)


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def replay_html(src: ReplayInput, *, fps: float = DEFAULT_FPS, camera: Camera | None = None) -> tuple[str, Frames, str]:
    """(the page, its frames, how the robot is drawn: "meshes" or "capsules")."""
    robot, traj = src.robot, src.trajectory
    parts, drawn_as = V.robot_visuals(robot)
    joints = tuple(sorted({p.joint_id for p in parts if p.joint_id > 0} | {c.joint_id for c in robot.capsules}))
    frames = sample(robot, src.obstacles, traj.t, traj.q, joints, fps=fps, cutoff=src.d_influence)
    trace = task_point_positions(robot, traj.q)
    planar = len(robot.task_axes) == 2 and bool(np.allclose(trace[:, 2], trace[0, 2]))
    up = _up(robot.model.gravity.linear)
    if camera is None:
        pts = [trace, frames.poses[:, :, :3].reshape(-1, 3)]
        arm = np.vstack(pts)
        centre, size = 0.5 * (arm.min(axis=0) + arm.max(axis=0)), float(np.ptp(arm, axis=0).max())
        # the obstacles near the arm, wherever they move during the run (a far-away one is left out of view)
        near = [frames.obstacle_positions[:, j] for j, o in enumerate(src.obstacles)
                if np.linalg.norm(o.position - centre) < size + o.bounding_radius()]
        camera = default_camera(np.vstack(pts + near), up, planar)
    html = _offline(_record(src, frames, parts, drawn_as, trace, camera, planar))
    fig = explain(traj, d_safe=src.d_safe, d_influence=src.d_influence, tau_max=src.tau_max)
    config = {
        "title": src.title,
        "duration": float(frames.times[-1]) if len(frames.times) else 0.0,
        "frameTimes": [float(x) for x in frames.times],
        "frameTicks": [int(i) for i in frames.ticks],
        "fps": fps,
        "dSafe": src.d_safe, "dInfluence": src.d_influence,
        "scale": [[d, _hex(c)] for d, c in V.scale_stops(src.d_safe, src.d_influence)],
        "colours": {k: _hex(getattr(V, k.upper())) for k in ("neutral", "contact", "marker", "trace", "reference",
                                                             "rigid", "soft")},
        "robot": f"{robot.name} ({drawn_as})",
        "camera": camera._asdict(),
        "figure": {"png": base64.b64encode(fig.png).decode(), "width": fig.width, "height": fig.height,
                   "t0": fig.t0, "t1": fig.t1, "left": fig.left, "right": fig.right, "top": fig.top,
                   "bottom": fig.bottom},
    }
    return _inject(html, config), frames, drawn_as


def write_replay(src: ReplayInput, path: str | Path, *, fps: float = DEFAULT_FPS,
                 camera: Camera | None = None) -> ReplayStats:
    """Write the replay page of ``src`` to ``path`` (module docstring); what it wrote."""
    t0 = time.perf_counter()
    html, frames, drawn_as = replay_html(src, fps=fps, camera=camera)
    path = Path(path)
    path.write_text(html, encoding="utf-8")
    return ReplayStats(path, path.stat().st_size, len(frames.times), time.perf_counter() - t0, drawn_as)
