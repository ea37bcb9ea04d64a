#!/bin/bash
# experiments/paper.py as N one-thread processes at once on a many-core machine, one OUT between them:
#     bash experiments/paper_shards.sh OUT N [paper.py options, e.g. --budget 150 --runs 3 --seeds 2]
# Each process takes every N-th run of the plan (`--shard K/N`), logs to OUT/shardK.log, and appends to
# OUT/results.jsonl; OUT/paper.md is rewritten from all of them at the end. Seed 2 of docs/paper.md ran
# this way on a lent 16-core machine (docs/training.md, "The paper, re-run").
set -u
out=$1; shards=$2; shift 2
mkdir -p "$out"
export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 MKL_NUM_THREADS=1 PYTHONUNBUFFERED=1
here=$(dirname "$0")
for k in $(seq 0 $((shards - 1))); do
  python3 "$here/paper.py" --out "$out" --shard "$k/$shards" "$@" > "$out/shard$k.log" 2>&1 &
done
wait
python3 "$here/paper.py" --out "$out" --report "$@"
