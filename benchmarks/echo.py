"""Is the late return of the Stanford 40 cm charts their own interreflection echo?

    python benchmarks/echo.py [--block 16] [--files data_resolution_chart_40cm,data_dot_chart_40cm]

The surface fit of the resolution chart leaves an "unexplained return" at 0.84-0.85 m, about
twice the chart's 0.406 m (BENCHMARKS.md, "Hidden surfaces"). A confocal scan of a chart that
sends light back toward where it came from holds a path wall P -> chart -> P -> chart -> P: the
light the chart returns to P is scattered by the wall at P toward the chart again. Its range
(path / 2, the files being rectified to the wall) is then the sum of two third-bounce ranges
from the same P, so the echo of scan point P is the self-convolution (in range) of P's own
third-bounce return, times one factor for the whole scan. That prediction uses the data only,
no model of the chart.

For each block of ``--block`` x ``--block`` scan points (summed; a 64 ps moving average): the
main return m (range lo..hi, minus the level just before it) and the late part of the trace
(range 2 lo..2 hi - 0.1, minus a cubic through the trace beside it), the prediction m * m (the
same cubic removal). One least-squares factor kappa for all blocks; printed: the fraction of the
late part's variance it explains (R2), the same with the prediction shifted in range (the
response enters m * m twice and the data once: its tail moves m * m later than the echo; a
return at a fixed place in the room would not follow the blocks' own ranges at all), and with each
block's prediction taken from the block half the scan away (the control). Writes
``benchmarks/results/echo.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stircasadi.datasets import data_dir  # noqa: E402

BIN_S = 4e-12        # the release's bin (NOTES.md)
C = 299_792_458.0


class Blocks:
    """A scan cut into ``block`` x ``block`` blocks once: per block the late part of the data
    (``E``) and the main return's self-convolution (``auto``), with the range axis and masks."""

    def __init__(self, rect: np.ndarray, block: int, lo: float, hi: float):
        rect = rect.astype(np.float64)
        rect[:, :, :600] = 0.0               # the wall's own return (the authors' gate)
        self.dr = BIN_S * C / 2.0
        r = self.r = np.arange(rect.shape[2]) * self.dr
        k = np.ones(16) / 16.0
        side = self.side = np.zeros(r.size, bool)
        side |= (r > 2 * lo - 0.1) & (r < 2 * lo)
        side |= (r > 2 * hi - 0.1) & (r < 2 * hi + 0.1)
        late = self.late = (r > 2 * lo) & (r < 2 * hi - 0.1)
        self.n = rect.shape[0] // block
        self.E, self.auto = [], []
        for i in range(self.n):
            for j in range(self.n):
                s = np.convolve(rect[i * block:(i + 1) * block, j * block:(j + 1) * block].sum((0, 1)), k, "same")
                base = np.median(s[(r > lo - 0.06) & (r < lo - 0.01)])
                m = np.where((r > lo) & (r < hi), s - base, 0.0)
                self.auto.append(np.convolve(m, m)[:r.size])
                self.E.append(s[late] - np.polyval(np.polyfit(r[side], s[side], 3), r[late]))

    def late_parts(self, shift_m: float = 0.0, swap: bool = False):
        """(late part of the data, prediction) over all blocks, concatenated; ``shift_m``: the
        prediction moved in range; ``swap``: each block's prediction from the block half the scan
        away (the control: an echo of its own return?)."""
        r, side, late, n = self.r, self.side, self.late, self.n
        shift = int(round(shift_m / self.dr))
        P = []
        for a in self.auto:
            auto = np.roll(a, shift)
            P.append(auto[late] - np.polyval(np.polyfit(r[side], auto[side], 3), r[late]))
        if swap:       # block (i, j) against block ((i + n/2) mod n, (j + n/2) mod n)
            idx = np.arange(n * n).reshape(n, n)
            P = [P[q] for q in np.roll(idx, (n // 2, n // 2), axis=(0, 1)).ravel()]
        return np.concatenate(self.E), np.concatenate(P)


def fit(E, P):
    kappa = float(P @ E / (P @ P))
    res = E - kappa * P
    return kappa, float(1.0 - res @ res / (E @ E))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--block", type=int, default=16)
    ap.add_argument("--files", default="data_resolution_chart_40cm,data_dot_chart_40cm")
    ap.add_argument("--range", default="0.36,0.62", help="the main return's range lo,hi (m)")
    a = ap.parse_args(argv)
    from scipy.io import loadmat

    lo, hi = (float(x) for x in a.range.split(","))
    rows = []
    print(f"{'file':32s} {'shift m':>8s} {'kappa':>10s} {'R2':>6s}")
    for name in [f for f in a.files.split(",") if f]:
        path = data_dir() / "otoole2018_confocal" / f"{name}.mat"
        if not path.exists():
            print(f"{name}: absent ({path}); skipped")
            continue
        blocks = Blocks(loadmat(path)["rect_data"], a.block, lo, hi)
        for sh, swap in ((0.0, False), (-0.03, False), (-0.015, False), (0.015, False), (0.03, False),
                         (0.0, True), (-0.015, True)):
            kappa, r2 = fit(*blocks.late_parts(sh, swap))
            rows.append({"file": name, "block": a.block, "shift_m": sh, "other_block": swap, "kappa": kappa, "r2": r2})
            print(f"{name:32s} {sh:8.3f} {kappa:10.3e} {r2:6.3f}" + ("  (each block against another's return)" if swap else ""))
    out = ROOT / "benchmarks" / "results" / "echo.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    print(f"written {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
