"""Where a tick's time goes: the Panda canopy ticks of one controller, timed part by part.

    python -m benchmarks.profile [--solver daqp] [--seed 100] [--top 25]

Replays the states of a closed-loop run of the canopy scene (``benchmarks.scenes.canopy_scene``) and
prints (1) the median wall time of each part of a tick, measured by timing the same calls the
controller makes, one part at a time, on every state; (2) cProfile's functions with the most
cumulative time (cProfile's own overhead inflates those, by about 1.3× here: compare shares).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time
from collections.abc import Callable

import numpy as np

from benchmarks.scenes import canopy_scene
from qpctl.law import closed_form_acceleration, law_terms
from qpctl.simulation import Simulator
from qpctl.solvers import make_solver


def _median_us(fn: Callable[[int], object], ticks: range) -> float:
    out = np.empty(len(ticks))
    for i, k in enumerate(ticks):
        t0 = time.perf_counter()
        fn(k)
        out[i] = time.perf_counter() - t0
    return float(np.median(out) * 1e6)


def _states(solver: str, seed: int, duration: float | None):
    scene = canopy_scene(seed)
    run_for = scene.duration if duration is None else duration
    return scene, Simulator(scene.controller("qp", solver), dt=scene.dt, duration=run_for).run(scene.q0)


def parts(solver: str = "daqp", seed: int = 100, duration: float | None = None) -> dict[str, float]:
    """Median wall time [µs] of each part of a tick on the canopy scene's states (the first
    ``duration`` seconds; None: all)."""
    scene, traj = _states(solver, seed, duration)
    Q, V, T = traj.q, traj.v, traj.t
    ticks = range(len(T))
    paper, qp = scene.controller("paper"), scene.controller("qp", solver)
    dyn = qp.dynamics
    states = [dyn.compute(Q[k], V[k], float(T[k])) for k in ticks]
    refs = [qp.path(float(T[k])) for k in ticks]
    terms = [law_terms(states[k], refs[k], qp.gains, weighted=True) for k in ticks]
    for s in states:
        s.barrier_drift()
    form = qp.formulation()
    problems = [form.build(states[k], terms[k], relax=True) for k in ticks]
    solver_obj = make_solver(solver)  # a solver of its own, warm-started along the sequence as in a run
    out = {
        "paper law: whole tick": _median_us(lambda k: paper.step(Q[k], V[k], float(T[k])), ticks),
        "QP: whole tick": _median_us(lambda k: qp.step(Q[k], V[k], float(T[k])), ticks),
        "state: Pinocchio terms + distances (both)": _median_us(lambda k: dyn.compute(Q[k], V[k], float(T[k])),
                                                               ticks),
        "law terms a, g, e_N, q̈₀ (both)": _median_us(lambda k: law_terms(states[k], refs[k], qp.gains,
                                                                        weighted=True), ticks),
        "paper law: its closed form (eq. 19)": _median_us(
            lambda k: closed_form_acceleration(states[k], terms[k], qp.gains, weighted=True), ticks),
        "QP: barrier drift": _median_us(lambda k: dyn.barrier_drift(states[k]), ticks),
        "QP: tasks + constraints + stacking (drift cached)": _median_us(
            lambda k: form.build(states[k], terms[k], relax=True), ticks),
        f"QP: {solver} solve": _median_us(lambda k: solver_obj.solve(problems[k]), ticks),
    }
    return out


def profile(solver: str = "daqp", seed: int = 100, top: int = 25, duration: float | None = None) -> str:
    """cProfile's report (cumulative time) of the QP controller over the canopy scene's states."""
    scene, traj = _states(solver, seed, duration)
    qp = scene.controller("qp", solver)
    prof = cProfile.Profile()
    prof.enable()
    for k in range(len(traj.t)):
        qp.step(traj.q[k], traj.v[k], float(traj.t[k]))
    prof.disable()
    buf = io.StringIO()
    pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(top)
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solver", default="daqp")
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--top", type=int, default=25)
    args = ap.parse_args(argv)
    print(f"Panda canopy-{args.seed}, qp-{args.solver}: median wall time per part of a tick [µs]\n")
    print("| part | median µs |\n|---|---|")
    for name, us in parts(args.solver, args.seed).items():
        print(f"| {name} | {us:.0f} |")
    print()
    print(profile(args.solver, args.seed, args.top))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
