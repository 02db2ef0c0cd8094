#!/usr/bin/env bash
# The GPU checks, run on the device machine (about 5 minutes):
#   scripts/device_prepare.sh                       # here, once per session (wheels, garment cache)
#   run(command="bash scripts/device_check.sh", carry=[".whl", ".devcache"], timeout_s=540)
# 1. the CUDA tests (tests/test_cuda.py: training, validation, checkpoints and rollouts on the GPU against the CPU);
# 2. bench/device_speed.py on the GPU and on 2 CPU threads of that machine (rollout ms/frame, training steps/s).
# Everything it prints also lands in $OUT (gpu.txt, pytest.log, device_speed_*.json), which comes back.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/smln_device_out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 SMLN_CACHE_DIR="$PWD/.devcache"
if [ "${SKIP_WHEELS:-0}" != 1 ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || { echo "wheels did not install: run scripts/device_prepare.sh here and carry .whl" >&2; exit 1; }
  export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
fi
DEVICE=${DEVICE:-cuda}
(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true) | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())" | tee -a "$OUT/gpu.txt"
status=0
timeout 300 python3 -m pytest -q -p no:cacheprovider -rs tests/test_cuda.py 2>&1 | tee "$OUT/pytest.log"
[ "${PIPESTATUS[0]}" = 0 ] || status=1
for dev in "$DEVICE" cpu; do
  timeout 200 python3 bench/device_speed.py --device "$dev" --threads 2 --train-seconds 45 \
    --json "$OUT/device_speed_$dev.json" || status=1
done
exit $status
