"""bench/layer_push_probe.py: the repulsion push of one frame against the layer beneath (analytic case)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from tests.script_loader import load_script

ROOT = Path(__file__).resolve().parent.parent


def _bench() -> ModuleType:
    return load_script("bench/layer_push_probe.py")


def _grid(z: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat 3 × 3 grid of 1 cm cells at height z, wound so that its normals point up (+z)."""
    r, c = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
    vertices = np.stack([c.ravel() * 0.01, r.ravel() * 0.01, np.full(9, z)], axis=1)
    faces = [(i, i + 1, i + 3) for i in (0, 1, 3, 4)] + [(i + 1, i + 4, i + 3) for i in (0, 1, 3, 4)]
    return vertices, np.array(faces)


def test_shares_against_a_flat_layer_beneath():
    bench = _bench()
    inner, inner_faces = _grid(0.0)
    outer, outer_faces = _grid(0.002)  # 2 mm in front of the layer beneath ...
    outer[4, 2] = -0.003  # ... but its centre 3 mm behind it
    x = np.concatenate([inner, outer]).astype(np.float32)
    faces = torch.as_tensor(np.concatenate([inner_faces, outer_faces + 9]))
    push = np.zeros_like(x)
    push[9 + 4] = (0.0, 0.0, 0.001)  # the centre pushed outward
    push[9 + 0] = (0.0, 0.0, -0.001)  # a corner in front pushed inward
    pairs = np.array([[9 + 4], [4]])  # the layer paired the centre with the inner centre ...
    read = np.array([0.006])  # ... and read it 6 mm in front: at or above its 5 mm threshold
    figures = dict(zip(bench.FIGURES, bench.frame_figures(x, push, faces, slice(0, 9), slice(9, 18), pairs, read,
                                                          threshold=0.005, far=0.05), strict=True))
    assert figures["pushed"] == pytest.approx(2 / 9)
    assert figures["behind"] == pytest.approx(1 / 9)
    assert figures["pushed_outward"] == pytest.approx(0.5)
    assert figures["behind_pushed"] == pytest.approx(1.0)
    assert figures["behind_pushed_outward"] == pytest.approx(1.0)
    assert figures["median_push"] == pytest.approx(0.001)
    assert figures["median_depth"] == pytest.approx(0.003, abs=1e-6)
    assert figures["behind_far"] == 0.0  # 3 mm from the layer beneath
    assert figures["behind_paired"] == 1.0 and figures["behind_paired_read_clear"] == 1.0
    assert figures["behind_median_pair_distance"] == pytest.approx(0.006)


def test_a_vertex_beyond_the_hem_counts_as_far_and_unpaired():
    bench = _bench()
    inner, faces = _grid(0.0)
    outer, _ = _grid(0.004)
    outer[0] = (0.01, 0.01, -0.07)  # 7 cm below the inner centre: behind its normal plane, far from it
    x = np.concatenate([inner, outer]).astype(np.float32)
    all_faces = torch.as_tensor(np.concatenate([faces, faces + 9]))
    pairs = np.array([[9 + k for k in range(1, 9)], [k for k in range(1, 9)]])  # every other outer vertex paired
    figures = dict(zip(bench.FIGURES, bench.frame_figures(x, np.zeros_like(x), all_faces, slice(0, 9), slice(9, 18),
                                                          pairs, np.full(8, 0.004)), strict=True))
    assert figures["behind"] == pytest.approx(1 / 9) and figures["behind_far"] == 1.0
    assert figures["behind_paired"] == 0.0 and np.isnan(figures["behind_paired_read_clear"])


def test_nothing_behind_gives_nan_shares_not_errors():
    bench = _bench()
    inner, faces = _grid(0.0)
    outer, _ = _grid(0.004)
    x = np.concatenate([inner, outer]).astype(np.float32)
    all_faces = torch.as_tensor(np.concatenate([faces, faces + 9]))
    figures = bench.frame_figures(x, np.zeros_like(x), all_faces, slice(0, 9), slice(9, 18))
    assert figures[0] == 0.0 and figures[1] == 0.0
    assert np.isnan(figures[2:]).all()
