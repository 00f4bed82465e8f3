"""The candidate filter on synthetic streams: spill and memory against N, T and B, beside issue 26's bound.

    python bench/spill_sim.py                         # the grid up to 10^8 points; a table on stdout
    python bench/spill_sim.py --max-n 1e7 --json bench/out/spill_sim.json --plot bench/spill_sim.png
    python bench/spill_sim.py --no-widen              # heaps never widen: the levels alone past width 16
    python bench/spill_sim.py --render bench/out/spill_sim_*.json --plot bench/spill_sim.png
    python bench/spill_sim.py --case 1e10,3000,0.01 --case 1e9,16777216,0.01 --json bench/out/spill_sim_1e10.json

Each case feeds ``core.candidates.CandidateFilter`` (the filter and the numba kernel pass one runs) with
chunks of 8-bit colors and consecutive ids: no file, no decode. B distinct random 24-bit colors of equal
expected size, in random order, or sorted (``--order sorted``: every bin arrives at once, most of them late).
It counts the candidates (the spill) and reads the filter's memory (dense table, heaps, levels), beside the
bound 2 T (1 + ln(N / T)) (never above N) and T (1 + ln(N / T)), about what exact per-bin heaps spill.
``tests/test_one_read.py`` runs a small grid of the same (seconds).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from prism_stream.core import candidates as cand_mod  # noqa: E402
from prism_stream.core.kernels import loop_channels  # noqa: E402
from prism_stream.core.bins import BinSpec  # noqa: E402
from prism_stream.core.quotas import Options  # noqa: E402
from prism_stream.run import tempspace  # noqa: E402
from prism_stream.run.spill import Spill, compact_mark  # noqa: E402

CHUNK = 1 << 20


def bound(n: int, t: int) -> float:
    return min(n, 2 * t * (1 + math.log(n / t))) if t else 0.0


def filter_bytes(f) -> int:
    arrays = [f.dense, f.ge, f.pool, f.fill, f.roots, f.slot_key, f.level, f.below]
    return int(sum(a.nbytes for a in arrays))


class _Source:
    """What a Spill of the index alone asks of a source."""
    ordinal = 0

    @staticmethod
    def spill_state(chunk, at):
        return None


def simulate(n: int, bins: int, ratio: float | None = None, k: int | None = None, order: str = "random",
             seed: int = 0, compact: bool = True) -> dict:
    """Spill and memory of one stream of ``n`` points over ``bins`` colors.

    ``compact``: the candidates go to a spill of the index alone (``run.spill.Spill(records=False)``, in a
    temporary folder) compacted at the engine's mark, as a run's are: ``spill`` is what is left at the end
    (pass two's read), ``peak`` the most it held, ``written`` every candidate admitted."""
    rng = np.random.default_rng(seed)
    palette = np.sort(rng.choice(1 << 24, size=bins, replace=False)).astype(np.uint32)
    options = Options(ratio=ratio, seed=seed) if k is None else Options(k=k, seed=seed)
    f = cand_mod.CandidateFilter(BinSpec("rgb", 0), options, n)
    spilled = 0
    peak = 0
    folder = tempfile.TemporaryDirectory(prefix="spill_sim-")
    spill = Spill(folder.name, records=False) if compact else None
    mark = compact_mark(tempspace.spill_bound(n, tempspace.target_bound(options, n)))
    if spill is not None:
        spill.begin_source(_Source)
        spill.limit(mark)
    t0 = time.perf_counter()
    for a in range(0, n, CHUNK):
        m = min(CHUNK, n - a)
        if order == "sorted":  # bin b holds points [b n / B, (b + 1) n / B): each bin's points come together
            idx = (np.arange(a, a + m, dtype=np.int64) * bins) // n
        else:
            idx = rng.integers(0, bins, m)
        c = palette[idx]
        r, g, b = (c >> 16).astype(np.uint8), ((c >> 8) & 255).astype(np.uint8), (c & 255).astype(np.uint8)
        keys, cand = f.chunk(*loop_channels(r, g, b), 0, a, False)
        spilled += int(cand.sum())
        peak = max(peak, filter_bytes(f))
        if spill is not None:
            spill.add(None, keys, cand, a, f)
    if f.target is not None:
        t = f.target
    else:  # --k: what the run keeps, sum of min(n_b, k), stands for T
        counts = f.counts()
        t = int(np.minimum(counts[counts > 0], k).sum())
    written, held, left, compactions = spilled, spilled, spilled, 0
    if spill is not None:
        written, held, left, compactions = spill.admitted, spill.peak, spill.size, spill.compactions
        spill.close()
        folder.cleanup()
    out = {"n": n, "bins": bins, "ratio": ratio, "k": k, "order": order, "target": t, "spill": left,
           "peak": held, "written": written, "compactions": compactions, "spill_share": left / n,
           "filter_mib": round(peak / 2**20, 1), "seconds": round(time.perf_counter() - t0, 2),
           "width": int(f.width), "slots": int(f.state[0]), "mark": mark, "compacting": spill is not None}
    if spill is None:  # counted only: the engine's spill compacts when it would reach the mark, so below it (every
        # add then below it too) this count is exactly what a compacting run holds; at or past it, it is not
        out["as_engine"] = spilled < mark
    if t:
        out["bound"] = bound(n, t)
        out["heaps_expected"] = min(n, t * (1 + math.log(n / t)))
        out["within"] = held <= out["bound"]
    return out


def grid(max_n: float, orders, min_n: float = 0) -> list[tuple]:
    cases = []
    for n in (10**5, 10**6, 10**7, 10**8, 10**9, 10**10):
        if n > max_n or n < min_n:
            continue
        for bins in (1, 100, 3_000, 10_000, 200_000):
            if bins > n // 4:
                continue
            for ratio in (1e-4, 1e-3, 0.01, 0.05, 0.2, 0.5):
                if round(ratio * n) < 1:
                    continue
                for order in orders:
                    cases.append((n, bins, ratio, order, None))
            for k in (1, 16, 260, 5000):  # --k: what the run keeps, sum of min(n_b, k), stands for T
                if "random" in orders:
                    cases.append((n, bins, None, "random", k))
    return cases


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--max-n", type=float, default=1e8)
    ap.add_argument("--min-n", type=float, default=0, help="the grid's sizes from this one (a larger grid in parts)")
    ap.add_argument("--order", choices=["random", "sorted", "both"], default="both")
    ap.add_argument("--no-compact", action="store_true", help="the candidates counted only, never compacted (no disk): "
                    "exactly the engine's spill while the count stays below the compaction mark (as_engine)")
    ap.add_argument("--no-widen", action="store_true", help="heaps never widen (WIDEN_BYTES = 0)")
    ap.add_argument("--json", help="write every case here")
    ap.add_argument("--plot", help="a PNG of spill / T(1 + ln(N/T)) against N, the bound drawn at 2")
    ap.add_argument("--render", nargs="+", metavar="JSON",
                    help="only draw --plot from saved --json files (a case again in a later file replaces it)")
    ap.add_argument("--case", action="append", metavar="N,B,RATIO[,ORDER]",
                    help="run this case instead of the grid (repeatable), e.g. 1e10,3000,0.01; RATIO k260: --k 260")
    a = ap.parse_args()
    if a.render:  # a case given again in a later file (a rerun) replaces the earlier row
        rows = {(r["n"], r["bins"], r["ratio"], r.get("k"), r["order"]): r
                for f in a.render for r in json.loads(Path(f).read_text())["cases"]}
        plot(list(rows.values()), a.plot or "spill_sim.png")
        return
    if a.no_widen:
        cand_mod.WIDEN_BYTES = 0
    orders = ("random", "sorted") if a.order == "both" else (a.order,)
    rows = []
    print(f"{'N':>12} {'B':>8} {'ratio':>7} {'order':>7} {'T':>11} {'written':>12} {'peak':>12} {'left':>12} "
          f"{'cpt':>4} {'/heaps':>7} {'peak/bd':>7} {'wr/bd':>7} {'MiB':>6} {'s':>6}")
    cases = grid(a.max_n, orders, a.min_n)
    if a.case:
        cases = []
        for c in a.case:
            parts = c.split(",")
            ratio, k = (None, int(parts[2][1:])) if parts[2].startswith("k") else (float(parts[2]), None)
            cases.append((int(float(parts[0])), int(float(parts[1])), ratio, parts[3] if len(parts) > 3 else "random",
                          k))
    for n, bins, ratio, order, k in cases:
        row = simulate(n, bins, ratio=ratio, order=order, k=k, compact=not a.no_compact)
        rows.append(row)
        what = f"{ratio:g}" if k is None else f"k {k}"
        print(f"{n:>12,} {bins:>8,} {what:>7} {order:>7} {row['target']:>11,} {row['written']:>12,} "
              f"{row['peak']:>12,} {row['spill']:>12,} {row['compactions']:>4} "
              f"{row['peak'] / row['heaps_expected']:>7.2f} {row['peak'] / row['bound']:>7.2f} "
              f"{row['written'] / row['bound']:>7.2f} {row['filter_mib']:>6} {row['seconds']:>6}", flush=True)
        if a.json:  # after every case: a grid of hours keeps what it ran
            Path(a.json).parent.mkdir(parents=True, exist_ok=True)
            Path(a.json).write_text(json.dumps({"no_widen": a.no_widen, "cases": rows}, indent=1))
    off = [r for r in rows if r.get("as_engine") is False]
    if off:
        print(f"{len(off)} counted-only cases reached the compaction mark: not the engine's spill, "
              "rerun them compacting")
    missed = [r for r in rows if not r["within"]]
    print(f"{len(rows)} cases, {len(missed)} held more than the bound at once; largest peak / bound "
          f"{max(r['peak'] / r['bound'] for r in rows):.2f}, written / bound "
          f"{max(r['written'] / r['bound'] for r in rows):.2f}"
          f"; largest filter memory "
          f"{max(r['filter_mib'] for r in rows)} MiB")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"no_widen": a.no_widen, "cases": rows}, indent=1))
    if a.plot:
        plot(rows, a.plot, a.no_widen)


