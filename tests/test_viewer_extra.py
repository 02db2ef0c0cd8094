"""The viewer's saved-rollout variants (``launch_viewer.py --extra-rollout``, the rollout NPZ upload), headless."""

from __future__ import annotations

import io
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from app.extras import MAX_ROLLOUT_UPLOAD_BYTES, ExtraRolloutError, ExtraStore, load_extra
from app.sources import Setting
from tests.test_viewer import free_port

SCENE = ("tshirt_jacket", "05_01_walk", "female_average")
FRAMES = 8


@pytest.fixture(scope="module")
def saved_rollout(tmp_path_factory) -> Path:
    """A short skinning rollout of tshirt_jacket / 05_01_walk saved as a rollout NPZ (like the physics one)."""
    from smln.data_sampling import make_scene
    from smln.evaluate import method_frames
    from smln.export import save_rollout_npz

    outfit, clip, shape = SCENE
    scene = make_scene(outfit, shape, clip, edge_length=0.035, max_frames=20)
    frames = list(method_frames("skinning", None, scene, FRAMES))
    path = tmp_path_factory.mktemp("extra") / "physics_like.npz"
    meta = {"outfit": outfit, "clip": clip, "shape": shape, "variant": "physics (Newton VBD)"}
    save_rollout_npz(path, frames, scene.cloth, scene.body.faces, meta=meta)
    return path


def test_saved_rollout_loads_as_variant(saved_rollout, tmp_path):
    from app.server import ViewerApp

    store = ExtraStore()
    extra = store.add(saved_rollout)
    assert extra.label == "physics (Newton VBD)" and extra.num_frames == FRAMES and not extra.note
    assert extra.scene == SCENE
    app = ViewerApp(port=free_port(), checkpoint_dir=None, max_frames=24, setting=Setting(*SCENE), extras=store)
    try:
        assert app.variants == ["skinning", extra.key]  # enabled at start, after the computed variants
        assert app.worker.variants == ("skinning",)  # the worker never computes a saved rollout
        assert app.label(extra.key) == "physics (Newton VBD)"
        assert app.controls.variants[extra.key].value is True
        assert app.worker.wait_frames(24, timeout=90)
        caches = app.caches()
        cache = caches[extra.key]
        assert cache.done and len(cache) == FRAMES and not cache.error
        assert app.available_frames() == 24  # the saved rollout does not shorten the shared timeline
        f = cache.frames[3]
        r = extra.rollout
        assert np.array_equal(f.garment_positions, r.garment_positions[3])
        assert np.array_equal(f.layer_penetration, r.layer_penetration[3]) and "l_coll" in f.metrics

        app.set_playing(False)
        app.seek(5)
        time.sleep(0.4)  # the playback thread pushes the frame
        view = app.scene.views[extra.key]
        assert view.spec.label == "physics (Newton VBD)" and view.shown_index == 5
        assert len(view.layers) == 2  # its own meshes: one per layer of its layer index
        assert app.seek(20) == 20  # past its length: it holds its last frame
        time.sleep(0.4)
        assert view.shown_index == FRAMES - 1 and app.scene.views["skinning"].shown_index == 20
        assert "holding its last frame" in view._label_text
        table = app.metrics.table_markdown(app.caches(), 20)
        assert "physics (Newton VBD) (frame 7)" in table

        name, data = app.export(extra.key, "npz")  # exported whole from its own arrays
        assert name == "physics_like.npz" and len(data) > 1000

        # the timeline with only the saved rollout: its own length
        app.set_variants([extra.key])
        assert app.worker.variants == () and app.available_frames() == FRAMES

        # another scene: still enabled, hidden from the scene and the metrics, with a note in the status line
        app.set_variants(["skinning", extra.key])
        assert app.set_setting(clip="02_01_walk")
        assert app.worker.wait_frames(3, timeout=90)
        time.sleep(0.4)
        other = app.caches()[extra.key]
        assert len(other) == 0 and other.error == "other scene"
        assert extra.key in app.variants and app.controls.variants[extra.key].value is True
        assert list(app.scene.views) == ["skinning"] and app.metrics.variants == ("skinning",)
        assert "physics (Newton VBD) hidden: made on tshirt_jacket / 05_01_walk" in app.controls.status.content
        assert app.available_frames() >= 3  # the computed variant plays on
    finally:
        app.stop()


