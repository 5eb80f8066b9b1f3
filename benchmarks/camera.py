"""The simulated depth camera's cost and agreement: qpctl's ray-casting kernel and MuJoCo's mj_multiRay.

    python -m benchmarks.camera [--out results/camera] [--rounds 10]      (make camera)

On the packaged ``panda_canopy_depth`` (300 leaves, 12 branches, trunk, 3 wires, 3 fruits, the Panda's
7 link capsules: 330 shapes) it renders 640×480 frames from the scenario's world camera and from a
wrist camera (on ``panda_hand``, looking along the gripper), at the arm's start and at each
reachable fruit's configuration. Per round the casters run in rotating order on the same states
(one process, interleaved, as the machine is shared): the kernel's rendering, mj_multiRay's in a
MuJoCo model of the same scene, and a full ``capture`` (the kernel's rendering + the noise model,
encoding, labels, truth). Reports medians and 90th percentiles [ms], the ratio MuJoCo / kernel,
the pixels where the two casters see the same shape, and the load average. Writes ``camera.md``
(the table of docs/camera.md), ``camera.json`` and ``camera_frame.png`` (a frame of the world
camera: depth, labels, what each pixel saw, the noise).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np

from qpctl import Scenario
from qpctl.adapters.mujoco import scene_caster
from qpctl.simulation.camera import CameraConfig, DepthCamera

SCENARIO = "panda_canopy_depth"
#: The wrist camera: on panda_hand, 6 cm off its axis, looking along the gripper (the hand's z), a D405's 7 cm near limit.
WRIST = {"mount": "panda_hand", "position": [0.0, 0.06, 0.0], "look_at": None, "quaternion": [0.0, 0.0, 0.0, 1.0],
         "range_min": 0.07}


def states(scen: Scenario) -> list[np.ndarray]:
    robot = scen.build_robot()
    canopy = scen.canopy()
    assert canopy is not None
    return [scen.q0(robot)] + [f.q for f in canopy.fruits if f.reachable and f.q is not None]


def measure(keys: dict, rounds: int) -> dict:
    """Time the casters on the scenario's camera with ``keys`` changed."""
    scen = Scenario.load(SCENARIO)
    robot = scen.build_robot()
    cfg = dataclasses.replace(scen.camera_config(), **keys)
    kernel, mj = (DepthCamera(cfg, robot, scen.build_obstacles(), scenery=scen.scenery()) for _ in range(2))
    mj.caster = scene_caster(mj)
    qs = states(scen)
    for q in qs[:1]:  # compile / load the kernels, build MuJoCo's data
        kernel.capture(q, 0.0)
        mj.render(q, 0.0)
    timed = {"kernel": [], "mujoco": [], "capture": []}
    agree, returns = [], []
    jobs = {"kernel": lambda q: kernel.render(q, 0.0), "mujoco": lambda q: mj.render(q, 0.0),
            "capture": lambda q: kernel.capture(q, 0.0)}
    names = list(jobs)
    for r in range(rounds):
        order = names[r % 3:] + names[:r % 3]
        for q in qs:
            for name in order:
                start = time.perf_counter()
                jobs[name](q)
                timed[name].append(1e3 * (time.perf_counter() - start))
    for q in qs:
        a, b = kernel.render(q, 0.0)[1], mj.render(q, 0.0)[1]
        agree.append(float((a.hit == b.hit).mean()))
        returns.append(float((kernel.capture(q, 0.0).depth > 0).mean()))
    return {"median_ms": {k: float(np.median(v)) for k, v in timed.items()},
            "p90_ms": {k: float(np.percentile(v, 90)) for k, v in timed.items()},
            "ratio": float(np.median(timed["mujoco"]) / np.median(timed["kernel"])),
            "same_shape": min(agree), "returns": float(np.mean(returns)), "states": len(qs),
            "shapes": len(kernel.visible)}


