"""Run a study's cells: serially, on a local Dask cluster sized to the machine, or on a cluster.

When to use
-----------
``run_study(spec, out)`` (``stircasadi study SPEC --out DIR``). Every cell runs
``stircasadi.studies.cell.run_cell`` in its own right (it builds its own scene and model); each
finished record is cached at once (``out/cells/<key>.json``), so an interrupted study resumes
and a rerun skips what is done. A failing cell is recorded with its error and the study goes
on. At the end the tables, provenance and pictures are written (``stircasadi.studies.results``).

Parallelism
-----------
Default: a ``distributed.LocalCluster`` of one single-threaded worker process per CPU core,
on the loopback interface, with BLAS pinned to one thread per worker (``OMP_NUM_THREADS``,
``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS`` = 1, set before the workers start) so workers do
not oversubscribe the cores. ``scheduler="tcp://host:8786"`` uses an existing cluster instead:
start its workers with those variables set and ``--nthreads 1`` (each needs stircasadi
installed). ``workers=0`` (``--serial``) runs in this process.

What it neglects
----------------
A cell that hangs is not timed out (IPOPT and LM have iteration limits); a worker that dies is
retried by Dask and then recorded as failed (``KilledWorker``).
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import os
import time
from dataclasses import dataclass
from pathlib import Path

from ..errors import StudyError
from ..progress import get_logger, progress
from .cache import CellCache, cell_key
from .cell import run_cell
from .spec import Study, load_study

__all__ = ["run_study", "RunSettings", "BLAS_ENV", "local_cluster"]

log = get_logger(__name__)

#: set in every worker before it starts: one BLAS thread per single-threaded worker
BLAS_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@dataclass
class RunSettings:
    """How a study runs (not what it computes: that is the spec)."""

    scheduler: str | None = None
    """Address of a running Dask scheduler (``tcp://host:8786``); None: a LocalCluster."""
    workers: int | None = None
    """LocalCluster size; None: one per CPU core; 0: serial, in this process."""
    retry_failed: bool = False
    """Recompute cached cells whose status is not ``ok``."""
    fresh: bool = False
    """Ignore the cache (recompute every cell; the cache is overwritten)."""
    keep_estimates: bool = False
    """Keep each cell's estimate.json dict in its record."""
    figures: bool = True
    """Draw the pictures at the end."""
    memory_limit: str | None = None
    """Memory of each LocalCluster worker (``"4GB"``); a worker that exceeds it is restarted and
    its cell recorded as failed (``KilledWorker``). None: the machine's memory / workers."""
    cached_only: bool = False
    """Compute nothing: write the tables and pictures of the cells already cached (the others
    are counted as missing in the provenance)."""

    def validate(self) -> "RunSettings":
        if self.workers is not None and (not isinstance(self.workers, int) or self.workers < 0):
            raise StudyError(f"workers must be None (one per core), 0 (serial) or a positive integer; "
                             f"got {self.workers!r}.")
        if self.scheduler is not None and self.workers is not None:
            raise StudyError("Give either scheduler (a running cluster) or workers (a local one), not both.")
        if self.scheduler is not None and "://" not in self.scheduler and ":" not in self.scheduler:
            raise StudyError(f"scheduler must be an address like tcp://host:8786; got {self.scheduler!r}.")
        return self


def default_workers() -> int:
    """One worker per CPU core this process may use, at most one per 1.5 GB of memory."""
    from .._cpus import usable_cpus

    n = usable_cpus()
    try:
        import psutil

        n = min(n, max(1, int(psutil.virtual_memory().total / 1.5e9)))
    except ImportError:
        pass
    return max(1, n)


@contextlib.contextmanager
def local_cluster(n_workers: int, memory_limit: str | None = None):
    """A loopback-only LocalCluster of ``n_workers`` single-threaded processes (BLAS pinned,
    each under ``memory_limit``; a cell that kills its worker is not retried elsewhere)."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise StudyError("Running a study on Dask needs dask[distributed]: pip install "
                         "'stircasadi[studies]' (or run it serially with --serial).") from exc
    for k, v in BLAS_ENV.items():  # inherited by the worker processes
        os.environ.setdefault(k, v)
    with dask.config.set({"distributed.nanny.pre-spawn-environ": dict(BLAS_ENV),
                          "distributed.worker.daemon": False, "logging.distributed": "error",
                          "distributed.scheduler.allowed-failures": 0,
                          # one cell per worker thread at a time: a cell queued on a worker that
                          # another cell kills (its memory limit) would be recorded as failed too
                          "distributed.scheduler.worker-saturation": 1.0}):
        try:
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                   host="127.0.0.1", dashboard_address=None, env=dict(BLAS_ENV),
                                   memory_limit=memory_limit or "auto")
        except RuntimeError as exc:  # "Nanny failed to start": the workers could not spawn
            raise StudyError(
                f"The local Dask workers did not start ({exc}). A script that calls run_study must "
                "guard it with `if __name__ == \"__main__\":` (workers are spawned processes that "
                "import the script); or run serially (workers=0, --serial).") from exc
        client = Client(cluster)
        try:
            yield client
        finally:  # short timeouts: after an interruption the workers may be busy in C code
            client.close(timeout=10)
            cluster.close(timeout=20)


@contextlib.contextmanager
def _remote(address: str):
    try:
        from distributed import Client
    except ImportError as exc:
        raise StudyError("--scheduler needs dask[distributed]: pip install 'stircasadi[studies]'.") from exc
    try:
        client = Client(address, timeout="20s")
    except (OSError, TimeoutError) as exc:
        raise StudyError(f"No Dask scheduler answers at {address} ({exc}). Start one "
                         "(dask scheduler; dask worker ADDRESS --nthreads 1) or leave --scheduler out "
                         "for a local cluster.") from exc
    try:
        yield client
    finally:
        client.close()


class _Tally:
    """Counts and the progress bar: cells done / running / failed."""

    def __init__(self, total: int, cached: int, failed: int, desc: str):
        self.done, self.failed, self.running = cached, failed, 0
        self.bar = progress(total=total, desc=desc, unit="cell", initial=cached)
        self._show()

    def _show(self):
        self.bar.set_postfix_str(f"done {self.done}, running {self.running}, failed {self.failed}",
                                 refresh=True)

    def finished(self, record: dict, running: int):
        self.done += 1
        self.failed += record["status"] in ("failed", "crashed")
        self.running = running
        self.bar.update(1)
        self._show()

    def close(self):
        self.bar.close()


def _failed_record(params: dict, exc: BaseException) -> dict:
    from .. import __version__

    msg = str(exc)
    if type(exc).__name__ == "KilledWorker":
        msg = ("the worker process died while running this cell: most often it exceeded its memory "
               "limit (--memory-limit; the worker log says 'exceeded 95% memory budget'), else a "
               "crash in compiled code. " + msg)
    return {"params": params, "status": "failed", "stage": "worker",
            "error": {"type": type(exc).__name__, "message": msg[:2000], "traceback": ""},
            "measures": {"hard_verdict": "FAILED"}, "numbers": [], "worker": "", "version": __version__}


def run_study(spec, out, size: str | None = None, settings: RunSettings | None = None,
              on_result=None):
    """Run every cell of ``spec`` (a ``Study``, a dict, a spec file or a built-in name) into
    folder ``out``; return the ``StudyResults`` (tables, provenance, pictures).

    ``on_result(key, record)`` is called as each cell finishes (after it is cached); an
    exception it raises (KeyboardInterrupt included) stops the study like Ctrl-C: cached cells
    are kept and partial tables written before it propagates.
    """
    from .results import write_results

    settings = (settings or RunSettings()).validate()
    study = load_study(spec, size=size)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise StudyError(f"--out {out} is a file; give a folder for the study's results.")
    cache = CellCache(out / "cells")
    cells = study.cells()
    keys = [cell_key(c) for c in cells]
    unique = dict(zip(keys, cells))
    todo, cached, cached_failed = [], 0, 0
    for k, c in unique.items():
        rec = None if settings.fresh else cache.get(k)
        if rec is not None and not (settings.retry_failed and rec.get("status") != "ok"):
            cached += 1
            cached_failed += rec.get("status") in ("failed", "crashed")
        else:
            todo.append((k, c))
    started = _dt.datetime.now(_dt.timezone.utc)
    t0 = time.perf_counter()
    mode = "serial" if settings.workers == 0 else (settings.scheduler or
                                                   f"LocalCluster({settings.workers or default_workers()} workers)")
    log.info(f"study {study.name}: {len(unique)} cells, {cached} cached, {len(todo)} to run ({mode})")
    tally = _Tally(len(unique), cached, cached_failed, study.name)
    run_info = {"mode": mode, "n_cells": len(unique), "n_cached": cached, "n_computed": 0,
                "started": started.isoformat(), "interrupted": False, "n_missing": 0}
    if settings.cached_only:
        run_info["mode"] = "cached only"
        run_info["n_missing"] = len(todo)
        todo = []

    def finish(key, rec, running):
        cache.put(key, rec)
        run_info["n_computed"] += 1
        tally.finished(rec, running)
        if on_result is not None:
            on_result(key, rec)

    try:
        if not todo:
            pass
        elif settings.workers == 0:
            for k, c in todo:
                finish(k, run_cell(c, study.sigma_limit, settings.keep_estimates), 0)
        else:
            ctx = _remote(settings.scheduler) if settings.scheduler else local_cluster(
                settings.workers or default_workers(), settings.memory_limit)
            with ctx as client:
                run_info["workers"] = _worker_info(client)
                _run_dask(client, todo, study, settings, finish)
    except BaseException:
        run_info["interrupted"] = True
        raise
    finally:
        tally.close()
        run_info["wall_s"] = time.perf_counter() - t0
        run_info["finished"] = _dt.datetime.now(_dt.timezone.utc).isoformat()
        results = write_results(study, out, keys, cache, run_info, figures=settings.figures and
                                not run_info["interrupted"])
    return results


def _worker_info(client) -> dict:
    try:
        info = client.scheduler_info()
        ws = info.get("workers", {})
        return {"n": len(ws), "threads": sum(w.get("nthreads", 0) for w in ws.values()),
                "hosts": sorted({w.get("host", "") for w in ws.values()})}
    except Exception:  # informative only
        return {}


def _run_dask(client, todo, study, settings, finish):
    from distributed import as_completed

    futures = {}
    for k, c in todo:
        f = client.submit(run_cell, c, study.sigma_limit, settings.keep_estimates,
                          key=f"stircasadi-cell-{k}", pure=False, retries=0)
        futures[f] = (k, c)
    try:
        for f in as_completed(list(futures)):
            k, c = futures[f]
            try:
                rec = f.result()
            except Exception as exc:  # KilledWorker, CommClosedError, ...: the cell is recorded
                rec = _failed_record(c, exc)
            f.release()
            finish(k, rec, _running(client))
    finally:
        pending = [f for f in futures if not f.done()]
        if pending:
            client.cancel(pending)


def _running(client) -> int:
    try:
        return sum(len(v) for v in client.processing().values())
    except Exception:  # informative only
        return 0
