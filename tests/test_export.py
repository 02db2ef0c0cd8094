"""Rollout NPZ round trip and the OBJ / PC2 / GLB exports (synthetic frames, no model needed)."""

from __future__ import annotations

import argparse
import io
import struct
import zipfile

import numpy as np
import pytest
import trimesh

from smln.export import (
    ExportError,
    cli_main,
    export_bytes,
    load_rollout_npz,
    pc2_bytes,
    read_pc2,
    rollout_from_frames,
    save_rollout_npz,
)
from smln.rollout import RolloutFrame


def _grid(n: int, z: float) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of 1 cm cells at height z: vertices (n*n, 3), faces (2(n-1)^2, 3)."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v = np.stack([i.ravel() * 0.01, j.ravel() * 0.01, np.full(n * n, z)], axis=1).astype(np.float32)
    a = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    f = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
    return v, f


@pytest.fixture()
def cloth_frames():
    v0, f0 = _grid(4, 1.0)
    v1, f1 = _grid(5, 1.01)
    verts = np.concatenate([v0, v1])
    faces = np.concatenate([f0, f1 + len(v0)])
    layer = np.concatenate([np.zeros(len(v0), int), np.ones(len(v1), int)])
    body_v, body_f = _grid(3, 0.5)
    rng = np.random.default_rng(0)
    frames = []
    for t in range(6):
        x = verts + np.float32(0.01 * t)
        frames.append(RolloutFrame(
            index=t, garment_positions=x, body_vertices=body_v + np.float32(t),
            predicted_acceleration=np.zeros_like(x),
            repulsion_acceleration=rng.normal(size=x.shape).astype(np.float32),
            layer_penetration=rng.random(len(x)) < 0.2, body_penetration=rng.random(len(x)) < 0.1,
            metrics={"l_coll": float(t), "h_coll": 0.5 * t} | ({"strain_mean": 0.01} if t else {}),
            fallback=False,
        ))
    return frames, faces, layer, body_f


def test_npz_round_trip(tmp_path, cloth_frames):
    frames, faces, layer, body_f = cloth_frames
    r = rollout_from_frames(frames, faces, layer, body_f, ["shirt", "jacket"], meta={"clip": "x"})
    path = tmp_path / "r.npz"
    save_rollout_npz(path, r)
    back = load_rollout_npz(path)
    assert back.garment_positions.shape == (6, 41, 3)
    np.testing.assert_array_equal(back.garment_positions, r.garment_positions)
    np.testing.assert_array_equal(back.repulsion_acceleration, r.repulsion_acceleration)
    np.testing.assert_array_equal(back.layer_penetration, r.layer_penetration)
    np.testing.assert_array_equal(back.faces, faces)
    np.testing.assert_array_equal(back.layer_index, layer)
    assert back.body_vertices.shape == (6, 9, 3)
    assert back.layer_names == ["shirt", "jacket"] and back.meta == {"clip": "x"}
    assert back.metric_names == ["l_coll", "h_coll", "strain_mean"]
    np.testing.assert_allclose(back.metric("l_coll"), np.arange(6))
    assert np.isnan(back.metric("strain_mean")[0]) and back.metric("strain_mean")[1] == pytest.approx(0.01)


def test_load_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ExportError):
        load_rollout_npz(bad)
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    with pytest.raises(ExportError, match="missing"):
        load_rollout_npz(other)


def test_pc2_header_and_values(cloth_frames):
    frames, faces, layer, body_f = cloth_frames
    r = rollout_from_frames(frames, faces, layer, body_f)
    data = export_bytes(r, "pc2")[1]
    sig, version, n, start, rate, t = struct.unpack("<12siiffi", data[:32])
    assert (sig, version, n, start, rate, t) == (b"POINTCACHE2\0", 1, 41, 0.0, 1.0, 6)
    assert len(data) == 32 + 6 * 41 * 3 * 4
    values = np.frombuffer(data[32:], dtype="<f4").reshape(6, 41, 3)
    np.testing.assert_array_equal(values, r.garment_positions)
    header, pos = read_pc2(pc2_bytes(r.garment_positions, start_frame=5))
    assert header["start_frame"] == 5.0 and pos.shape == (6, 41, 3)


def test_obj_zip_has_one_file_per_frame(cloth_frames):
    frames, faces, layer, body_f = cloth_frames
    r = rollout_from_frames(frames, faces, layer, body_f, ["shirt", "jacket"])
    zf = zipfile.ZipFile(io.BytesIO(export_bytes(r, "obj")[1]))
    names = sorted(zf.namelist())
    assert names == [f"garment_{t:04d}.obj" for t in range(6)]
    for t, name in enumerate(names):
        text = zf.read(name).decode()
        lines = text.splitlines()
        assert sum(ln.startswith("v ") for ln in lines) == 41
        assert sum(ln.startswith("f ") for ln in lines) == len(faces)
        assert "g 0_shirt" in text and "g 1_jacket" in text
        mesh = trimesh.load(io.BytesIO(text.encode()), file_type="obj", process=False, force="mesh")
        assert len(mesh.vertices) == 41
        np.testing.assert_allclose(mesh.vertices, r.garment_positions[t], atol=1e-5)


def test_glb_zip_loads_with_trimesh(cloth_frames):
    frames, faces, layer, body_f = cloth_frames
    r = rollout_from_frames(frames[:3], faces, layer, body_f, ["shirt", "jacket"])
    zf = zipfile.ZipFile(io.BytesIO(export_bytes(r, "glb", include_body=True)[1]))
    assert sorted(zf.namelist()) == [f"frame_{t:04d}.glb" for t in range(3)]
    scene = trimesh.load(io.BytesIO(zf.read("frame_0002.glb")), file_type="glb")
    geoms = scene.geometry
    assert {"0_shirt", "1_jacket", "body"} <= set(geoms)
    assert len(geoms["0_shirt"].vertices) == 16 and len(geoms["1_jacket"].vertices) == 25
    np.testing.assert_allclose(np.sort(geoms["1_jacket"].vertices[:, 2]), np.full(25, 1.03), atol=1e-5)


def test_cli_export(tmp_path, cloth_frames, capsys):
    frames, faces, layer, body_f = cloth_frames
    npz = tmp_path / "r.npz"
    save_rollout_npz(npz, rollout_from_frames(frames, faces, layer, body_f))
    out = tmp_path / "r.pc2"
    cli_main(argparse.Namespace(argv=[str(npz), "--format", "pc2", "--out", str(out)]))
    assert out.stat().st_size == 32 + 6 * 41 * 12
    with pytest.raises(FileExistsError):
        cli_main(argparse.Namespace(argv=[str(npz), "--format", "pc2", "--out", str(out)]))
    from smln.cli import main

    assert main(["export", str(npz), "--format", "obj", "--out", str(tmp_path / "o.zip")]) == 0
    assert main(["export", str(tmp_path / "missing.npz"), "--format", "obj", "--out", str(tmp_path / "x")]) == 2
