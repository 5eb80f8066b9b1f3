"""``qpctl sweep --summarize DIR``: tables and plots of a sweep folder's dataset.

Writes into DIR:

* ``summary.md`` and ``summary.csv`` — per family × controller × solver: runs, failed runs, success
  rate (reached within 1 cm and no collision), collisions, least-clearance percentiles (p5, p50)
  [m], tracking percentiles (rms p50, p95; max p95) [m], tick-time percentiles (median over runs of
  each run's p50 and p99, the largest tick) [µs];
* ``success_vs_<key>.png`` — success rate against each numeric swept key (random keys in 8 bins);
* ``clearance_cdf.png`` — the CDF of each run's least clearance, per family, one line per law.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.sweep.store import read_dataset

COLUMNS = ("family", "controller", "solver", "runs", "failed", "success_rate", "collisions",
           "clearance_p5", "clearance_p50", "rms_tracking_p50", "rms_tracking_p95", "max_tracking_p95",
           "tick_us_p50", "tick_us_p99", "tick_us_max")


def _pct(values: Sequence[Any], q: float) -> float | None:
    v = [float(x) for x in values if x is not None and math.isfinite(float(x))]
    return float(np.percentile(v, q)) if v else None


def _law(r: dict[str, Any]) -> str:
    return r["controller"] if r["solver"] == "closed-form" else f"{r['controller']}-{r['solver']}"


def summary_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One summary row per (family, controller, solver), in first-seen order."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["family"], r["controller"], r["solver"]), []).append(r)
    out = []
    for (fam, ctrl, solver), rs in sorted(groups.items()):
        ok = [r for r in rs if r["status"] == "ok"]
        out.append({
            "family": fam, "controller": ctrl, "solver": solver, "runs": len(rs), "failed": len(rs) - len(ok),
            "success_rate": sum(bool(r["success"]) for r in ok) / len(rs),
            "collisions": sum(bool(r["collided"]) for r in ok),
            "clearance_p5": _pct([r["min_clearance"] for r in ok], 5),
            "clearance_p50": _pct([r["min_clearance"] for r in ok], 50),
            "rms_tracking_p50": _pct([r["rms_tracking_error"] for r in ok], 50),
            "rms_tracking_p95": _pct([r["rms_tracking_error"] for r in ok], 95),
            "max_tracking_p95": _pct([r["max_tracking_error"] for r in ok], 95),
            "tick_us_p50": _pct([r["tick_us_p50"] for r in ok], 50),
            "tick_us_p99": _pct([r["tick_us_p99"] for r in ok], 50),
            "tick_us_max": _pct([r["tick_us_max"] for r in ok], 100),
        })
    return out


def _cell(key: str, v: Any) -> str:
    if v is None:
        return "–"
    if key == "success_rate":
        return f"{100 * v:.0f} %"
    if isinstance(v, float):
        return f"{v:.0f}" if key.startswith("tick") else f"{v:.3g}"
    return str(v)


def markdown(summary: list[dict[str, Any]], *, title: str, failures: list[dict[str, Any]]) -> str:
    head = ("| family | controller | solver | runs | failed | success | collisions | clearance p5 [m] | "
            "clearance p50 [m] | rms e p50 [m] | rms e p95 [m] | max e p95 [m] | tick p50 [µs] | tick p99 [µs] | "
            "tick max [µs] |")
    lines = [f"# Sweep {title}", "", head, "|" + "---|" * len(COLUMNS)]
    for s in summary:
        lines.append("| " + " | ".join(_cell(k, s[k]) for k in COLUMNS) + " |")
    lines += ["", ("Success: the task point ends within 1 cm of its reference and no link touched an obstacle. "
                   "Clearance: each run's least signed distance between the arm and an obstacle. Tick times: the "
                   "median over the runs of each run's p50 and p99, and the largest tick; wall-clock, measured "
                   "with the runs spread over parallel workers (indicative only).")]
    if failures:
        lines += ["", "## Failed runs", "", "| run | family | scene | law | error |", "|---|---|---|---|---|"]
        for r in failures[:50]:
            lines.append(f"| {r['run_id']} | {r['family']} | {r['scene']} | {_law(r)} | {r['error'][:200]} |")
        if len(failures) > 50:
            lines.append(f"| … {len(failures) - 50} more | | | | |")
    return "\n".join(lines) + "\n"



def _bin_centre(edges: np.ndarray, v: float) -> float:
    """The centre of the bin of ``edges`` that holds v."""
    k = int(np.searchsorted(edges, v, side="right"))
    return float(np.mean([edges[max(k - 1, 0)], edges[min(k, len(edges) - 1)]]))


def _plots(rows: list[dict[str, Any]], swept: list[str], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    laws = sorted({_law(r) for r in rows})
    for key in swept:
        raw = [r.get(key) for r in rows]
        if not raw or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in raw):
            continue
        vals = [float(v) for v in raw if v is not None]
        distinct = sorted(set(vals))
        if len(distinct) > 8:  # a random key: 8 bins of equal counts
            edges = np.unique(np.quantile(vals, np.linspace(0, 1, 9)))
            centre = {v: _bin_centre(edges, v) for v in distinct}
        else:
            centre = {v: float(v) for v in distinct}
        fig, ax = plt.subplots(figsize=(6, 4))
        for law in laws:
            pts: dict[float, list[bool]] = {}
            for r in rows:
                if _law(r) == law:
                    pts.setdefault(centre[r[key]], []).append(r["status"] == "ok" and bool(r["success"]))
            xs = sorted(pts)
            ax.plot(xs, [100 * np.mean(pts[x]) for x in xs], marker="o", label=law)
        ax.set_xlabel(key)
        ax.set_ylabel("success [%]")
        ax.set_ylim(-5, 105)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        ax.set_title(f"success vs {key}")
        fig.tight_layout()
        path = out / f"success_vs_{key.replace('.', '_')}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    families = sorted({r["family"] for r in rows})
    fig, axes = plt.subplots(1, len(families), figsize=(5 * len(families), 4), squeeze=False)
    for ax, fam in zip(axes[0], families):
        for law in laws:
            c = np.sort([r["min_clearance"] for r in rows if r["family"] == fam and _law(r) == law
                         and r["status"] == "ok" and r["min_clearance"] is not None])
            if c.size:
                ax.step(c, np.arange(1, c.size + 1) / c.size, where="post", label=law)
        ax.axvline(0.0, color="k", lw=0.8)
        ax.set_xlabel("least clearance [m]")
        ax.set_ylabel("share of runs")
        ax.set_title(fam)
        ax.grid(alpha=0.3)
        if ax.get_lines():
            ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "clearance_cdf.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    written.append(path)
    return written


def summarize(root: str | Path, *, plots: bool = True) -> list[Path]:
    """Write summary.md, summary.csv and the plots of the sweep folder ``root``; return their paths."""
    import json

    root = Path(root)
    rows = read_dataset(root).to_pylist()
    meta_path = root / "sweep.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    swept = list(meta.get("swept", []))
    summary = summary_rows(rows)
    failures = [r for r in rows if r["status"] != "ok"]
    title = f"`{meta.get('name', root.name)}`: {len(rows)} of {meta.get('runs', len(rows))} runs"
    (root / "summary.md").write_text(markdown(summary, title=title, failures=failures))
    with open(root / "summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(COLUMNS))
        w.writeheader()
        w.writerows(summary)
    written = [root / "summary.md", root / "summary.csv"]
    if plots:
        written += _plots(rows, swept, root)
    return written
