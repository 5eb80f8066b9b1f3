"""Same ticks, side by side: time every controller's tick on one recorded sequence of states.

A closed-loop run gives the states (t, q, v); each controller then steps through exactly those
states, all controllers interleaved in blocks of consecutive ticks (the order rotating from block to
block so that none always runs first or last), so that they are compared on identical inputs under
the same machine conditions. Each controller keeps its own warm start along the sequence, as in a run;
each runs ``warmup()`` first, and each block opens with an untimed tick replaying the controller's
previous state, so that no timed tick pays for the cache the other controllers' blocks evicted
(see :func:`time_on_states`).

Two clocks per tick: the wall time of ``step()`` (``ControlOutput.compute_us``, what a control loop
waits for) and the thread's CPU time around it (what the code costs, without the time slices other
processes take — on a loaded machine the wall time's tail is mostly those). To tell a slow solve
from a slow machine, each tick also records the solver's iterations and the page faults the thread
took. The garbage collector is paused while timing (as ``timeit`` does); it is collected between
sequences.

The floor (:class:`PinocchioFloor`, label ``"floor"``) is ``pin.computeAllTerms`` alone, stepped
through the same states in the same blocks as a controller: every tick is also reported as a ratio
to it, the figure that carries from one machine to another.
"""

from __future__ import annotations

import gc
import resource
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import pinocchio as pin

from qpctl.robot.model import RobotModel

#: The per-tick stages a controller reports in ``ControlOutput.info`` [µs], cumulative as the tick
#: runs: rigid_us = Pinocchio's computeAllTerms; state_us = Pinocchio + the state kernel (rigid
#: terms, link–obstacle pairs and distances, barrier drift); build_us = the law's terms and, for the
#: QP, its cost and rows written in place (for paper/hsu: the law's terms and closed form);
#: solve_us = the solver call and the check of its answer (QP only).
STAGES = ("rigid_us", "state_us", "build_us", "solve_us")

#: The per-tick breakdown the tables and the stages plot show [µs]: (key, column title).
#: pinocchio = rigid_us, state kernel = state_us − rigid_us, law + rows = build_us, solve = solve_us,
#: other = wall − (state_us + build_us + solve_us): input checks, the kernel call (its arguments), the output, the timers.
BREAKDOWN = (("pinocchio_us", "Pinocchio"), ("state_kernel_us", "state kernel"), ("law_rows_us", "law + rows"),
             ("solve_us", "solve"), ("other_us", "other"))

FLOOR = "floor"  # the label of the floor in every same-tick suite


class Steppable(Protocol):
    """What the timing loop needs: a controller, or the floor."""

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> Any: ...

    def reset(self) -> None: ...


@dataclass
class FloorOutput:
    """The floor's tick: its wall time [µs] and no diagnostics."""

    compute_us: float
    info: dict[str, Any] = field(default_factory=dict)


class PinocchioFloor:
    """``pin.computeAllTerms(model, data, q, v)`` alone, stepped like a controller (its own ``pin.Data``):
    the floor under every tick, which each controller runs first."""

    kind = FLOOR

    def __init__(self, robot: RobotModel) -> None:
        self.model = robot.model
        self.data = robot.model.createData()

    def step(self, q: np.ndarray, v: np.ndarray, t: float) -> FloorOutput:
        start = time.perf_counter()
        pin.computeAllTerms(self.model, self.data, q, v)
        return FloorOutput((time.perf_counter() - start) * 1e6)

    def reset(self) -> None:
        """Nothing is kept between ticks."""


@dataclass(frozen=True)
class StateSequence:
    """States of a closed-loop run: t (T,) [s], q and v (T, n) [rad], [rad/s]."""

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def every(self, stride: int) -> StateSequence:
        """Every ``stride``-th state (a shorter benchmark; the warm start then spans ``stride`` ticks)."""
        return StateSequence(self.t[::stride], self.q[::stride], self.v[::stride])


@dataclass
class TickTimes:
    """One controller's timings over a :class:`StateSequence` (T ticks, all [µs])."""

    wall: np.ndarray  # (T,) wall time of step()
    cpu: np.ndarray  # (T,) thread CPU time of step()
    stages: dict[str, np.ndarray] = field(default_factory=dict)  # stage -> (T,), NaN where not reported
    pairs: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) link–obstacle pairs within the cutoff
    iterations: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) solver iterations (NaN: none)
    faults: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) page faults taken during step()
    cold: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (blocks,) wall time of each block's
    # untimed re-warm tick: a tick right after the other controllers' blocks (NaN: none)

    @staticmethod
    def concatenate(parts: Iterable[TickTimes]) -> TickTimes:
        parts = list(parts)
        stages = {s: np.concatenate([p.stages[s] for p in parts]) for s in STAGES}
        wall, cpu = (np.concatenate([getattr(p, f) for p in parts]) for f in ("wall", "cpu"))
        return TickTimes(wall, cpu, stages,
                         *(np.concatenate([getattr(p, f) for p in parts])
                           for f in ("pairs", "iterations", "faults", "cold")))