def plot(rows: list, path: str, no_widen: bool = False) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    ks = [r for r in rows if r.get("k") is not None and r.get("target")]
    if ks:
        ax.scatter([r["n"] * 0.87 for r in ks], [r.get("peak", r["spill"]) / r["heaps_expected"] for r in ks], s=18,
                   marker="^", color="black", label="--k 1, 16, 260, 5000 (drawn at 0.87 N)")
    for i, ratio in enumerate(sorted({r["ratio"] for r in rows if r["ratio"] is not None})):
        for order, marker, shift in (("random", "o", 1.0), ("sorted", "x", 1.15)):
            pts = [r for r in rows if r["ratio"] == ratio and r["order"] == order]
            if pts:
                ax.scatter([r["n"] * shift for r in pts],
                           [r.get("peak", r["spill"]) / r["heaps_expected"] for r in pts], s=16, marker=marker,
                           color=colors[i % len(colors)],
                           label=f"ratio {ratio:g}" if order == "random" else None)
    ax.axhline(2, color="red", lw=1, label="bound: 2 T (1 + ln(N/T))")
    ax.set_xscale("log")
    ax.set_xlabel("N (points); o: random order, x: sorted (each color at once), drawn at 1.15 N")
    ax.set_ylabel("most candidates held at once / T (1 + ln(N/T))")
    big = sorted({r["n"] for r in rows if r["bins"] > 200_000})
    ax.set_title("candidate spill, every B from 1 to 200,000" + (" (2^24 at N = " + ", ".join(f"{n:.0e}" for n in big)
                                                                  + ")" if big else "")
                 + (" (heaps never widen)" if no_widen else ""))
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)

if __name__ == "__main__":
    main()
