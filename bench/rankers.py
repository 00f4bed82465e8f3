"""The two rankers side by side: numpy's in-memory sorts against DuckDB's spilling window functions.

    python bench/rankers.py --sizes 1M 4M 16M 64M --repeats 3

Each (ranker, size) runs in its own process under ``/usr/bin/time -v``:
n points spread over 2^20 bins (bin place and 64-bit priority drawn at
random, as a sample's points are), ranked by
:func:`prism_stream.core.ranks.rank_sample` or
:func:`~prism_stream.engines.ranking.rank_sample_duckdb` (1 GB memory limit, one
thread, spilling to bench/out/tmp). Median wall time and peak RSS go to
bench/RESULTS_RANK.md (appended under its own heading) and bench/out/rankers-<date>.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

BINS = 1 << 20


def one(ranker: str, n: int) -> dict:
    import time

    import numpy as np

    from prism_stream.core.ranks import rank_sample
    from prism_stream.engines.ranking import rank_sample_duckdb

    rng = np.random.default_rng(1)
    place = rng.integers(0, BINS, n, dtype=np.uint32)
    priority = rng.integers(0, 1 << 63, n, dtype=np.uint64)
    t = time.perf_counter()
    if ranker == "numpy":
        ranks = rank_sample(place, priority, BINS)
        check = int(ranks[-1])
    else:
        from run import TMP

        TMP.mkdir(parents=True, exist_ok=True)
        step = 1 << 20
        check = 0
        for r in rank_sample_duckdb(lambda: ((place[a:a + step], priority[a:a + step]) for a in range(0, n, step)),
                                    str(TMP)):
            check = int(r[-1]) if len(r) else check
    return {"seconds": time.perf_counter() - t, "last_rank": check}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["1M", "4M", "16M", "64M"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--one", nargs=2, metavar=("RANKER", "N"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.one:
        print(json.dumps(one(a.one[0], int(a.one[1]))))
        return 0
    import make_data
    from run import OUT, PY, machine, measure

    rows = []
    for size in a.sizes:
        n = make_data.parse_size(size)
        for ranker in ("numpy", "duckdb"):
            runs = [measure([PY, __file__, "--one", ranker, str(n)]) for _ in range(a.repeats)]
            rows.append({"size": size, "ranker": ranker, "median_s": statistics.median(r["wall"] for r in runs),
                         "inner_median_s": statistics.median(r["report"]["seconds"] for r in runs),
                         "peak_rss_mib": max(r["rss_mib"] for r in runs), "load1": [r["load1"] for r in runs]})
            print(rows[-1], flush=True)
    m = machine()
    result = {"machine": m, "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"), "rows": rows,
              "argv": sys.argv}
    (OUT / f"rankers-{dt.datetime.now():%Y%m%d-%H%M%S}.json").write_text(json.dumps(result, indent=1))
    lines = ["", "## The two rankers: numpy in memory against DuckDB spilling", "",
             f"`python bench/rankers.py {' '.join(sys.argv[1:])}` on {m['cpu']}, {m['cores']} cores, "
             f"{m['ram_gib']} GiB, engine {m['git']}, {result['date']}: n points over 2^20 bins, each ranker its own "
             "process; median of the ranking itself (inner), of the whole process (wall), largest peak RSS.", "",
             "| points | ranker | inner median s | wall median s | peak RSS MiB | load |",
             "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r['size']} | {r['ranker']} | {r['inner_median_s']:.2f} | {r['median_s']:.2f} | "
              f"{r['peak_rss_mib']:.0f} | {', '.join(f'{x:.1f}' for x in r['load1'])} |" for r in rows]
    with open(HERE / "RESULTS_RANK.md", "a") as f:
        f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
