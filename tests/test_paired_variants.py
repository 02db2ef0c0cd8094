"""scripts/paired_variants.py: one variant minus another, paired per scene, on hand-made and on shipped figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from smln.evaluate import RunResult, aggregate, load_results
from tests.script_loader import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "paired_variants.py"
paired = load_script("scripts/paired_variants.py")


def _run(method: str, outfit: str, motion: str, l_coll: float, frames: int) -> RunResult:
    return RunResult(method, outfit, motion, "test", {"l_coll": l_coll, "num_frames": frames})


def test_weighted_and_unweighted_means_per_outfit_on_common_scenes_only():
    a = [_run("full", "o1", "m1", 1.0, 100), _run("full", "o1", "m2", 3.0, 300), _run("full", "o2", "m1", 2.0, 100),
         _run("full", "o3", "m1", 0.0, 50),  # only in A: left out, counted as unmatched
         _run("baseline", "o1", "m1", 9.0, 100)]  # another method in the same file: ignored
    b = [_run("no_repulsion_layer", "o1", "m1", 2.0, 100), _run("no_repulsion_layer", "o1", "m2", 2.0, 300),
         _run("no_repulsion_layer", "o2", "m1", 4.0, 100)]
    rows = paired.paired_variants(a, b, "full", "no_repulsion_layer")
    # differences -1 (100 frames), +1 (300), -2 (100): frame-weighted (-100 + 300 - 200) / 500 = 0
    assert rows["all"]["mean"] == pytest.approx(0.0)
    assert rows["all"]["a"] == pytest.approx((100 + 900 + 200) / 500) and rows["all"]["b"] == pytest.approx(2.4)
    counts = (rows["all"]["scenes"], rows["all"]["better"], rows["all"]["worse"], rows["all"]["unmatched"])
    assert counts == (3, 2, 1, 1)
    assert set(rows) == {"all", "o1", "o2"}
    assert rows["o1"]["mean"] == pytest.approx((-100 + 300) / 400) and rows["o2"]["mean"] == pytest.approx(-2.0)
    unweighted = paired.paired_variants(a, b, "full", "no_repulsion_layer", weighted=False)["all"]
    assert unweighted["mean"] == pytest.approx(-2.0 / 3.0)
    # every scene alike: sd of (-1, +1, -2) / sqrt(3)
    diffs = [-1.0, 1.0, -2.0]
    mean = sum(diffs) / 3
    sd = (sum((d - mean) ** 2 for d in diffs) / 2) ** 0.5
    assert unweighted["se"] == pytest.approx(sd / 3**0.5)


def test_cli_on_shipped_evaluations_matches_the_tables(capsys):
    full, ablation = ROOT / "docs/results/r43_a_seen_full.json", ROOT / "docs/results/r48_seen_no_repulsion_layer.json"
    assert paired.main([str(full), str(ablation)]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    expected = (aggregate(load_results([full]))["full"]["l_coll"]
                - aggregate(load_results([ablation]))["no_repulsion_layer"]["l_coll"])
    assert first.startswith("all: l_coll full ") and f"= {expected:+.3f} ± " in first


def test_cli_refuses_files_without_common_scenes():
    full = ROOT / "docs/results/r43_a_seen_full.json"
    with pytest.raises(SystemExit, match="no common scenes"):
        paired.main([str(full), str(full)])  # that file holds no no_repulsion_layer rows


def test_cli_pools_pairs_with_their_scenes_kept_apart(capsys):
    files = [str(ROOT / "docs/results" / name) for name in ("r43_a_held_full.json", "r48_held_no_repulsion_layer.json")]
    assert paired.main(files) == 0
    single = capsys.readouterr().out.splitlines()[0]
    assert paired.main(files + files) == 0  # the same pair twice: twice the scenes, the same means
    pooled = capsys.readouterr().out.splitlines()[0]
    scenes = int(single.split(" over ")[1].split()[0])
    assert f" over {2 * scenes} scenes" in pooled
    assert single.split(" (SE)")[0].rsplit(" ± ", 1)[0] == pooled.split(" (SE)")[0].rsplit(" ± ", 1)[0]
    with pytest.raises(SystemExit):
        paired.main(files[:1])  # not a pair
