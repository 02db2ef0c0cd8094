"""bench/hcoll_depth.py: the per-layer penetration profile on hand-made distances."""

from __future__ import annotations

import math

import numpy as np

from tests.script_loader import load_script

hcoll_depth = load_script("bench/hcoll_depth.py")


def test_profile_counts_depths_and_the_contact_band_per_layer():
    # layer 0: 4 vertices over 2 frames; penetrations of 1 mm, 1 mm, 5 mm (of 8 vertex-frames), 2 in the band
    # (0 and 2.5 mm), the rest far away. layer 1: never inside, one vertex in the band.
    d0 = np.array([[-1e-3, -1e-3, 0.0, 0.02], [-5e-3, 2.5e-3, 0.02, 0.02]])
    d1 = np.array([[0.01, 1e-3], [0.01, 0.01]])
    prof = hcoll_depth.penetration_profile(np.concatenate([d0, d1], axis=1), np.array([0, 0, 0, 0, 1, 1]))
    assert math.isclose(prof[0]["h_coll"], 100 * 3 / 8)
    assert math.isclose(prof[0]["depth_p50_mm"], 1.0)
    assert math.isclose(prof[0]["depth_p90_mm"], 1.0 + 0.8 * 4.0)  # numpy's linear interpolation of [1, 1, 5]
    assert math.isclose(prof[0]["shallow"], 100 * 2 / 3)
    assert math.isclose(prof[0]["contact_band"], 100 * 2 / 8)
    assert prof[1]["h_coll"] == 0.0 and prof[1]["depth_p50_mm"] == 0.0 and math.isnan(prof[1]["shallow"])
    assert math.isclose(prof[1]["contact_band"], 25.0)


def test_body_distances_on_a_sphere():
    import torch
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=4)
    body = torch.as_tensor(s.vertices, dtype=torch.float32)
    dirs = s.vertices[:5] / np.linalg.norm(s.vertices[:5], axis=1, keepdims=True)
    d = hcoll_depth.body_distances((dirs * np.array([0.99, 1.0, 1.003, 1.01, 1.2])[:, None]).astype(np.float32),
                                   body, torch.as_tensor(s.faces))
    np.testing.assert_allclose(d, [-0.01, 0.0, 0.003, 0.01, 0.2], atol=2e-4)
