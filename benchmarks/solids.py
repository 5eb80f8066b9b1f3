"""Boxes and cylinders in the tick: the Panda canopy with capsules only against the same canopy with a
box and a cylinder among its obstacles (issue 23, item 4; docs/performance.md, "Boxes and cylinders").

Three variants of the packaged ``panda_canopy`` scenario, timed on the same states (those of the
capsule scene's closed-loop QP run), interleaved in blocks of 25 ticks (:func:`qpctl.bench.timing.
time_on_states`):

* ``capsules`` — the scenario as packaged (three branch capsules, leaves as spheres);
* ``box+cylinder`` — ``branch_low`` becomes a box of the capsule's extent and ``trunk`` a cylinder
  of its radius and length, both in closed form in the kernel (:mod:`qpctl.kernels.solids`);
* ``box+cylinder (python-fcl)`` — the same two shapes under other names, so that the kernels do not
  know them and python-fcl computes their pairs between two kernel calls (what the tick did before).

Run: ``.venv/bin/python -m benchmarks.solids [--ticks N]``; prints one table (median and p90 of the
tick [µs], its ratio to the capsules', the state kernel's and the solve's medians [µs] (the
stages of ``qpctl bench``), the pairs, DAQP's mean iterations, and the closed-loop clearance).
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from qpctl import Obstacle
from qpctl.bench.scenes import BenchScene, scenario_scene
from qpctl.bench.suites import ControllerSpec, closed_loop
from qpctl.bench.timing import StateSequence, time_on_states
from qpctl.geometry.shapes import SHAPES, Box, Cylinder, register_shape


class _FclBox(Box):
    name = "box_via_fcl"


class _FclCylinder(Cylinder):
    name = "cylinder_via_fcl"


def variants(scene: BenchScene) -> dict[str, BenchScene]:
    """The capsule scene, and the two with ``branch_low`` a box and ``trunk`` a cylinder."""
    out = {"capsules": scene}
    for label, box, cyl in (("box+cylinder", "box", "cylinder"),
                            ("box+cylinder (python-fcl)", _FclBox.name, _FclCylinder.name)):
        obs = []
        for o in scene.obstacles:
            if o.name == "branch_low":  # along x, 0.6 m, radius 0.025 m: a box of the same extent
                obs.append(Obstacle(box, o.position, size=[o.length + 2 * o.radius, 2 * o.radius, 2 * o.radius],
                                    name=o.name))
            elif o.name == "trunk":
                obs.append(Obstacle(cyl, o.position, radius=o.radius, length=o.length, axis=o.axis, name=o.name))
            else:
                obs.append(o)
        out[label] = replace(scene, name=f"{scene.name} {label}", obstacles=tuple(obs))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ticks", type=int, default=3000, help="closed-loop ticks whose states are timed")
    args = parser.parse_args(argv)
    register_shape(_FclBox())
    register_shape(_FclCylinder())
    try:
        scenes = variants(scenario_scene("panda_canopy", "canopy"))
        spec = ControllerSpec("qp", "daqp")
        runs = {label: closed_loop(s, spec, max_ticks=args.ticks) for label, s in scenes.items()}
        states = runs["capsules"].states
        assert isinstance(states, StateSequence)
        times = time_on_states({label: s.controller("qp", "daqp") for label, s in scenes.items()}, states)
    finally:
        SHAPES.pop(_FclBox.name)
        SHAPES.pop(_FclCylinder.name)
    base = float(np.median(times["capsules"].wall))
    print(f"panda_canopy, QP (daqp), {len(states)} same states, interleaved in blocks of 25")
    print(f"{'scene':28s} {'median µs':>10s} {'p90 µs':>8s} {'× capsules':>11s} {'state µs':>9s} "
          f"{'solve µs':>9s} {'pairs':>6s} {'iterations':>10s} {'min clearance m':>16s}")
    for label, t in times.items():
        med = float(np.median(t.wall))
        clearance = runs[label].metrics.get("min_clearance", float("nan"))
        state = float(np.nanmedian(t.stages["state_us"] - t.stages["rigid_us"]))
        print(f"{label:28s} {med:10.1f} {np.percentile(t.wall, 90):8.1f} {med / base:11.2f} {state:9.2f} "
              f"{np.nanmedian(t.stages['solve_us']):9.2f} {np.nanmedian(t.pairs):6.0f} "
              f"{np.nanmean(t.iterations):10.2f} {clearance:16.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
