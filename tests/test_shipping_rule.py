"""The shipping rule of scripts/shipping_rule.py on hand-made figures."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "shipping_rule.py"
spec = importlib.util.spec_from_file_location("shipping_rule", SCRIPT)
rule = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rule)


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
    d = rule.paired_differences(candidate, shipped, "l_coll")
    # differences +0.5, -1.0, +0.5 (scene c is not in the shipped evaluation; the baseline row is another method)
    assert d["scenes"] == 3 and d["better"] == 1 and d["worse"] == 2
    assert d["mean"] == 0.0
    assert d["se"] == (((0.5**2 + 1.0**2 + 0.5**2) / 2) ** 0.5) / 3**0.5
    one = rule.paired_differences(candidate[:1], shipped, "l_coll")
    assert one["mean"] == 0.5 and math.isnan(one["se"])  # no spread from one scene
