"""bench/layer_sink.py: the top band of the outer layer and its sink below skinning (analytic cases)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from tests.script_loader import load_script

ROOT = Path(__file__).resolve().parent.parent


def _bench() -> ModuleType:
    return load_script("bench/layer_sink.py")


def test_top_band_takes_the_outer_layers_highest_vertices_only():
    bench = _bench()
    z = np.array([1.50, 1.45, 1.30, 1.49, 1.40, 1.20, 1.00])
    vertices = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    layer = np.array([0, 0, 0, 1, 1, 1, 1])  # the inner layer is higher, but only the outer one counts
    assert bench.top_band(vertices, layer, band=0.10).tolist() == [3, 4]
    assert bench.top_band(vertices, layer, band=0.0).tolist() == [3]
    assert bench.top_band(vertices, np.zeros(7, int), band=0.06).tolist() == [0, 1, 3]


def test_band_sink_is_the_mean_drop_below_skinning_in_mm():
    bench = _bench()
    rng = np.random.default_rng(0)
    skinned = rng.normal(size=(4, 6, 3))
    moved = skinned.copy()
    moved[:, :, 2] -= np.array([0.0, 0.01, 0.02, -0.005])[:, None]  # down 0, 10, 20 mm, up 5 mm
    moved[:, :, :2] += 0.3  # sideways motion does not count
    band = np.array([1, 2, 4])
    assert np.allclose(bench.band_sink(moved, skinned, band), [0.0, 10.0, 20.0, -5.0])
    moved[:, 0, 2] -= 1.0  # a vertex outside the band does not count
    assert np.allclose(bench.band_sink(moved, skinned, band), [0.0, 10.0, 20.0, -5.0])


def test_paired_summary_means_and_paired_differences():
    bench = _bench()
    sinks = {"a": [10.0, 20.0, 30.0], "b": [12.0, 19.0, 36.0]}  # b - a: +2, -1, +6
    out = bench.paired_summary(sinks)
    assert out["a"] == {"mean_mm": 20.0, "scenes": 3}
    d = np.array([2.0, -1.0, 6.0])
    assert np.isclose(out["b"]["mean_mm"], 67.0 / 3)
    assert np.isclose(out["b"]["diff_mm"], d.mean())
    assert np.isclose(out["b"]["diff_se_mm"], d.std(ddof=1) / np.sqrt(3))
    assert (out["b"]["less"], out["b"]["more"]) == (1, 2)
    one = bench.paired_summary({"a": [5.0], "b": [4.0]})
    assert one["b"]["diff_mm"] == -1.0 and np.isnan(one["b"]["diff_se_mm"])
    with pytest.raises(ValueError, match="scenes"):
        bench.paired_summary({"a": [1.0, 2.0], "b": [1.0]})
