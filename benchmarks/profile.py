"""Where a tick's time goes: the Panda canopy ticks of one controller, timed part by part.

    python -m benchmarks.profile [--solver daqp] [--seed 100] [--top 25]

Replays the states of a closed-loop run of the canopy scene (``qpctl.bench.scenes.canopy_scene``) and
prints (1) the median wall time of each part of a tick, measured by making the calls the compiled
tick makes (``rigid_pass``: crba and nonLinearEffects, then each stage's kernel of ``qpctl.kernels`` and the solve), one at a
time and in tick order, on every state; (2) cProfile's functions with the most cumulative time
(cProfile's own overhead inflates those: compare shares).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import time
from collections.abc import Callable

import numpy as np

from qpctl.bench.scenes import canopy_scene
from qpctl.kernels import tick as K
from qpctl.simulation import Simulator
from qpctl.solvers import make_solver
from qpctl.solvers.daqp_ import DAQPSolver
from qpctl.tick import rigid_pass


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
    ``duration`` seconds; None: all): the whole ticks, then the calls of one QP tick timed one by
    one, in tick order, on the controller's own workspace."""
    scene, traj = _states(solver, seed, duration)
    Q, V, T = traj.q, np.ascontiguousarray(traj.v), traj.t
    ticks = range(len(T))
    paper, qp = scene.controller("paper"), scene.controller("qp", solver)
    paper.warmup()
    qp.warmup()
    out = {
        "paper law: whole tick": _median_us(lambda k: paper.step(Q[k], V[k], float(T[k])), ticks),
        "QP: whole tick": _median_us(lambda k: qp.step(Q[k], V[k], float(T[k])), ticks),
    }
    ws = qp.workspace()
    buf = ws.relaxed
    assert buf is not None
    solver_obj = make_solver(solver)  # a solver of its own, warm-started along the sequence as in a run
    names = ["Pinocchio crba + nonLinearEffects (both)", "state kernel: rigid terms, pairs, distances, barrier drift (both)",
             "law terms a, g, e_N, q̈₀ (both)", "paper law: its closed form (eq. 19)", "QP: cost and rows, in place",
             f"QP: {solver} solve", "QP: check, torque, record"]
    times = np.empty((len(ticks), len(names)))
    for i, k in enumerate(ticks):
        q, v, t = Q[k], V[k], float(T[k])
        c = [time.perf_counter()]
        rigid_pass(ws.model, ws.data, q, v)
        c.append(time.perf_counter())
        K.state(ws.work, q, v, t)
        c.append(time.perf_counter())
        K.law_terms(ws.work, True)
        c.append(time.perf_counter())
        K.closed_form(ws.work, True)
        c.append(time.perf_counter())
        K.qp_build(ws.work, buf.H, buf.f, buf.rows, buf.bu, buf.bl)
        c.append(time.perf_counter())
        if isinstance(solver_obj, DAQPSolver):
            x = solver_obj.solve_buffers(buf.H, buf.f, buf.rows, buf.bu, buf.bl, buf.sense)[0]
        else:
            x = solver_obj.solve(buf.problem).x
        c.append(time.perf_counter())
        K.qp_finish(ws.work, x, buf.rows, buf.bu, buf.bl, 1e-4, False)
        c.append(time.perf_counter())
        times[i] = np.diff(c)
    out.update({name: float(np.median(times[:, j]) * 1e6) for j, name in enumerate(names)})
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