def breakdown(t: TickTimes) -> dict[str, np.ndarray]:
    """Per tick [µs]: the :data:`BREAKDOWN` columns from the reported stages (NaN where the tick
    reported none, as the floor; a closed form's solve is NaN and counts as 0 in ``other``)."""
    rigid, state, build, solve = (t.stages[s] for s in STAGES)
    reported = np.isfinite(state)
    other = t.wall - state - np.nan_to_num(build) - np.nan_to_num(solve)
    return {"pinocchio_us": rigid, "state_kernel_us": state - rigid, "law_rows_us": build, "solve_us": solve,
            "other_us": np.where(reported, other, np.nan)}


def _faults() -> int:
    """Page faults (major + minor) this thread has taken so far."""
    use = resource.getrusage(resource.RUSAGE_THREAD)
    return use.ru_majflt + use.ru_minflt


def summary(values: np.ndarray) -> dict[str, float]:
    """Median, 99th percentile and maximum (NaNs ignored; all NaN gives NaNs)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"median": float("nan"), "p99": float("nan"), "max": float("nan")}
    return {"median": float(np.median(v)), "p99": float(np.percentile(v, 99)), "max": float(np.max(v))}


BLOCK = 25  # consecutive ticks a controller runs before the next one takes over


def time_on_states(controllers: Mapping[str, Steppable], states: StateSequence, *,
                   progress: bool = False, desc: str = "same ticks", block: int = BLOCK,
                   warmup: bool = True, rewarm: bool = True) -> dict[str, TickTimes]:
    """Step every controller through ``states``, interleaved in blocks of ``block`` ticks (the order
    of the controllers rotating from block to block); their timings by label. With ``warmup``, each
    controller's ``warmup()`` runs first (then ``reset()``), as before a control loop.

    Blocks, not single ticks: a control loop runs one controller tick after tick, its Pinocchio data
    and solver workspace warm in the cache. Interleaving seven controllers tick by tick evicts them
    between ticks and measured the paper law 1.7× and the daqp QP 1.6× slower than in blocks (Panda
    canopy, this machine); blocks of 25 ticks keep each warm while machine drift still falls on all
    alike.

    ``rewarm``: each block after the first opens with one untimed tick that replays the controller's
    previous state (k0 − 1, the last of its previous block), which brings its data back into the cache
    without changing its warm start; its wall time is kept in ``TickTimes.cold``. Without it, the first
    tick of every block runs after the other controllers' blocks evicted its data: 1 tick in 25 measured
    2.5–3× its median (Panda + 10 spheres, this machine), which made up the whole p99."""
    labels = list(controllers)
    T = len(states)
    n_blocks = -(-T // block)
    out = {lb: TickTimes(np.empty(T), np.empty(T), {s: np.full(T, np.nan) for s in STAGES}, np.zeros(T),
                         np.full(T, np.nan), np.zeros(T), np.full(n_blocks, np.nan)) for lb in labels}
    for c in controllers.values():
        if warmup and hasattr(c, "warmup"):
            c.warmup()  # compile or load the kernels, build the workspace: what a loop does before it starts
        c.reset()
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=T, desc=desc, unit="tick", leave=False)
    gc.collect()
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        for k0 in range(0, T, block):
            shift = (k0 // block) % len(labels)
            for lb in labels[shift:] + labels[:shift]:
                if rewarm and k0 > 0:
                    k = k0 - 1
                    res = controllers[lb].step(states.q[k], states.v[k], float(states.t[k]))
                    out[lb].cold[k0 // block] = res.compute_us
                for k in range(k0, min(k0 + block, T)):
                    _time_tick(controllers[lb], states, k, out[lb])
            if bar is not None:
                bar.update(min(block, T - k0))
    finally:
        if was_enabled:
            gc.enable()
        if bar is not None:
            bar.close()
    return out


def _time_tick(controller: Steppable, states: StateSequence, k: int, rec: TickTimes) -> None:
    """Step ``controller`` on state k and record its clocks, stages, pairs, iterations, page faults."""
    q, v, t = states.q[k], states.v[k], float(states.t[k])
    f0 = _faults()
    c0 = time.thread_time()
    res = controller.step(q, v, t)
    c1 = time.thread_time()
    rec.faults[k] = _faults() - f0
    rec.wall[k] = res.compute_us
    rec.cpu[k] = (c1 - c0) * 1e6
    info = res.info  # built on first access, after the clocks stopped
    for s in STAGES:
        if s in info:
            rec.stages[s][k] = info[s]
    rec.pairs[k] = info.get("pairs", np.nan)
    rec.iterations[k] = info.get("iterations", np.nan)
