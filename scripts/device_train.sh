#!/usr/bin/env bash
# A training run on the GPU machine, NPROC processes sharing its one GPU (DDP over gloo; each process does its
# CPU-side work, KD-tree queries and graph building, on its own core), for MINUTES minutes:
#   scripts/device_prepare.sh          # here, once per session
#   run(command="NPROC=8 MINUTES=6 bash scripts/device_train.sh --config docs/results/r27_config.json \
#       --variant full --init-from checkpoints/full --lr-restart --lr 1e-5", carry=[".whl", ".devcache"],
#       timeout_s=MINUTES*60+180)
# The arguments are `smln train`'s (not --out, --minutes, --device). The run's log.csv, loss.png, config.json,
# last and best checkpoints and train_state.pt come back in $OUT; `smln train --resume --out DIR` continues it here
# on the CPU (rank 0's episode and noise streams; the other ranks' are not saved). DEVICE (default cuda:0) and
# BACKEND (default gloo) override; SKIP_WHEELS=1 where smln's dependencies are installed.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/smln_device_out}
NPROC=${NPROC:-8}
MINUTES=${MINUTES:-5}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 SMLN_CACHE_DIR="$PWD/.devcache" OMP_NUM_THREADS=1
if [ "${SKIP_WHEELS:-0}" != 1 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
fi
run=/tmp/smln_device_run
rm -rf "$run"
python3 -m torch.distributed.run --standalone --nproc_per_node="$NPROC" -m smln.train --out "$run" \
  --minutes "$MINUTES" --device "${DEVICE:-cuda:0}" --dist-backend "${BACKEND:-gloo}" --threads 1 "$@" 2>&1 \
  | tr '\r' '\n' | grep -v "^ *$" | awk 'NR % 50 == 1' || true
for f in log.csv loss.png config.json last.json last.safetensors best.json best.safetensors train_state.pt; do
  [ -f "$run/$f" ] && cp "$run/$f" "$OUT/"
done
python3 - "$run/log.csv" <<'PY'
import csv, sys
rows = [r for r in csv.DictReader(open(sys.argv[1])) if r.get("total")]
if len(rows) > 1:
    (a, b) = rows[0], rows[-1]
    steps, wall = float(b["step"]) - float(a["step"]), float(b["wall_s"]) - float(a["wall_s"])
    print(f"optimiser steps {a['step']} -> {b['step']} in {wall:.0f} s: {steps / max(wall, 1e-9):.2f} steps/s")
PY
