"""``smln eval``: the tables of a short real evaluation, with the point-to-triangle collision columns."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

CHECKPOINT = Path(__file__).parents[1] / "checkpoints" / "full"


@pytest.mark.slow
def test_eval_with_surface_metrics(tmp_path):
    from smln.data_sampling import make_scene
    from smln.evaluate import main
    from smln.metrics import surface_h_coll, surface_l_coll

    if not (CHECKPOINT.with_suffix(".safetensors").exists() or CHECKPOINT.exists()):
        pytest.skip("no shipped checkpoint")
    md = tmp_path / "eval.md"
    results = main(["--checkpoint", str(CHECKPOINT), "--outfits", "tshirt_jacket", "--motions", "05_01_walk",
                    "--frames", "6", "--edge-length", "0.035", "--threads", "1", "--surface-metrics",
                    "--markdown", str(md)])
    by_method = {r.method: r for r in results}
    assert set(by_method) == {"full", "skinning"}
    for r in results:
        assert 0.0 <= r.metrics["l_coll_surface"] <= 100.0 and 0.0 <= r.metrics["h_coll_surface"] <= 100.0
        assert len(r.per_frame) == 6
    # the skinning row's per-frame values are the metric functions on the skinned garment
    scene = make_scene("tshirt_jacket", "female_average", "05_01_walk", edge_length=0.035, max_frames=6)
    faces, layers = scene.cloth.faces.numpy(), scene.cloth.layer_index.numpy()
    for t, row in enumerate(by_method["skinning"].per_frame):
        x = scene.skinned[t].numpy()
        assert row["l_coll_surface"] == pytest.approx(surface_l_coll(x, faces, layers))
        assert row["h_coll_surface"] == pytest.approx(
            surface_h_coll(x, scene.body.vertices[t].numpy(), scene.body.faces.numpy()))
    text = md.read_text()
    assert "L-Coll surf. %" in text and "H-Coll surf. %" in text
    full_line = next(line for line in text.splitlines() if line.startswith("| full "))
    cells = [c.strip() for c in full_line.strip("|").split("|")]
    assert float(cells[5]) == pytest.approx(by_method["full"].metrics["l_coll_surface"], abs=0.006)
    assert np.isfinite(float(cells[6]))


def test_eval_divergence_guard_flags(tmp_path):
    """``--max-body-distance``: a 1 mm bound makes every predicted frame fall back to skinning (a jacket is
    centimetres off the body somewhere), the skinned frames 0-1 are kept, and the row's name says which bounds ran;
    a non-positive bound is refused."""
    from smln.evaluate import main

    if not (CHECKPOINT.with_suffix(".safetensors").exists() or CHECKPOINT.exists()):
        pytest.skip("no shipped checkpoint")
    common = ["--checkpoint", str(CHECKPOINT), "--outfits", "tshirt_jacket", "--motions", "05_01_walk", "--frames",
              "5", "--edge-length", "0.035", "--threads", "1", "--no-skinning"]
    (tight,) = main(common + ["--max-body-distance", "0.001"])
    assert tight.method == "full [guard skin 0.4 m, body 0.001 m]"
    assert [r["fallback"] for r in tight.per_frame] == [0.0, 0.0, 1.0, 1.0, 1.0]
    (default,) = main(common)
    assert default.method == "full" and default.metrics["fallback_frames"] == 0.0
    # a 3 cm skinned bound: every predicted frame falls back (the jacket is 3.3-3.9 cm off its skinned place in
    # frames 2-4), unless the guard waits for a symptom (this walk has none: strain 5-6 %, H-Coll 1-3 %) or 6 cm
    tight_skin = common + ["--max-skin-distance", "0.03"]
    (always,) = main(tight_skin)
    assert [r["fallback"] for r in always.per_frame] == [0.0, 0.0, 1.0, 1.0, 1.0]
    (symptomatic,) = main(tight_skin + ["--skin-guard", "symptomatic", "--max-body-distance", "0.45"])
    assert symptomatic.method == "full [guard skin 0.03 m, body 0.45 m] [skin guard symptomatic]"
    assert all(r["fallback"] == 0.0 for r in symptomatic.per_frame)
    with pytest.raises(ValueError, match="--max-skin-distance must be a positive distance"):
        main(common + ["--max-skin-distance", "0"])


def test_markdown_table_marks_missing_surface_metrics_with_a_dash():
    """Rows merged from runs with and without ``--surface-metrics``: the missing cells read "—", not "nan"."""
    from smln.evaluate import markdown_table

    base = {"bend": 0.05, "collision_loss": 6e-6, "l_coll": 1.5, "h_coll": 2.0, "strain_mean": 0.05,
            "strain_max": 0.5, "offset_rms": 0.07, "ms_model": 40.0, "fallback_frames": 3.0, "frames": 100.0}
    text = markdown_table({"full": {**base, "l_coll_surface": 1.234, "h_coll_surface": 0.5},
                           "baseline": {**base, "l_coll_surface": float("nan"), "h_coll_surface": float("nan")}}, "t")
    full, baseline = (next(line for line in text.splitlines() if line.startswith(f"| {m} "))
                      for m in ("full", "baseline"))
    assert "| 1.23 | 0.50 |" in full
    assert "| — | — |" in baseline and "nan" not in text


def test_two_checkpoints_of_one_variant_get_a_row_each(tmp_path):
    """An old and a new ``full`` checkpoint side by side: the second row is named by its path instead of
    overwriting the first; the same path twice is refused."""
    import shutil

    from smln.evaluate import main

    other = tmp_path / "old_full"
    shutil.copytree(CHECKPOINT, other)
    args = ["--outfits", "tshirt_jacket", "--motions", "05_01_walk", "--frames", "4", "--edge-length", "0.035",
            "--threads", "1", "--no-skinning"]
    results = main(["--checkpoint", str(CHECKPOINT), "--checkpoint", str(other), *args])
    assert sorted(r.method for r in results) == ["full", f"full ({other})"]
    with pytest.raises(ValueError, match="more than once"):
        main(["--checkpoint", str(CHECKPOINT), "--checkpoint", str(CHECKPOINT), *args])


def _run_json(method: str, outfit: str, motion: str, frames: float, l_coll: float) -> dict:
    """One run of an ``smln eval --json`` file with round metric values."""
    metrics = {"num_frames": frames, "bend": 0.05, "collision_loss": 6e-6, "l_coll": l_coll, "h_coll": 1.0,
               "strain_mean": 0.05, "strain_max": 0.5, "strain_max_max": 0.5, "offset_rms": 0.07, "ms_model": 30.0,
               "fallback": 0.0, "fallback_frames": 0.0, "exploded": 0.0}
    return {"method": method, "outfit": outfit, "motion": motion, "split": "train", "metrics": metrics}


def test_from_json_merges_files_frame_weighted_and_refuses_duplicates(tmp_path):
    """``--from-json A B``: the runs of both files make one table; a method's row is the frame-weighted mean
    of its runs (100 frames at 1 % and 300 at 3 % read 2.50 %); a run present in two files is refused."""
    import json

    from smln.evaluate import main

    full = tmp_path / "full.json"
    full.write_text(json.dumps([_run_json("full", "tshirt_jacket", "05_01_walk", 100, 1.0),
                                _run_json("full", "tshirt_jacket", "09_06_run", 300, 3.0)]))
    skin = tmp_path / "skinning.json"
    skin.write_text(json.dumps([_run_json("skinning", "tshirt_jacket", "05_01_walk", 100, 4.0)]))
    out = tmp_path / "t.md"
    results = main(["--from-json", str(full), str(skin), "--markdown", str(out)])
    assert [r.method for r in results] == ["full", "full", "skinning"]
    rows = {line.split("|")[1].strip(): line.split("|") for line in out.read_text().splitlines()
            if line.startswith("| full ") or line.startswith("| skinning ")}
    assert rows["full"][4].strip() == "2.50" and rows["skinning"][4].strip() == "4.00"  # L-Coll column
    assert rows["full"][-2].strip() == "400"  # frames
    with pytest.raises(ValueError, match="also in"):
        main(["--from-json", str(full), str(full)])
    bad = tmp_path / "bad.json"
    bad.write_text('{"not": "a list of runs"}')
    with pytest.raises(ValueError, match="not an `smln eval --json` output"):
        main(["--from-json", str(bad)])
