"""A study's results: tidy tables (pandas), provenance, and the summaries the pictures read.

When to use
-----------
``write_results`` is called by the runner; ``load_results(out)`` reads a results folder back
(a notebook, a report). The folder holds::

    cells.parquet    one row per cell: its factors, status, error, and every measure
    numbers.parquet  one row per reported number of every cell (err, std, |err|/std, flags)
    provenance.json  package version and commit, machine, date, seeds, run mode, wall time
    study.json       the study as it ran (after --size)
    summary.md       per design point: medians over repetitions (markdown)
    figures/*.png    the pictures (stircasadi.studies.plots)
    cells/<key>.json the cache (one record per cell)

Parquet needs pyarrow; without it the tables are CSV (``cells.csv``, ``numbers.csv``).
Lists and tables among the factors (``scene_args``, ``drop_direct``) are stored as JSON text.
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import StudyError
from ..io import atomic_write_text
from .cache import dumps

__all__ = ["StudyResults", "write_results", "load_results", "design_columns", "markdown_table", "as_text"]

_RUN_COLS = ("repetition", "seed")
#: the columns of the numbers table (stircasadi.testing.compare rows, tied to their cell)
NUMBER_COLUMNS = ["cell", "patch_id", "truth_index", "visible", "quantity", "component", "kind",
                  "estimate", "truth", "err", "std", "std_missing", "z", "flagged", "given", "nonfinite"]


@dataclass
class StudyResults:
    """Tables and provenance of one results folder."""

    out: Path
    cells: object
    """pandas DataFrame, one row per cell."""
    numbers: object
    """pandas DataFrame, one row per reported number."""
    provenance: dict
    study: dict
    figures: list = field(default_factory=list)

    def design_columns(self) -> list[str]:
        return design_columns(self.cells, self.study)

    def summary(self) -> str:
        c = self.cells
        counts = c["status"].value_counts().to_dict() if len(c) else {}
        p = self.provenance
        return (f"study {self.study.get('name')}: {len(c)} cells ("
                + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + f"); "
                f"{p.get('run', {}).get('n_computed', 0)} computed, {p.get('run', {}).get('n_cached', 0)} "
                f"cached, " + (f"{p['run']['n_missing']} not run, " if p.get("run", {}).get("n_missing") else "")
                + f"wall {p.get('run', {}).get('wall_s', float('nan')):.1f} s ({p.get('run', {}).get('mode')}); "
                f"results in {self.out}")


def _pd():
    try:
        import pandas as pd
    except ImportError as exc:
        raise StudyError("Study tables need pandas: pip install 'stircasadi[studies]'.") from exc
    return pd


def _has_pyarrow() -> bool:
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        return False
    return True


def _flat(v):
    if isinstance(v, (dict, list, tuple)):
        return dumps(v, sort_keys=True)
    return v


def as_text(series):
    """A column as text labels, missing values as "-" (pandas' string dtype keeps NaN)."""
    return series.map(lambda v: "-" if v is None or (isinstance(v, float) and v != v) else str(v))


def design_columns(cells, study: dict) -> list[str]:
    """Factor columns that vary across the cells (besides repetition and seed)."""
    keys = set()
    for part in ("base", "factors"):
        keys |= set((study.get(part) or {}))
    for c in study.get("cases") or []:
        keys |= set(c)
    cols = [k for k in sorted(keys) if k in cells.columns and as_text(cells[k]).nunique() > 1]
    return cols


def _tables(keys, cache):
    pd = _pd()
    rows, nums = [], []
    seen = set()
    for k in keys:
        if k in seen:
            continue
        seen.add(k)
        rec = cache.get(k)
        if rec is None:
            continue
        row = {"cell": k}
        row.update({p: _flat(v) for p, v in rec["params"].items()})
        row["status"] = rec["status"]
        row["stage"] = rec.get("stage")
        err = rec.get("error") or {}
        row["error_type"] = err.get("type", "")
        row["error"] = err.get("message", "")
        row.update({m: _flat(v) for m, v in (rec.get("measures") or {}).items()})
        row["worker"] = rec.get("worker", "")
        rows.append(row)
        for r in rec.get("numbers") or []:
            nums.append({"cell": k, **r})
    cells = pd.DataFrame(rows)
    numbers = pd.DataFrame(nums, columns=None if nums else NUMBER_COLUMNS)
    for df in (cells, numbers):
        for col in df.columns:
            if df[col].dtype == object:
                types = {type(v) for v in df[col] if v is not None and v == v}
                if len(types) > 1 or (types and not types <= {str, bool}):
                    df[col] = df[col].map(lambda v: None if v is None else str(v))
    return cells, numbers


def _git_commit() -> str:
    here = Path(__file__).resolve().parents[2]
    try:
        r = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True,
                           timeout=5)
        d = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True, timeout=5)
        return r.stdout.strip() + ("-dirty" if d.stdout.strip() else "") if r.returncode == 0 else ""
    except (OSError, subprocess.SubprocessError):
        return ""


def provenance(study, cells, run_info: dict) -> dict:
    """Package, machine, date and seeds of a run."""
    from .. import __version__

    from importlib import metadata

    versions = {}
    for dist in ("numpy", "scipy", "casadi", "dask", "distributed", "pandas", "pyarrow"):
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    try:
        import psutil

        mem_gb = psutil.virtual_memory().total / 1e9
    except ImportError:
        mem_gb = None
    seeds = sorted({int(s) for s in cells["seed"]}) if len(cells) and "seed" in cells else []
    return {"package": "stircasadi", "version": __version__, "commit": _git_commit(),
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(),
            "machine": {"node": platform.node(), "platform": platform.platform(),
                        "python": platform.python_version(), "cpu_count": os.cpu_count(),
                        "memory_gb": mem_gb, "processor": platform.processor()},
            "versions": versions, "seeds": seeds, "run": run_info, "study": study.name}