def figure(out: Path) -> None:
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    from qpctl.perception import RIGID, SOFT

    scen = Scenario.load(SCENARIO)
    robot = scen.build_robot()
    camera = DepthCamera.from_scenario(scen, robot)
    q = states(scen)[1]  # the arm at the first fruit
    frame = camera.capture(q, 0.0)
    truth = frame.truth
    z = frame.metres()
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(2, 2, figsize=(13, 9.2), layout="constrained")

    def legend(ax, entries):
        ax.legend(handles=[Patch(color=c, label=n) for n, c in entries], loc="lower right", fontsize=8)

    im = axes[0, 0].imshow(np.where(z > 0, z, np.nan), cmap="viridis")
    fig.colorbar(im, ax=axes[0, 0], label="depth [m]", shrink=0.8)
    axes[0, 0].set_title("depth (noise on; white: no return)")
    lab = np.zeros(z.shape)
    lab[frame.labels == RIGID], lab[frame.labels == SOFT] = 1, 2
    lab[(frame.labels == 0) & (z > 0)] = 3
    axes[0, 1].imshow(lab, cmap=ListedColormap(["white", "saddlebrown", "yellowgreen", "0.6"]), vmin=0, vmax=3)
    axes[0, 1].set_title("labels, as from a segmenter")
    legend(axes[0, 1], [("rigid", "saddlebrown"), ("soft", "yellowgreen"), ("unlabeled", "0.6")])
    kind = np.zeros(z.shape)
    hit = truth.hit
    names = truth.names
    kind[hit >= 0] = 1
    for prefix, value in (("branch", 2), ("trunk", 3), ("wire", 3)):
        ids = [i for i, n in enumerate(names) if n.startswith(prefix)]
        kind[np.isin(hit, ids)] = value
    kind[truth.robot], kind[truth.scenery] = 4, 5
    axes[1, 0].imshow(kind, cmap=ListedColormap(["white", "yellowgreen", "saddlebrown", "black", "tab:blue",
                                                  "red"]), vmin=0, vmax=5)
    axes[1, 0].set_title("truth: the shape each pixel saw")
    legend(axes[1, 0], [("leaf", "yellowgreen"), ("branch", "saddlebrown"), ("trunk, wire", "black"),
                        ("robot (the self-filter's)", "tab:blue"), ("fruit", "red")])
    err = np.where(z > 0, z - np.nan_to_num(truth.depth), np.nan)
    im = axes[1, 1].imshow(1e3 * err, cmap="coolwarm", vmin=-10, vmax=10)
    fig.colorbar(im, ax=axes[1, 1], label="measured − true depth [mm]", shrink=0.8)
    fv, fu = np.nonzero(truth.flying)
    axes[1, 1].scatter(fu, fv, s=1, c="black")
    axes[1, 1].set_title(f"noise; flying pixels black ({truth.flying.sum()}), "
                         f"{truth.dropped.sum()} returns dropped")
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{SCENARIO}: the world camera's 640×480 frame, the arm at the first fruit")
    fig.savefig(out / "camera_frame.png", dpi=80)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="results/camera")
    parser.add_argument("--rounds", type=int, default=10)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()[0]
    rows = {"world camera": measure({}, args.rounds), "wrist camera": measure(WRIST, args.rounds)}
    load_after = os.getloadavg()[0]
    figure(out)
    (out / "camera.json").write_text(json.dumps({"rows": rows, "load": [load_before, load_after]}, indent=2) + "\n")
    cfg = CameraConfig()
    lines = [(f"`python -m benchmarks.camera` on {SCENARIO}, {cfg.width}×{cfg.height}, "
              f"{rows['world camera']['shapes']} shapes, {args.rounds} rounds × the arm's states, interleaved; "
              f"load average {load_before:.1f} → {load_after:.1f} on this machine's {os.cpu_count()} cores."), "",
             ("| camera | kernel render [ms] | mj_multiRay [ms] | MuJoCo / kernel | capture (kernel + noise) [ms] "
              "| pixels, same shape | pixels with a return |"),
             "|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        m, p = r["median_ms"], r["p90_ms"]
        lines.append(f"| {name} | {m['kernel']:.1f} (p90 {p['kernel']:.1f}) | {m['mujoco']:.1f} (p90 {p['mujoco']:.1f}) "
                     f"| {r['ratio']:.1f}× | {m['capture']:.1f} (p90 {p['capture']:.1f}) | {100 * r['same_shape']:.2f} % "
                     f"| {100 * r['returns']:.0f} % |")
    (out / "camera.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
