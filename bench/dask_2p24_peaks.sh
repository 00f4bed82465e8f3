#!/bin/bash
# Each process's peak RSS on Dask over 2^24 colors, revisions side by side, interleaved (issue 26).
#
#   bench/dask_2p24_peaks.sh REV [REV ...]
#
# For each of 3 rounds, for --reads two and --reads one, for each revision (a git worktree of it in
# /tmp/wt_REV, made here if missing): bench/peak_by_process.py over the 100M points of
# bench/data/b2p24/e01.parquet and e02.parquet (15.9M distinct colors; bench/equal_bins.py makes e01, e02
# is a copy), --ratio 0.05 --dask local:2. Writes bench/out/dask_2p24_fold_REV_READS_ROUND.json (the
# peaks) and ..._summary.json (the run's --summary: phase seconds, kept rows).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
py=${PYTHON:-$here/.venv/bin/python}
for rev in "$@"; do
  [ -d /tmp/wt_$rev ] || git -C "$here" worktree add -q /tmp/wt_$rev "$rev"
done
for round in 1 2 3; do
  for reads in two one; do
    for rev in "$@"; do
      out=$here/bench/out/dask_2p24_fold_${rev}_${reads}_$round
      (cd /tmp/wt_$rev && PYTHONPATH=/tmp/wt_$rev timeout 900 "$py" "$here/bench/peak_by_process.py" -- \
        "$py" -m prism_stream "$here/bench/data/b2p24/e01.parquet" "$here/bench/data/b2p24/e02.parquet" \
        /tmp/dask_2p24_$rev.parquet --ratio 0.05 --quiet --overwrite --dask local:2 --reads $reads \
        --summary "${out}_summary.json" > "$out.json")
    done
  done
done