def write_results(study, out, keys, cache, run_info: dict, figures: bool = True) -> StudyResults:
    """Tables, provenance, summary and (optionally) pictures of the cached cells of ``keys``."""
    out = Path(out)
    cells, numbers = _tables(keys, cache)
    prov = provenance(study, cells, run_info)
    atomic_write_text(out / "provenance.json", dumps(prov, indent=2))
    atomic_write_text(out / "study.json", dumps(study.to_dict(), indent=2))
    for name in ("cells", "numbers"):
        for suffix in (".parquet", ".csv"):
            (out / f"{name}{suffix}").unlink(missing_ok=True)
    if _has_pyarrow():
        cells.to_parquet(out / "cells.parquet", index=False)
        numbers.to_parquet(out / "numbers.parquet", index=False)
    else:
        cells.to_csv(out / "cells.csv", index=False)
        numbers.to_csv(out / "numbers.csv", index=False)
    res = StudyResults(out=out, cells=cells, numbers=numbers, provenance=prov, study=study.to_dict())
    if len(cells):
        atomic_write_text(out / "summary.md", summary_markdown(res))
    if figures and len(cells):
        from .plots import draw_all

        res.figures = draw_all(res, out / "figures")
    return res


def load_results(out) -> StudyResults:
    """Read a results folder written by ``stircasadi study``."""
    pd = _pd()
    out = Path(out)
    if not (out / "provenance.json").is_file():
        raise StudyError(f"{out} holds no study results (no provenance.json); run "
                         "`stircasadi study SPEC --out {out}` first.")
    tables = {}
    for name in ("cells", "numbers"):
        if (out / f"{name}.parquet").is_file():
            tables[name] = pd.read_parquet(out / f"{name}.parquet")
        elif (out / f"{name}.csv").is_file():
            tables[name] = pd.read_csv(out / f"{name}.csv")
        else:
            tables[name] = pd.DataFrame()
    prov = json.loads((out / "provenance.json").read_text())
    study = json.loads((out / "study.json").read_text()) if (out / "study.json").is_file() else {}
    figs = sorted((out / "figures").glob("*.png")) if (out / "figures").is_dir() else []
    return StudyResults(out=out, cells=tables["cells"], numbers=tables["numbers"], provenance=prov,
                        study=study, figures=figs)


def markdown_table(df, floatfmt: str = ".3g") -> str:
    """A pandas DataFrame as a GitHub markdown table (no extra dependency)."""
    def fmt(v):
        if isinstance(v, float):
            return format(v, floatfmt) if v == v else "-"
        return str(v)
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    sep = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body])


_SUMMARY_COLS = ("wall_s", "simulate_s", "estimate_s", "peak_rss_mb", "iterations", "err_position_m",
                 "err_position_m_hidden", "err_normal_deg", "err_albedo", "std_albedo", "max_abs_z",
                 "frac_z_le1", "frac_z_le2", "stir_change_rel", "stir_change_sigma", "sim_s_auto")


def aggregate(res: StudyResults):
    """Per design point (factors except repetition/seed): number of cells, ok / success counts
    and medians of the main measures over repetitions."""
    pd = _pd()
    c = res.cells
    design = res.design_columns() or ["label"] * 0
    cols = [m for m in _SUMMARY_COLS if m in c.columns]
    if not design:
        c = c.assign(_all="all")
        design = ["_all"]
    g = c.groupby(design, dropna=False, sort=False)
    agg = g.agg(cells=("cell", "size"), ok=("status", lambda s: int((s == "ok").sum())))
    if "success" in c.columns:
        agg["success"] = g["success"].apply(lambda s: int((s == True).sum()))  # noqa: E712
    for m in cols:
        agg[m] = g[m].apply(lambda s: pd.to_numeric(s, errors="coerce").median())
    if "hard_verdict" in c.columns:
        agg["verdicts"] = g["hard_verdict"].apply(
            lambda s: ", ".join(f"{k} {v}" for k, v in s.value_counts().items()))
    if "worst_unflagged" in c.columns:
        agg["worst (first cell)"] = g["worst_unflagged"].first()
    return agg.reset_index()


def summary_markdown(res: StudyResults) -> str:
    p = res.provenance
    lines = [f"# {res.study.get('name')}", "", res.study.get("description", ""), "",
             f"stircasadi {p['version']} ({p.get('commit') or 'no git'}), {p['date'][:19]} UTC, "
             f"{p['machine']['node']} ({p['machine']['cpu_count']} CPUs); {p['run'].get('mode')}; "
             f"wall {p['run'].get('wall_s', float('nan')):.1f} s; {len(res.cells)} cells", "",
             "Medians over repetitions per design point:", "", markdown_table(aggregate(res))]
    if "hard_verdict" in res.cells.columns:
        vc = res.cells["hard_verdict"].value_counts()
        lines += ["", "Verdicts (blind_score's rule, MISSED: a hidden patch not placed, unflagged): "
                  + ", ".join(f"{k} {v}" for k, v in vc.items())]
    return "\n".join(lines) + "\n"
