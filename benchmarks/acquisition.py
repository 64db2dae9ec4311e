"""Capture files before and after compression, and the cost of the crash-proof capture journal.

Files: each capture is written uncompressed (float64, contiguous: the layout before) and as the
package writes it now (one trace per chunk; gzip 4 + shuffle where that saves >= 25 %), then read back
whole and trace by trace (200 random traces). Captures: a real confocal scan (O'Toole et al.
2018 ``data_s_u.mat``, imported) and ``three_planes`` simulated with its sensor noise.

Journal: an emulated 3-patch counter rig captured with ``acquire`` (every row fsync'ed in the
journal, then assembled) against the same rows written straight into a Capture.

    python benchmarks/acquisition.py
Writes benchmarks/results/acquisition.json.
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))


def _old_write(cap, path) -> None:
    """The layout before compression: every dataset contiguous float64."""
    import h5py

    from stircasadi.capture_io import _write_header

    with h5py.File(path, "w") as f:
        _write_header(f, cap)
        name = "stir" if cap.stir is not None else "traces"
        f.create_dataset(name, data=getattr(cap, name))


def _measure(cap, folder: Path, label: str) -> list[dict]:
    import h5py

    from stircasadi.capture import Capture

    rows = []
    name = "stir" if cap.stir is not None else "traces"
    data = getattr(cap, name)
    rng = np.random.default_rng(0)
    flat = data.reshape(-1, data.shape[-1])
    picks = rng.integers(0, flat.shape[0], 200)
    for layout, write in (("uncompressed", _old_write), ("package now", lambda c, p: c.write(p))):
        path = folder / f"{label}-{layout}.h5"
        t0 = time.perf_counter()
        write(cap, path)
        t_write = time.perf_counter() - t0
        t0 = time.perf_counter()
        back = Capture.read(path)
        t_read = time.perf_counter() - t0
        assert np.array_equal(getattr(back, name), data)
        t0 = time.perf_counter()
        with h5py.File(path) as f:
            ds = f[name]
            for k in picks:
                idx = np.unravel_index(int(k), data.shape[:-1])
                _ = ds[idx]
        t_trace = (time.perf_counter() - t0) / len(picks)
        rows.append({"capture": label, "layout": layout, "shape": list(data.shape),
                     "size_MB": path.stat().st_size / 1e6, "write_s": t_write, "read_s": t_read,
                     "trace_read_ms": 1e3 * t_trace})
    return rows


def _journal_cost(folder: Path) -> dict:
    from stircasadi.acquisition.cli import main

    t0 = time.perf_counter()
    rc = main(["acquire", "--emulate", "three_patch", "--out", str(folder / "j.h5"), "--shots", "1000",
               "--quiet", "--timeout", "1"])
    assert rc == 0
    return {"acquire_three_patch_s": time.perf_counter() - t0}


def main() -> None:
    from stircasadi.datasets import data_dir

    res = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        real = data_dir() / "otoole2018_confocal" / "data_s_u.mat"
        if real.exists():
            from stircasadi.acquisition.importers import import_file
            res += _measure(import_file(real), folder, "data_s_u (real)")
        else:
            print(f"skipped the real scan: {real} not found")
        from stircasadi.cli import _simulate_problem
        _, _, _, cap = _simulate_problem("three_planes")
        res += _measure(cap, folder, "three_planes (simulated)")
        journal = _journal_cost(folder)
    print(f"{'capture':26s} {'layout':13s} {'shape':18s} {'MB':>8s} {'write s':>8s} {'read s':>8s} {'trace ms':>9s}")
    for r in res:
        print(f"{r['capture']:26s} {r['layout']:13s} {str(tuple(r['shape'])):18s} {r['size_MB']:8.2f} "
              f"{r['write_s']:8.3f} {r['read_s']:8.3f} {r['trace_read_ms']:9.3f}")
    print(f"acquire --emulate three_patch (journal + assembly, 3 rows): {journal['acquire_three_patch_s']:.2f} s")
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "acquisition.json").write_text(json.dumps({"files": res, "journal": journal}, indent=2))
    print(f"wrote {HERE / 'results' / 'acquisition.json'}")


if __name__ == "__main__":
    main()
