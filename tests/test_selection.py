"""``smln select``: the score, the ranking, the refusal of the test split, and a real two-checkpoint selection."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from smln.evaluate import RunResult
from smln.selection import check_training_split, rank, selection_score

CHECKPOINTS = Path(__file__).parents[1] / "checkpoints"


def _run(method: str, motion: str, frames: int, strain: float, h: float, l: float, fallback: int) -> RunResult:
    metrics = {"num_frames": float(frames), "strain_mean": strain, "h_coll": h, "l_coll": l,
               "fallback_frames": float(fallback), "strain_max_max": 2 * strain}
    for key in ("bend", "collision_loss", "offset_rms", "ms_model", "l_coll_surface", "h_coll_surface"):
        metrics[key] = 0.0
    return RunResult(method, "tshirt_jacket", motion, "train", metrics)


def test_selection_score_is_the_validation_score_with_fallbacks_per_frame():
    row = {"strain_mean": 0.05, "h_coll": 1.0, "l_coll": 2.0, "fallback_frames": 3.0, "frames": 300.0}
    assert selection_score(row) == pytest.approx(0.05 + 0.01 + 0.02 + 0.01)
    assert selection_score({**row, "fallback_frames": 0.0}) == pytest.approx(0.08)
    assert selection_score({**row, "h_coll": math.nan}) == math.inf


def test_rank_weights_scenes_by_frames_and_puts_the_lowest_score_first():
    results = [
        # a: 100 frames at 4 % strain, 1 % / 1 %, then 300 frames at 6 %, 2 % / 3 %, one fallback
        _run("a", "02_01_walk", 100, 0.04, 1.0, 1.0, 0), _run("a", "02_09_swordplay", 300, 0.06, 2.0, 3.0, 1),
        # b: the same scenes, uniformly 5 %, 1.5 % / 2 %, no fallback
        _run("b", "02_01_walk", 100, 0.05, 1.5, 2.0, 0), _run("b", "02_09_swordplay", 300, 0.05, 1.5, 2.0, 0),
    ]
    ranked = rank(results)
    assert [r["checkpoint"] for r in ranked] == ["b", "a"]
    a = next(r for r in ranked if r["checkpoint"] == "a")
    strain, h, l_coll = (0.04 + 3 * 0.06) / 4, (1.0 + 3 * 2.0) / 4, (1.0 + 3 * 3.0) / 4
    assert a["strain_mean"] == pytest.approx(strain) and a["frames"] == 400
    assert a["score"] == pytest.approx(strain + h / 100 + l_coll / 100 + 1 / 400)
    assert ranked[0]["score"] == pytest.approx(0.05 + 0.015 + 0.02)


def test_selection_refuses_the_test_split():
    check_training_split(["tshirt_jacket", "leggings_skirt"], ["02_01_walk", "06_10_dribble_left_turns"])
    with pytest.raises(ValueError, match="'05_01_walk' is not a training clip"):
        check_training_split(["tshirt_jacket"], ["02_01_walk", "05_01_walk"])
    with pytest.raises(ValueError, match="'tanktop_jacket' is not a training outfit"):
        check_training_split(["tanktop_jacket"], ["02_01_walk"])


def test_select_ranks_real_checkpoints_and_writes_the_ranking(tmp_path):
    from smln.selection import main

    full, baseline = CHECKPOINTS / "full", CHECKPOINTS / "baseline"
    if not (full.exists() and baseline.exists()):
        pytest.skip("no shipped checkpoints")
    out = tmp_path / "selection.json"
    ranked = main([str(full), str(baseline), "--outfits", "tshirt_jacket", "--motions", "02_01_walk", "--frames", "5",
                   "--json", str(out)])
    assert {r["checkpoint"] for r in ranked} == {str(full), str(baseline)}
    assert ranked[0]["score"] <= ranked[1]["score"]
    for r in ranked:
        assert r["frames"] == 5 and r["score"] == pytest.approx(selection_score(r))
    written = json.loads(out.read_text())
    assert written["settings"]["motions"] == ["02_01_walk"] and written["settings"]["frames"] == 5
    assert [r["checkpoint"] for r in written["ranking"]] == [r["checkpoint"] for r in ranked]
    with pytest.raises(ValueError, match="given twice"):
        main([str(full), str(full), "--motions", "02_01_walk", "--frames", "5"])
    with pytest.raises(ValueError, match="not a training clip"):
        main([str(full), "--motions", "05_01_walk", "--frames", "5"])
