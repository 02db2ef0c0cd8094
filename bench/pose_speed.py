"""Time to parse, retarget and pose a 300-frame clip on the body (issue target: < 1 s on 2 CPU cores).

    python bench/pose_speed.py [--clip 09_12_navigate_fwd_back_sideways] [--frames 300] [--repeats 5] [--json OUT]

Prints the median of ``--repeats`` runs of each stage: BVH parse (+ validation), retarget + 30 fps resampling,
posing (forward kinematics + linear blend skinning of the 12,272-vertex body) and floor alignment.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

from smln.body import load_body
from smln.geometry import set_threads
from smln.motion import load_bvh, pose_sequence, retarget
from smln.motion.library import clip_path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clip", default="09_12_navigate_fwd_back_sideways")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json")
    a = p.parse_args()
    set_threads(a.threads)
    body = load_body()
    times: dict[str, list[float]] = {"parse": [], "retarget": [], "pose": [], "total": []}
    for _ in range(a.repeats):
        t0 = time.perf_counter()
        clip = load_bvh(clip_path(a.clip))
        t1 = time.perf_counter()
        motion = retarget(clip, body)
        motion.world_orientations = motion.world_orientations[: a.frames]
        motion.root_positions = motion.root_positions[: a.frames]
        t2 = time.perf_counter()
        seq = pose_sequence(body, motion)
        t3 = time.perf_counter()
        for k, v in zip(times, (t1 - t0, t2 - t1, t3 - t2, t3 - t0), strict=True):
            times[k].append(v)
    out = {k: round(statistics.median(v), 4) for k, v in times.items()}
    out.update(clip=a.clip, frames=seq.num_frames, vertices=int(seq.vertices.shape[1]), threads=a.threads,
               load_avg=os.getloadavg()[0], note="whole clip parsed and retargeted; first `frames` frames posed")
    print(json.dumps(out, indent=1))
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
