"""benchmarks/peers.py: qpctl, Pink and mink on the Panda canopy in one process (issue 23, item 6).

Needs the ``[peers]`` extra (pin-pink, mink): skipped only when it is not installed; ``make peers``
installs it and runs this test after the benchmark (marked slow: out of ``make test``'s time).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pink", reason="the [peers] extra (pin-pink) is not installed: make peers runs this test")
pytest.importorskip("mink", reason="the [peers] extra (mink) is not installed: make peers runs this test")

from benchmarks import peers


@pytest.mark.slow  # ~8 s with Pink's and mink's imports: make peers (and make soak) run it
def test_three_controllers_on_the_same_scene_interleaved():
    """0.06 s of the canopy path: each loop ran every tick (a positive time each), tracked x_d(t) to
    1 mm from the home pose, kept clear of every obstacle (the world's clearance, positive), and the
    peers' pair counts are every link × obstacle (8 capsules × the scenario's obstacles); the table
    has a row per controller with qpctl's ratio 1.00 first."""
    loops = peers.run(0.06)
    assert list(loops) == ["qpctl (QP, daqp)", "Pink (IK, daqp)", "mink (IK, daqp)"]
    qp = loops["qpctl (QP, daqp)"]
    n_obs = len(qp.world.ws.obstacles)
    for name, lp in loops.items():
        assert lp.tick_us.size == 61 and (lp.tick_us > 0).all(), name
        assert lp.error.max() <= 1e-3, (name, lp.error.max())
        assert lp.clearance.min() > 0, name
        if name != "qpctl (QP, daqp)":
            assert lp.pairs == len(qp.robot.capsules) * n_obs, (name, lp.pairs)
    text = peers.table(loops)
    rows = [r for r in text.splitlines() if r.startswith("| ") and "controller" not in r]
    assert len(rows) == 3 and "| 1.00 |" in rows[0]
    assert np.isfinite([float(r.split("|")[3]) for r in rows]).all()
