#!/usr/bin/env bash
# Prepare, on this machine, what scripts/device_check.sh needs on the GPU machine (device tool), which has
# PyTorch, numpy, scipy, safetensors, tqdm, matplotlib and pytest but not smln's other dependencies, and no network:
#   .whl/       wheels for CPython 3.12 x86-64 of pykdtree, trimesh and pybvh (about 1.5 MB)
#   .devcache/  the garment cache (SMLN_CACHE_DIR) of the outfits the check uses, so that gpytoolbox (13 MB, used
#               only to build garments) need not travel
# Both are ignored by git (.git/info/exclude) and travel through the device tool's `carry`:
#   scripts/device_prepare.sh
#   run(command="bash scripts/device_check.sh", carry=[".whl", ".devcache"], timeout_s=540)
# The repository's files must stay under the tool's 64 MiB (tests/test_repository_size.py).
set -euo pipefail
cd "$(dirname "$0")/.."
for p in /.whl/ /.devcache/; do
  grep -qxF "$p" .git/info/exclude 2>/dev/null || echo "$p" >> .git/info/exclude
done
rm -rf .whl && mkdir -p .whl
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  -d .whl pykdtree==1.4.3 trimesh==5.2.0 pybvh==0.9.0
SMLN_CACHE_DIR="$PWD/.devcache" python3 - <<'PY'
import json

from smln.data_sampling import outfit_names
from smln.garments import build_outfit

shapes = json.load(open("docs/results/r27_config.json"))["shapes"]
built = 0
for outfit in outfit_names("train"):  # the training outfits at 3.5 cm on every training shape
    for shape in shapes:
        build_outfit(outfit, shape=shape, edge_length=0.035)
        built += 1
for edge in (0.035, 0.02):  # the rollout checks and bench/device_speed.py
    build_outfit("tshirt_jacket", shape="female_average", edge_length=edge)
    built += 1
print(f"garment cache: {built} outfits in .devcache")
PY
rm -rf .devcache/motions  # unpacked clips (22 MB): the GPU machine unpacks its own from the .bvh.gz files
du -sh .whl .devcache
