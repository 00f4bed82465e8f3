#!/bin/bash
# Cases of issue 26's grid at N = 10^10 in the simulator, one process a case, niced, each to
# bench/out/spill_sim_1e10_<B>_<ratio or kK>_<order>.json (a case whose JSON exists is skipped: rerun
# after a stop, or with other cases given as arguments: bench/spill_sim_1e10.sh 1e10,3000,0.001,sorted ...).
# Ratios of 0.05 and up are not in the default list: a compacting run keeps the spill's index on disk, up to
# 36 GB at T = 5 x 10^8 sorted (it needed room twice until 2cb303d compacted in place, and its first compaction was
# still reading the index, 30 passes in, after 25 minutes until 7fd3e81 counted the large quotas). SIM_ARGS=--no-compact counts the
# candidates without a spill (no disk): the engine's spill exactly while the count stays below the compaction
# mark, which a random-order case does (its JSON says so: "as_engine").
set -euo pipefail
cd "$(dirname "$0")/.."
py=${PYTHON:-.venv/bin/python}
cases=("$@")
[ ${#cases[@]} -gt 0 ] || cases=(
  1e10,100,0.0001,sorted 1e10,3000,0.001,sorted 1e10,200000,0.0001,sorted 1e10,100,0.001,sorted
  1e10,10000,0.01,sorted 1e10,1,0.01,sorted 1e10,10000,0.0001,sorted 1e10,3000,0.0001,sorted
  1e10,200000,0.001,sorted 1e10,10000,0.001,sorted 1e10,3000,0.01,sorted 1e10,100,0.01,random
  1e10,10000,k5000 1e10,200000,k16 1e10,100,k1)
for c in "${cases[@]}"; do
  tag=$(echo "$c" | cut -d, -f2- | tr ',' '_')
  f=bench/out/spill_sim_1e10_$tag.json
  [ -s "$f" ] && continue
  nice -n 19 "$py" bench/spill_sim.py ${SIM_ARGS:-} --case "$c" --json "$f.part" && mv "$f.part" "$f"
done