def test_corrupt_rollout_is_refused(saved_rollout, tmp_path):
    from app.server import ViewerApp

    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(b"PK\x03\x04 this is not a zip archive")
    store = ExtraStore()
    with pytest.raises(ExtraRolloutError, match="corrupt.npz: not a rollout NPZ") as err:
        store.add(bad)
    assert "\n" not in str(err.value)
    with pytest.raises(ExtraRolloutError, match="no such file"):
        store.add(tmp_path / "missing.npz")
    no_faces = tmp_path / "no_faces.npz"
    np.savez(no_faces, garment_positions=np.zeros((2, 3, 3), np.float32))
    with pytest.raises(ExtraRolloutError, match="missing arrays"):
        load_extra(no_faces, "extra:x")
    with pytest.raises(ExtraRolloutError, match="limit"):
        store.add(b"x" * (MAX_ROLLOUT_UPLOAD_BYTES + 1), "big.npz")
    assert len(store) == 0

    before = set(threading.enumerate())
    app = ViewerApp(port=free_port(), checkpoint_dir=None, max_frames=12, extras=store)
    try:
        assert app.variants == ["skinning"]
        notes: list[tuple[str, str]] = []
        app.notify = lambda title, body, client=None, error=True: notes.append((title, body))  # type: ignore
        upload = SimpleNamespace(target=SimpleNamespace(value=SimpleNamespace(name="corrupt.npz",
                                                                              content=bad.read_bytes())),
                                 client=None)
        app._on_upload_rollout(upload)
        assert notes and notes[-1][0] == "Rollout refused" and "corrupt.npz" in notes[-1][1]
        assert app.variants == ["skinning"] and len(app.extras) == 0
        assert app.worker.wait_frames(5, timeout=60) and app.worker.alive  # still running

        # a good upload (of another scene than the default one) becomes a variant with a notification
        upload.target.value = SimpleNamespace(name="physics_like.npz", content=saved_rollout.read_bytes())
        app._on_upload_rollout(upload)
        assert notes[-1][0] == "Rollout loaded"
        assert len(app.extras) == 1 and app.variants[-1].startswith("extra:")
        if app.setting != Setting(*SCENE):
            assert "pick that scene" in notes[-1][1]
        assert app.controls.variants[app.variants[-1]].value is True
        assert io.BytesIO(app.export(app.variants[-1], "pc2")[1]).read(12) == b"POINTCACHE2\0"
    finally:
        app.stop()
    time.sleep(0.2)
    leaked = [t for t in set(threading.enumerate()) - before if t.is_alive() and not t.daemon]
    assert not leaked, leaked


def test_launcher_reports_bad_extra(tmp_path, capsys):
    import launch_viewer

    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"garbage")
    store, setting = launch_viewer.load_extras([str(bad)], None)
    assert len(store) == 0 and setting is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("launch_viewer: skipping --extra-rollout") and "broken.npz" in err[0]


def test_camera_centre_does_not_jump_when_a_variant_lags():
    """The follow camera's centre is the body's, not the mean of whichever variants already have the frame."""
    from types import SimpleNamespace

    import numpy as np

    from app.scene import SceneView

    view = SceneView.__new__(SceneView)  # only the layout logic, no server
    view.views = {"full": None, "baseline": None, "skinning": None}
    body = np.random.default_rng(0).normal(size=(50, 3)) + np.array([0.3, -0.2, 1.0])
    frame = SimpleNamespace(body_vertices=body)
    all_there = view.centre({"full": frame, "baseline": frame, "skinning": frame})
    one_there = view.centre({"full": None, "baseline": None, "skinning": frame})
    np.testing.assert_allclose(all_there, body.mean(axis=0), atol=1e-12)
    np.testing.assert_allclose(one_there, all_there, atol=1e-12)
    assert view.centre({"full": None}) is None


@pytest.mark.parametrize("compiled", [False, True])
def test_catalog_passes_the_compile_option_to_its_rollouts(monkeypatch, compiled):
    """``launch_viewer.py --compile`` reaches every model rollout of the catalog (skinning has no model)."""
    import app.sources as sources

    seen = {}

    def fake_rollout(model, cloth, sequence, faces, **kw):
        seen.update(kw)
        return iter(())

    monkeypatch.setattr(sources, "rollout", fake_rollout)
    cat = sources.Catalog("checkpoints", max_frames=4, precision="float32", compiled=compiled)
    if "full" not in cat.checkpoints:
        pytest.skip("no shipped checkpoint")
    scenario = cat.prepare(Setting(*SCENE))
    list(cat.frames("full", scenario))
    assert seen["compiled"] is compiled and seen["precision"] == "float32"
