"""DAQP on the packed rows (qpctl.kernels.daqp_pack) against DAQP on the QP's full layout.

The reference is DAQP's C API driven here the way the tick drove it before packing: one workspace set
up on the layout's own arrays (every slot, the empty ones as zero rows with bounds ±∞), then
``daqp_update_ldp`` and ``daqp_solve`` each tick. Dropping rows that can never bind and keeping the
constraint states by layout index must leave every number DAQP computes for the other rows as it was:
x, the multipliers and the iteration counts are compared bit for bit over closed-loop ticks, through
slots that fill and empty and through cold starts.
"""

from __future__ import annotations

import ctypes as C
import importlib.metadata

import numpy as np
import pytest

from qpctl import Scenario
from qpctl.kernels import tick as K
from qpctl.kernels.daqp_pack import idle_state
from qpctl.simulation import Simulator
from qpctl.solvers import daqp_native
from qpctl.solvers.daqp_native import WORK_BYTES, NativeDAQP, _library, _Problem, _Result

# The packed path is DAQP's C API path, which qpctl uses only with a DAQP version it was checked
# against (the structs' layout): with another version the controller solves through daqp.Model and no
# code here runs. With a checked version the path must be there (the first test), so a failing
# self-test cannot pass for a skip.
CHECKED = importlib.metadata.version("daqp") in daqp_native.CHECKED_VERSIONS
pytestmark = pytest.mark.skipif(not CHECKED, reason=f"DAQP {importlib.metadata.version('daqp')} is not one the C "
                                f"API path was checked against ({', '.join(daqp_native.CHECKED_VERSIONS)}): "
                                "qpctl solves through daqp.Model there, and the packed rows are not used")


def test_the_c_api_path_is_used_with_a_checked_daqp():
    """daqp_native.available(): the settings pointer found and the self-test (random QPs with empty
    slots, on the packed rows) equal to daqp.solve."""
    assert daqp_native.available()

UPDATE_ALL = 1 | 2 | 4 | 8


class FullLayoutDAQP:
    """The reference: DAQP's C API on the full layout (no packing), its own copies of the arrays."""

    def __init__(self, H, f, rows, bu, bl, sense):
        self.lib = _library()
        self.H, self.f, self.rows, self.bu, self.bl = H.copy(), f.copy(), rows.copy(), bu.copy(), bl.copy()
        self.sense = sense.astype(np.int32)
        nv, m = H.shape[0], bu.shape[0]
        p = [a.ctypes.data_as(C.POINTER(C.c_double)) for a in (self.H, self.f, self.rows, self.bu, self.bl)]
        self.problem = _Problem(nv, m, nv, *p, self.sense.ctypes.data_as(C.POINTER(C.c_int)), None, 0, 0)
        self.x, self.lam = np.zeros(nv), np.zeros(m)
        self.result = _Result(*(a.ctypes.data_as(C.POINTER(C.c_double)) for a in (self.x, self.lam)), 0.0, 0.0, 0, 0,
                              0, 0.0, 0.0)
        self.work = np.zeros(WORK_BYTES, np.uint8)
        self.ready = False

    def load(self, H, f, rows, bu, bl):
        self.H[:], self.f[:], self.rows[:], self.bu[:], self.bl[:] = H, f, rows, bu, bl

    def solve(self):
        if not self.ready:
            self.lib.allocate_daqp_settings(self.work.ctypes.data)
            assert self.lib.setup_daqp(C.addressof(self.problem), self.work.ctypes.data, None) >= 0
            self.ready = True
        self.lib.daqp_update_ldp(UPDATE_ALL, self.work.ctypes.data, C.addressof(self.problem))
        self.lib.daqp_solve(C.addressof(self.result), self.work.ctypes.data)
        return self.result.exitflag, self.result.iter

    def free(self):
        if self.ready:
            self.lib.free_daqp_workspace(self.work.ctypes.data)
            self.lib.free_daqp_ldp(self.work.ctypes.data)
            self.work[:] = 0
            self.ready = False


def _problems(layout: str, duration: float = 6.0) -> list[tuple[np.ndarray, ...]]:
    """The QP in ``layout`` of every 2nd tick of panda_spheres' closed loop (the built-in simulator,
    1 ms), copied as the controller built it."""
    # the relaxed layout is built only on the ticks that solve it: every tick, with "always"
    relax = "always" if layout == "relaxed" else "auto"
    scenario = Scenario.load("panda_spheres", [f"controller.task_relaxation={relax}"])
    ctrl = scenario.build_controller("qp")
    buf = getattr(ctrl.qp_path().ws, layout)
    step, seen = ctrl.step, []

    def hooked(q, v, t):
        out = step(q, v, t)
        seen.append(tuple(a.copy() for a in (buf.H, buf.f, buf.rows, buf.bu, buf.bl)))
        return out

    ctrl.step = hooked
    Simulator(ctrl, dt=1e-3, duration=duration).run(scenario.q0(ctrl.robot))
    return seen[::2], buf.sense


