"""The physics reference (bench/physics_reference.py) writes a rollout NPZ the metrics and the viewer can read.

Skipped when the optional ``newton`` extra is missing (``pip install smln[physics]``). The first run compiles Warp
kernels for ~40 s (cached under ``WARP_CACHE_PATH``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("newton")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import physics_reference  # noqa: E402

from smln.export import load_rollout_npz  # noqa: E402


@pytest.mark.slow
def test_physics_rollout_npz_roundtrip(tmp_path: Path) -> None:
    out = tmp_path / "physics.npz"
    frames = physics_reference.run("tshirt_jacket", "05_01_walk", 3, out, substeps=2, iterations=2, progress=False)
    assert len(frames) == 3
    r = load_rollout_npz(out)
    assert r.num_frames == 3
    assert r.garment_positions.shape == (3, frames[0].garment_positions.shape[0], 3)
    assert np.isfinite(r.garment_positions).all()
    # frames 0-1 are the skinned initial state, frame 2 is simulated: it moved
    assert not np.allclose(r.garment_positions[2], r.garment_positions[1])
    for key in ("h_coll", "l_coll", "strain_mean", "strain_max", "ms_model"):
        assert key in r.metric_names
        assert np.isfinite(r.metric(key)).all()
    assert r.metric("ms_model")[2] > 0
    assert r.layer_penetration.shape == r.body_penetration.shape == (3, r.num_vertices)
    assert r.meta["variant"].startswith("physics")
    assert r.meta["solver"] == "newton.solvers.SolverVBD"


def test_bending_stiffness_matches_hood() -> None:
    # two right triangles sharing the hinge (0, 1): areas 0.5 each, hinge length 1
    rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0]], np.float32)
    edges = np.array([[2, 3, 0, 1], [-1, 3, 0, 3]])
    ke = physics_reference.bending_stiffness_per_edge(rest, edges, 2.0)
    np.testing.assert_allclose(ke, [2.0 * 1.0 / (4 * 1.0), 0.0], rtol=1e-6)
