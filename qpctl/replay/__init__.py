"""The replay page: ``replay.html``, a self-contained file that plays a run back in any browser,
offline — the robot (its meshes, or its capsules) coloured by its clearance, the obstacles moving,
the reference path and the task point's trace, a timeline with play, pause, scrub and speed, and the
figures that explain the run beside it.

* :mod:`~qpctl.replay.record` — what a replay is made of, from a run or a run's folder;
* :mod:`~qpctl.replay.frames` — the run sampled at the display rate;
* :mod:`~qpctl.replay.visuals` — the meshes and the colour scale;
* :mod:`~qpctl.replay.figures` — the figure beside the scene;
* :mod:`~qpctl.replay.page` — the page (viser's scene serializer, plus the panel);
* :mod:`~qpctl.replay.browser` — headless Chromium: a screenshot of a page, and what it logged.

``qpctl simulate`` writes ``replay.html`` beside every run's outputs (``--no-replay`` skips it);
``qpctl replay RUN_DIR`` writes it for a run folder (docs/replay.md).
"""

from qpctl.replay.page import REPLAY_FILE, Camera, ReplayStats, write_replay
from qpctl.replay.record import ReplayInput, from_result, from_run_dir


def write_run_replay(run_dir: str, out: str | None = None, **kwargs: object) -> ReplayStats:
    """Write ``run_dir``'s replay (to ``out``, default ``run_dir/replay.html``); what it wrote."""
    from pathlib import Path

    return write_replay(from_run_dir(run_dir), Path(out) if out else Path(run_dir) / REPLAY_FILE, **kwargs)  # type: ignore[arg-type]


__all__ = ["REPLAY_FILE", "Camera", "ReplayInput", "ReplayStats", "from_result", "from_run_dir", "write_replay",
           "write_run_replay"]
