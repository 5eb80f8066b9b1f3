"""Where a sweep's results live: one small Parquet file per finished run, read as one dataset.

    DIR/spec.toml              the spec as given (a folder holds one sweep: another spec is refused)
    DIR/sweep.json             the sweep's name, run count and swept keys
    DIR/runs/<run_id>.parquet  one row per finished run, written to a temporary name and renamed
    DIR/runs/part-<hash>.parquet  the rows of a finished sweep, compacted (:meth:`RunStore.compact`)

A run's file appears whole or not at all, so a sweep killed at any moment (Ctrl-C, SIGKILL) keeps
every run that had finished and loses only those in flight; the next sweep into DIR skips the runs
already written (failed runs included: they are finished, with their error text). When a sweep has
no run left to do, its one-row files are merged into one part file.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from qpctl.errors import ConfigError
from qpctl.sweep.runner import METRIC_COLUMNS, TIMING_COLUMNS, scene_name
from qpctl.sweep.spec import RunParams, SweepSpec

#: Columns every row starts with: who the run is.
ID_COLUMNS: dict[str, str] = {
    "run_id": "string", "sweep": "string", "family": "string", "kind": "string", "scene": "string",
    "scene_seed": "int64", "controller": "string", "solver": "string", "repetition": "int64", "seed": "int64",
    "params": "string",
}
STATUS_COLUMNS: dict[str, str] = {"status": "string", "error": "string"}


def _pa_type(name: str) -> Any:
    import pyarrow as pa

    return {"string": pa.string(), "int64": pa.int64(), "float64": pa.float64(), "bool": pa.bool_()}[name]


def _swept_type(values: list[Any]) -> str:
    if all(isinstance(v, bool) for v in values):
        return "bool"
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        return "float64"
    return "string"


def swept_columns(spec: SweepSpec) -> dict[str, str]:
    """One column per swept key (grid and random), named by the dotted key."""
    cols = {k: _swept_type(list(v)) for k, v in spec.grid}
    cols.update({k: "float64" for k, _ in spec.random})
    return cols


class RunStore:
    """The Parquet dataset of one sweep folder."""

    def __init__(self, root: str | Path, spec: SweepSpec | None = None) -> None:
        try:
            import pyarrow  # noqa: F401
        except ImportError as exc:
            raise ConfigError(f"pyarrow is not installed ({exc}); pip install 'qpctl[sweep]'") from None
        self.root = Path(root)
        self.runs_dir = self.root / "runs"
        self.spec = spec
        self.swept = swept_columns(spec) if spec is not None else {}
        columns = {**ID_COLUMNS, **self.swept, **STATUS_COLUMNS, **METRIC_COLUMNS, **TIMING_COLUMNS}
        import pyarrow as pa

        self.schema = pa.schema([(k, _pa_type(t)) for k, t in columns.items()])

    def open(self, total: int) -> None:
        """Create the folder for ``spec``, or check that it holds the same sweep."""
        assert self.spec is not None
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        for stale in self.runs_dir.glob(".*.tmp"):  # a row being written when a sweep was killed
            stale.unlink(missing_ok=True)
        kept = self.root / "spec.toml"
        if kept.exists():
            if kept.read_text() != self.spec.text:
                raise ConfigError(f"{self.root} holds another sweep ({kept} differs from {self.spec.source}); "
                                  "use another --out", key="--out")
        else:
            _atomic_write(kept, self.spec.text.encode())
        meta = {"name": self.spec.name, "source": self.spec.source, "runs": total,
                "swept": list(self.swept), "controllers": list(self.spec.controllers),
                "solvers": list(self.spec.solvers), "families": [f.name for f in self.spec.families]}
        _atomic_write(self.root / "sweep.json", (json.dumps(meta, indent=2) + "\n").encode())

    def done_ids(self) -> set[str]:
        """Ids of the runs whose row is written (one file each, or in a compacted part)."""
        singles, parts = _files(self.runs_dir)
        ids = {p.name[:-8] for p in singles}
        if parts:
            import pyarrow.parquet as pq

            for part in parts:
                ids.update(pq.read_table(part, columns=["run_id"]).column("run_id").to_pylist())
        return ids

    def compact(self) -> Path | None:
        """Merge the one-row files into one ``part-<hash>.parquet`` (then remove them): a sweep of 10⁵
        runs is then a few files, not 10⁵. Safe to kill at any point: a row is in its own file or in a
        part until the part is in place; a row found in both is read once."""
        import pyarrow.parquet as pq

        singles, _ = _files(self.runs_dir)
        if len(singles) < 2:
            return None
        table = pq.ParquetDataset([str(p) for p in singles]).read().sort_by("run_id")
        ids = table.column("run_id").to_pylist()
        name = "part-" + hashlib.sha256("".join(ids).encode()).hexdigest()[:16] + ".parquet"
        fd, tmp = tempfile.mkstemp(prefix=".", suffix=".tmp", dir=self.runs_dir)
        os.close(fd)
        try:
            pq.write_table(table, tmp)
            os.replace(tmp, self.runs_dir / name)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        for p in singles:
            p.unlink(missing_ok=True)
        return self.runs_dir / name

    def row(self, params: RunParams, result: dict[str, Any]) -> dict[str, Any]:
        """The full row of a run: its identity, swept values, status, metrics and timings."""
        assert self.spec is not None
        ov = dict(params.overrides)
        row: dict[str, Any] = {
            "run_id": params.run_id, "sweep": self.spec.name, "family": params.family, "kind": params.kind,
            "scene": scene_name(params), "scene_seed": params.scene_seed, "controller": params.controller,
            "solver": params.solver, "repetition": params.repetition, "seed": params.seed,
            "params": params.to_json(),
        }
        for key, typ in self.swept.items():
            v = ov.get(key)
            row[key] = json.dumps(v) if typ == "string" and not isinstance(v, str) else v
        row.update({k: result.get(k) for k in (*STATUS_COLUMNS, *METRIC_COLUMNS, *TIMING_COLUMNS)})
        return row

    def write(self, row: dict[str, Any]) -> Path:
        """Write one row as ``runs/<run_id>.parquet`` (whole or not at all)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.Table.from_pylist([row], schema=self.schema)
        dest = self.runs_dir / f"{row['run_id']}.parquet"
        fd, tmp = tempfile.mkstemp(prefix=".", suffix=".tmp", dir=self.runs_dir)
        os.close(fd)
        try:
            pq.write_table(table, tmp)
            os.replace(tmp, dest)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        return dest

    def read(self) -> Any:
        """Every written row, as one ``pyarrow.Table`` sorted by run id."""
        return read_dataset(self.root)


