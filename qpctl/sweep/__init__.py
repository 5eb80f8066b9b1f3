"""Sweeps at scale (issue 14): ``qpctl sweep SPEC [--backend local|ray] [--address ADDR] [--jobs N] [--out DIR]``.

* :mod:`~qpctl.sweep.spec` — sweep specs (TOML, packaged by name) expanded into runs with stable ids;
* :mod:`~qpctl.sweep.families` — scene families: seeded canopies, seeded planar scenes, scenarios;
* :mod:`~qpctl.sweep.runner` — one run: parameters in, a row of metrics out;
* :mod:`~qpctl.sweep.engine` and :mod:`~qpctl.sweep.backends` — the one engine (local processes or
  Ray) that ``qpctl sweep``, ``make demo``'s reproduction and ``qpctl bench``'s closed loop share;
* :mod:`~qpctl.sweep.store` — one Parquet file per finished run; a rerun resumes;
* :mod:`~qpctl.sweep.summary` — tables (Markdown, CSV) and plots of a sweep folder.
"""

from qpctl.sweep.backends import LocalBackend, RayBackend, make_backend
from qpctl.sweep.driver import SweepReport, run_sweep
from qpctl.sweep.engine import Outcome, execute, map_ordered
from qpctl.sweep.runner import execute_run
from qpctl.sweep.spec import RunParams, SweepSpec, packaged_specs
from qpctl.sweep.store import RunStore, read_dataset
from qpctl.sweep.summary import summarize

__all__ = ["LocalBackend", "Outcome", "RayBackend", "RunParams", "RunStore", "SweepReport", "SweepSpec",
           "execute", "execute_run", "make_backend", "map_ordered", "packaged_specs", "read_dataset", "run_sweep",
           "summarize"]
