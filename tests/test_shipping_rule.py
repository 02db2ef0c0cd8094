"""The shipping rule of scripts/shipping_rule.py on hand-made figures."""

from __future__ import annotations

import math
from pathlib import Path

from tests.script_loader import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "shipping_rule.py"
rule = load_script("scripts/shipping_rule.py")


def _figures(l_full: float, l_nr: float, l_base: float, strain: float = 0.05) -> dict[str, dict[str, float]]:
    row = {"h_coll": 1.0, "strain_mean": strain, "fallback_frames": 10.0}
    return {"full": {**row, "l_coll": l_full}, "no_repulsion_layer": {**row, "l_coll": l_nr},
            "baseline": {**row, "l_coll": l_base}}


def test_candidate_equal_to_shipped_passes():
    shipped = _figures(1.6, 1.7, 12.0)
    assert all(ok for _, ok in rule.check(shipped, shipped, "seen"))


def test_one_worse_figure_fails_only_its_check():
    shipped = _figures(1.6, 1.7, 12.0)
    checks = dict(rule.check(_figures(1.5, 1.7, 12.0, strain=0.0501), shipped, "seen"))
    failed = [text for text, ok in checks.items() if not ok]
    assert len(failed) == 1 and "strain" in failed[0] and "5.01" in failed[0]


def test_broken_ablation_order_fails():
    shipped = _figures(1.6, 1.7, 12.0)
    checks = rule.check(_figures(1.55, 1.50, 12.0), shipped, "held-out")
    assert [ok for text, ok in checks if "order" in text] == [False]
    assert all(ok for text, ok in checks if "order" not in text)


def test_missing_variant_fails():
    shipped = _figures(1.6, 1.7, 12.0)
    candidate = _figures(1.5, 1.7, 12.0)
    del candidate["baseline"]
    checks = rule.check(candidate, shipped, "seen")
    assert any(not ok and "baseline evaluated" in text for text, ok in checks)


def _run(outfit: str, motion: str, l_coll: float, method: str = "full"):
    from smln.evaluate import RunResult

    return RunResult(method, outfit, motion, "train", {"l_coll": l_coll})


def test_paired_differences_are_per_scene_and_only_on_common_scenes():
    shipped = [_run("a", "m1", 1.0), _run("a", "m2", 2.0), _run("b", "m1", 3.0), _run("b", "m1", 9.0, "baseline")]
    candidate = [_run("a", "m1", 1.5), _run("a", "m2", 1.0), _run("b", "m1", 3.5), _run("c", "m1", 0.0)]
    d = rule.weighted_paired_difference(candidate, shipped, "l_coll", weighted=False)
    # differences +0.5, -1.0, +0.5 (scene c is not in the shipped evaluation; the baseline row is another method)
    assert d["scenes"] == 3 and d["better"] == 1 and d["worse"] == 2
    assert d["mean"] == 0.0
    assert d["se"] == (((0.5**2 + 1.0**2 + 0.5**2) / 2) ** 0.5) / 3**0.5
    one = rule.weighted_paired_difference(candidate[:1], shipped, "l_coll", weighted=False)
    assert one["mean"] == 0.5 and math.isnan(one["se"])  # no spread from one scene


def _scene(outfit: str, motion: str, frames: int, method: str = "full", **metrics: float):
    from smln.evaluate import RunResult

    values = {"l_coll": 1.0, "h_coll": 1.0, "strain_mean": 0.05, "fallback_frames": 0.0, **metrics}
    return RunResult(method, outfit, motion, "test", {**values, "num_frames": float(frames)})


def test_weighted_paired_difference_matches_hand_computation():
    shipped = [_scene("a", "m", 100, l_coll=1.0), _scene("b", "m", 300, l_coll=2.0)]
    candidate = [_scene("a", "m", 100, l_coll=2.0), _scene("b", "m", 300, l_coll=2.0)]
    d = rule.weighted_paired_difference(candidate, shipped, "l_coll")
    # p = (0.25, 0.75), d_i = (1, 0): mean 0.25; SE = sqrt(2 * (0.25² * 0.75² + 0.75² * 0.25²)) = 0.375
    assert d["scenes"] == 2 and d["unmatched"] == 0
    assert math.isclose(d["mean"], 0.25) and math.isclose(d["se"], 0.375)
    # equal frames: the plain mean and sd / sqrt(n)
    equal = [_scene("a", "m", 50, l_coll=1.0), _scene("b", "m", 50, l_coll=1.0), _scene("c", "m", 50, l_coll=1.0)]
    moved = [_scene("a", "m", 50, l_coll=1.5), _scene("b", "m", 50, l_coll=1.0), _scene("c", "m", 50, l_coll=2.5)]
    d = rule.weighted_paired_difference(moved, equal, "l_coll")
    diffs = [0.5, 0.0, 1.5]
    sd = math.sqrt(sum((x - 2 / 3) ** 2 for x in diffs) / 2)
    assert math.isclose(d["mean"], 2 / 3) and math.isclose(d["se"], sd / math.sqrt(3))


def test_weighted_paired_difference_counts_fallbacks_as_fractions_and_unmatched_scenes():
    shipped = [_scene("a", "m", 100, fallback_frames=10.0), _scene("b", "m", 100)]
    candidate = [_scene("a", "m", 100, fallback_frames=0.0), _scene("c", "m", 100)]
    d = rule.weighted_paired_difference(candidate, shipped, "fallback_frames")
    assert d["scenes"] == 1 and d["unmatched"] == 2 and math.isclose(d["mean"], -0.1)


def _split(l_coll: list[float], h_coll: list[float]) -> list:
    pairs = enumerate(zip(l_coll, h_coll, strict=True))
    return [_scene(f"o{i}", "m", 100, l_coll=lc, h_coll=hc) for i, (lc, hc) in pairs]


def test_margin_rule_tolerates_noise_but_not_a_consistent_loss():
    shipped = _split([1.0, 1.2, 1.4, 1.1], [1.0, 1.0, 1.0, 1.0])
    # L-Coll up on average by 0.05 but down on two scenes: within two standard errors; H-Coll down everywhere
    noisy = _split([1.3, 1.0, 1.5, 1.1], [0.5, 0.6, 0.4, 0.5])
    checks, improved = rule.check_margin(noisy, shipped, "seen")
    assert improved and all(ok for _, ok in checks)
    # the same average loss on every scene: significant, fails
    consistent = _split([1.05, 1.25, 1.45, 1.15], [0.5, 0.6, 0.4, 0.5])
    checks, improved = rule.check_margin(consistent, shipped, "seen")
    failed = [text for text, ok in checks if not ok]
    assert improved and len(failed) == 1 and "L-Coll" in failed[0] and "difference" in failed[0]


def test_margin_rule_keeps_the_issue_targets_the_shipped_model_meets():
    shipped = _split([1.4, 1.4], [1.0, 1.0])  # seen L-Coll 1.4 <= 1.5: met
    checks, _ = rule.check_margin(_split([1.45, 1.6], [0.5, 0.5]), shipped, "seen")  # 1.525: lost
    failed = [text for text, ok in checks if not ok]
    assert len(failed) == 1 and "target <= 1.5" in failed[0]
    # a target the shipped model misses (H-Coll 1.0 > 0.5) is not checked
    assert not any("target <= 0.5" in text for text, _ in checks)
    # nothing better: improved is False, and an empty evaluation fails
    _, improved = rule.check_margin(shipped, shipped, "seen")
    assert not improved
    checks, _ = rule.check_margin([], shipped, "seen")
    assert checks and not any(ok for _, ok in checks)