def read_dataset(root: str | Path) -> Any:
    """The rows of the sweep folder ``root`` as one ``pyarrow.Table`` (sorted by run id)."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.dataset as ds

    runs = Path(root) / "runs"
    singles, parts = _files(runs)
    if not singles and not parts:
        raise ConfigError(f"no finished runs in {runs}", key="--summarize")
    tables = [ds.dataset([str(p) for p in parts], format="parquet").to_table()] if parts else []
    seen = set(tables[0].column("run_id").to_pylist()) if tables else set()
    rest = [str(p) for p in singles if p.name[:-8] not in seen]  # a compaction killed before its clean-up
    if rest:
        tables.append(ds.dataset(rest, format="parquet").to_table())
    table = pa.concat_tables(tables) if len(tables) > 1 else tables[0]
    if len(parts) > 1:  # parts of compactions killed before their clean-up may share rows
        _, first = np.unique(np.asarray(table.column("run_id").to_pylist(), dtype=object), return_index=True)
        table = table.take(pa.array(np.sort(first)))
    return table.take(pc.sort_indices(table, sort_keys=[("run_id", "ascending")]))


def _files(runs: Path) -> tuple[list[Path], list[Path]]:
    """(one-row files ``<run_id>.parquet``, compacted ``part-*.parquet``) in ``runs``, sorted."""
    if not runs.is_dir():
        return [], []
    files = sorted(p for p in runs.iterdir() if p.name.endswith(".parquet") and not p.name.startswith("."))
    parts = [p for p in files if p.name.startswith("part-")]
    return [p for p in files if not p.name.startswith("part-")], parts


def _atomic_write(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".", suffix=".tmp", dir=path.parent)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)
