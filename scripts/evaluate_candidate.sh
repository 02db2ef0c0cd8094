#!/usr/bin/env bash
# Evaluate a candidate's three variants on the test clips, as the shipping rule needs (docs/RESULTS.md).
#
#   scripts/evaluate_candidate.sh OUTDIR CKPT_FULL CKPT_NO_REPULSION_LAYER CKPT_BASELINE
#
# Writes OUTDIR/{seen,held}_{full,no_repulsion_layer,baseline}.{json,md}: the seen outfits on the 8 test clips
# (300 frames each) and the held-out outfits on 4 of them (150 frames), at the 3.5 cm training resolution, one
# thread per evaluation, two at a time (about 20 minutes on 2 idle cores). Every variant also gets the
# point-to-triangle metrics (since session 38: Table 3 on the triangles, not only on the vertex test; the full
# model alone had them before, about 9 minutes). Then:  python scripts/shipping_rule.py --seen OUTDIR/seen_*.json \
#   --held OUTDIR/held_*.json --sink-mm MM
set -euo pipefail
if [ $# -ne 4 ]; then
  echo "usage: $0 OUTDIR CKPT_FULL CKPT_NO_REPULSION_LAYER CKPT_BASELINE" >&2
  exit 2
fi
out=$1
mkdir -p "$out"
declare -A ckpt=([full]=$2 [no_repulsion_layer]=$3 [baseline]=$4)
common=(--edge-length 0.035 --threads 1 --no-skinning)
seen=(--outfits tshirt_jacket leggings_skirt tshirt_longsleeve_jacket --motions test --frames 300)
held=(--outfits held_out --motions 05_01_walk 09_06_run 05_11_dance_sideways_steps_pirouette 07_12_brisk_walk
      --frames 150)

one() {  # split variant
  local split=$1 variant=$2
  local -n args=$split
  smln eval --checkpoint "${ckpt[$variant]}" "${args[@]}" "${common[@]}" --surface-metrics \
    --json "$out/${split}_${variant}.json" --markdown "$out/${split}_${variant}.md" > "$out/${split}_${variant}.log" 2>&1
}

# two queues of about equal length (a seen evaluation takes about 2.5 times a held-out one)
( one seen full; one seen no_repulsion_layer ) &
q1=$!
( one seen baseline; one held full; one held no_repulsion_layer; one held baseline ) &
q2=$!
wait $q1 && wait $q2
echo "done: $out"