def _replay(layout: str, cold_every: int = 400):
    """Each problem solved by a packed workspace and by the reference, both warm-started from their
    previous solve (cold every ``cold_every``): (packed, reference, its (flag, iterations), ours, m)."""
    problems, sense = _problems(layout)
    mine = NativeDAQP(*[a.copy() for a in problems[0]], sense)
    ref = FullLayoutDAQP(*problems[0], sense)
    for k, args in enumerate(problems):
        for dst, src in zip(mine._arrays[:5], args):
            dst[...] = src
        ref.load(*args)
        if not mine.ready or k % cold_every == 0:
            mine.setup()
            ref.free()
        flag = K.native_solve(mine.dq)
        yield mine, ref, ref.solve(), (int(flag), int(mine.flag[1])), int(mine.m_view[0])
    mine.free()
    ref.free()


@pytest.mark.parametrize("layout", ["hard", "relaxed"])
def test_the_packed_solve_is_the_full_layouts_bit_for_bit(layout):
    """x, λ (by layout index) and the iteration counts of DAQP on the packed rows equal those of DAQP on
    the full layout, on every tick of a closed loop whose pairs come and go, through cold starts."""
    counts, solved, binding, moved = set(), 0, 0, 0
    last = None
    for mine, ref, ref_out, mine_out, m in _replay(layout):
        assert mine_out == ref_out
        assert np.array_equal(mine.x, ref.x) and np.array_equal(mine.lam, ref.lam)
        counts.add(m)
        solved += ref_out[0] > 0
        ineq = np.flatnonzero(ref.lam[ref.H.shape[0]:][ref.sense[ref.H.shape[0]:] == 0])
        binding += ineq.size > 0  # a working set with an inequality row in it, carried to the next tick
        idx = mine.idx[:m - ref.H.shape[0]].copy()
        moved += last is not None and (idx.size != last.size or not np.array_equal(idx, last))
        last = idx
        assert m < mine.bu_c.shape[0]  # empty slots were dropped
    assert len(counts) >= 3, counts  # slots filled and emptied: rows moved in the packed order
    # (binding: ticks whose working set holds an inequality row; moved: ticks whose packed rows are not
    # the last tick's, so the states DAQP kept had to follow their rows)
    assert solved > 2000 and binding > 200 and moved > 40, (solved, binding, moved)


def _zero_row_mark(s):  # DAQP's include/constants.h
    return 4 | 2048 | (s & 2) | ((s & 1) << 12) | ((s & (4 | 8)) << 11)


def _zero_row_sense(s):
    return ((s & 2) | ((s >> 12) & 1) | ((s >> 11) & (4 | 8))) if s & 2048 else s


def test_an_empty_slot_keeps_what_daqps_zero_row_mark_keeps():
    """idle_state against DAQP's macros (daqp_normalize_M: an equality found from the bounds is
    released first), for every state below the zero-row bit."""
    for s in range(2048):
        released = s & ~(1 | 4) if s & 128 else s
        assert idle_state(s) == _zero_row_sense(_zero_row_mark(released)) & 0b1111, s


def test_a_workspace_not_laid_out_as_expected_is_refused(monkeypatch):
    """The state pointer is taken only where the workspace's n, m and ms and the states DAQP copied
    say it is: at another offset the set-up raises instead of handing DAQP a wrong pointer."""
    ctrl = Scenario.load("panda_spheres").build_controller("qp")
    ctrl.step(np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785]), np.zeros(7), 0.0)
    buf = ctrl.qp_path().ws.hard
    nat = NativeDAQP(buf.H.copy(), buf.f.copy(), buf.rows.copy(), buf.bu.copy(), buf.bl.copy(), buf.sense)
    assert nat.setup() >= 0
    nat.free()
    monkeypatch.setattr(daqp_native, "_SENSE_OFFSET", 72)  # the next pointer: DAQP's row scalings
    with pytest.raises(RuntimeError, match="DAQPWorkspace"):
        nat.setup()
    assert not nat.ready


def test_the_packed_solve_is_the_full_layouts_through_a_depth_map():
    """The same on panda_canopy_depth's QP (2 s of its closed loop): the depth map's pair rows and soft
    speed rows, each link's slack column, slots that fill and empty as the map changes."""
    from qpctl.run import simulate

    scen = Scenario.load("panda_canopy_depth", ["sim.duration=2.0"])
    build, seen = scen.build_controller, []

    def hooked_build(*args, **kw):
        ctrl = build(*args, **kw)
        step = ctrl.step

        def hooked(q, v, t):
            out = step(q, v, t)
            buf = ctrl.qp_path().ws.hard
            seen.append((*(a.copy() for a in (buf.H, buf.f, buf.rows, buf.bu, buf.bl)), buf.sense))
            return out

        ctrl.step = hooked
        return ctrl

    scen.build_controller = hooked_build
    simulate(scen)
    mine = NativeDAQP(*[a.copy() for a in seen[0][:5]], seen[0][5])
    ref = FullLayoutDAQP(*seen[0][:5], seen[0][5])
    counts, solved = set(), 0
    for args in seen:
        for dst, src in zip(mine._arrays[:5], args[:5]):
            dst[...] = src
        ref.load(*args[:5])
        if not mine.ready:
            mine.setup()
        flag = K.native_solve(mine.dq)
        ref_out = ref.solve()
        assert (int(flag), int(mine.flag[1])) == ref_out
        assert np.array_equal(mine.x, ref.x) and np.array_equal(mine.lam, ref.lam)
        counts.add(int(mine.m_view[0]))
        solved += ref_out[0] > 0
    assert seen[0][2].shape[1] > 7 and len(counts) >= 3 and solved > 1500, (seen[0][2].shape, counts, solved)
    mine.free()
    ref.free()
