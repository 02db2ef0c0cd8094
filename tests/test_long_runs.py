"""Long runs with the full checkpoint: a whole test clip with a 2-layer outfit stays sane (issue 9).

Uses ``checkpoints/full`` (the published checkpoint) or the checkpoint named by ``SMLN_LONG_RUN_CHECKPOINT``
(e.g. ``runs/full/last`` while training); skips with the reason when there is none. The sweep over every test
clip x every outfit is ``bench/long_runs.py`` (CPU-heavy); this test runs the shortest test clip, full length,
with two outfits (tops and bottoms), in well under a minute.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

import pytest

from tests.script_loader import load_script

ROOT = Path(__file__).resolve().parent.parent
CHECKPOINT = Path(os.environ.get("SMLN_LONG_RUN_CHECKPOINT", ROOT / "checkpoints" / "full"))
CLIP = "09_06_run"
"""The shortest shipped test clip (36 frames at 30 fps): a run, fast body motion."""


def _bench() -> ModuleType:
    return load_script("bench/long_runs.py")


@pytest.fixture(scope="module")
def model():
    from smln.checkpoint import load_checkpoint

    if not (CHECKPOINT / "card.json").is_file() and not CHECKPOINT.with_suffix(".json").is_file():
        pytest.skip(f"no full checkpoint at {CHECKPOINT} (publish one with scripts/publish_checkpoints.py, or set "
                    "SMLN_LONG_RUN_CHECKPOINT=runs/full/last)")
    m, card = load_checkpoint(CHECKPOINT)
    assert card.get("variant") == "full", f"{CHECKPOINT} is the {card.get('variant')!r} variant, not full"
    return m


def test_long_run_clip_is_a_test_clip() -> None:
    from smln.motion import clip_split

    assert clip_split(CLIP) == "test"


@pytest.mark.slow
@pytest.mark.parametrize("outfit", ["tshirt_jacket", "leggings_skirt"])
def test_full_clip_rollout_stays_sane(model, outfit: str) -> None:
    """Full-length rollout: no NaN, every vertex within the stated bound of the body, every frame either a
    network frame within the rollout's divergence bounds or a flagged fallback identical to skinning."""

    from smln.geometry import set_threads
    from smln.motion import load_body_sequence

    set_threads(1)
    bench = _bench()
    r = bench.long_run(model, outfit, CLIP)
    from smln.body import load_body

    assert r.frames == load_body_sequence(CLIP, load_body("female_average")).num_frames  # the whole clip
    assert r.nan_frames == 0, r
    assert r.max_body_distance < bench.MAX_BODY_DISTANCE, r
    assert r.max_skin_distance <= bench.MAX_SKIN_DISTANCE, r
    assert r.fallback_equals_skinning, r
    assert r.fallback_frames < r.frames, f"every frame fell back to skinning: {r}"
    print(f"\n{outfit} on {CLIP}: {r}")
