"""Same ticks, side by side: time every controller's tick on one recorded sequence of states.

A closed-loop run gives the states (t, q, v); each controller then steps through exactly those
states, all controllers interleaved in blocks of consecutive ticks (the order rotating from block to
block so that none always runs first or last), so that they are compared on identical inputs under
the same machine conditions. Each controller keeps its own warm start along the sequence, as in a run.

Two clocks per tick: the wall time of ``step()`` (``ControlOutput.compute_us``, what a control loop
waits for) and the thread's CPU time around it (what the code costs, without the time slices other
processes take — on a loaded machine the wall time's tail is mostly those). To tell a slow solve
from a slow machine, each tick also records the solver's iterations and the page faults the thread
took. The garbage collector is paused while timing (as ``timeit`` does); it is collected between
sequences.
"""

from __future__ import annotations

import gc
import resource
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from qpctl.controllers.base import Controller

#: The per-tick stages a controller reports in ``ControlOutput.info`` [µs].
STAGES = ("rigid_us", "distance_us", "state_us", "build_us", "solve_us")


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

    @staticmethod
    def concatenate(parts: Iterable[TickTimes]) -> TickTimes:
        parts = list(parts)
        stages = {s: np.concatenate([p.stages[s] for p in parts]) for s in STAGES}
        return TickTimes(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("wall", "cpu")), stages,
                         *(np.concatenate([getattr(p, f) for p in parts]) for f in ("pairs", "iterations", "faults")))


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


def time_on_states(controllers: Mapping[str, Controller], states: StateSequence, *,
                   progress: bool = False, desc: str = "same ticks", block: int = BLOCK) -> dict[str, TickTimes]:
    """Step every controller through ``states``, interleaved in blocks of ``block`` ticks (the order
    of the controllers rotating from block to block); their timings by label.

    Blocks, not single ticks: a control loop runs one controller tick after tick, its Pinocchio data
    and solver workspace warm in the cache. Interleaving seven controllers tick by tick evicts them
    between ticks and measured the paper law 1.7× and the daqp QP 1.6× slower than in blocks (Panda
    canopy, this machine); blocks of 25 ticks keep each warm while machine drift still falls on all
    alike."""
    labels = list(controllers)
    T = len(states)
    out = {lb: TickTimes(np.empty(T), np.empty(T), {s: np.full(T, np.nan) for s in STAGES}, np.zeros(T),
                         np.full(T, np.nan), np.zeros(T)) for lb in labels}
    for c in controllers.values():
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


def _time_tick(controller: Controller, states: StateSequence, k: int, rec: TickTimes) -> None:
    """Step ``controller`` on state k and record its clocks, stages, pairs, iterations, page faults."""
    q, v, t = states.q[k], states.v[k], float(states.t[k])
    f0 = _faults()
    c0 = time.thread_time()
    res = controller.step(q, v, t)
    c1 = time.thread_time()
    rec.faults[k] = _faults() - f0
    rec.wall[k] = res.compute_us
    rec.cpu[k] = (c1 - c0) * 1e6
    for s in STAGES:
        if s in res.info:
            rec.stages[s][k] = res.info[s]
    rec.pairs[k] = res.info.get("pairs", np.nan)
    rec.iterations[k] = res.info.get("iterations", np.nan)
