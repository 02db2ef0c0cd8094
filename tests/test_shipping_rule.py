"""The shipping rule of scripts/shipping_rule.py on hand-made figures."""

from __future__ import annotations

import importlib.util
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
