"""The viewer: ViewerApp logic without a browser, uploads, and a real-browser run (Playwright + Debian Chromium).

The browser test is marked ``browser`` and skips cleanly when /usr/bin/chromium or playwright is missing.
Screenshots land in the test's temporary directory, or in ``$SMLN_SCREENSHOTS`` when set (e.g. docs/screenshots to
refresh the README's images): a test run leaves the working tree as it was.
"""

from __future__ import annotations

import os
import re
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from app.sources import Catalog, Setting
from app.uploads import MAX_BVH_BYTES, UploadError, UploadStore

ROOT = Path(__file__).resolve().parent.parent
SHOTS_ENV = "SMLN_SCREENSHOTS"
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_FLAGS = [
    "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader", "--disable-quic",
    "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def tiny_checkpoints(directory: Path, variants: tuple[str, ...] = ("full", "baseline")) -> Path:
    """Untrained small SMLN checkpoints (latent 16) standing in for the trained ones."""
    from smln.checkpoint import save_checkpoint
    from smln.model.smln import SMLN, SMLNConfig

    for v in variants:
        cfg = SMLNConfig(latent_size=16, use_repulsion_layer=v != "baseline")
        save_checkpoint(f"{directory / v}/", SMLN(cfg), card={"variant": v})  # a folder per variant
    return directory


def _viewer_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("smln-")]


def test_viewer_app_headless(tmp_path):
    from app.server import ViewerApp

    before = set(threading.enumerate())
    app = ViewerApp(port=free_port(), checkpoint_dir=None, max_frames=24)
    try:
        assert app.url.startswith("http://127.0.0.1:")
        assert app.variants == ["skinning"]
        assert app.worker.wait_frames(5, timeout=60)
        assert app.set_setting(outfit="leggings_skirt", clip="05_01_walk") is True
        assert app.set_setting(outfit="leggings_skirt") is False  # same setting: no new computation
        assert app.worker.configure(app.setting, ("skinning",)) is False
        assert app.worker.wait_frames(24, timeout=90)
        cache = app.worker.caches["skinning"]
        assert cache.done and len(cache) == 24 and not cache.error
        assert app.worker.scenario.setting == Setting("leggings_skirt", "05_01_walk", "female_average")
        f = cache.frames[10]
        assert f.garment_positions.shape == (app.worker.scenario.cloth.num_vertices, 3)
        assert np.isfinite(f.garment_positions).all() and "l_coll" in f.metrics

        app.seek(3)
        assert app.step(1) == 4 and not app.playing
        assert app.step(-5) == 23  # loops over the computed clip
        time.sleep(0.3)  # the playback thread pushes the shown frame
        assert app.controls.frame.value == 23
        assert app.scene.views["skinning"].shown_index == 23

        name, data = app.export("skinning", "npz")
        assert name == "leggings_skirt_05_01_walk_skinning.npz"
        path = tmp_path / name
        path.write_bytes(data)
        from smln.export import load_rollout_npz

        r = load_rollout_npz(path)
        assert r.num_frames == 24 and r.meta["variant"] == "skinning" and r.layer_names == ["leggings", "skirt"]
        assert app.export("skinning", "pc2")[1][:12] == b"POINTCACHE2\0"

        with pytest.raises(ValueError):
            app.set_setting(outfit="no_such_outfit")
        with pytest.raises(ValueError):
            app.set_variants(["full"])  # no checkpoint
        assert app.setting.outfit == "leggings_skirt"  # a refused request changes nothing
    finally:
        app.stop()
    time.sleep(0.2)
    assert not app.worker.alive
    assert not _viewer_threads()
    leaked = [t for t in set(threading.enumerate()) - before if t.is_alive() and not t.daemon]
    assert not leaked, leaked


def test_viewer_collision_projection_setting(tmp_path):
    """The projection picker re-runs the model variants with smln.projection; a bad value is refused."""
    from app.server import ViewerApp

    ckpt = tiny_checkpoints(tmp_path / "ckpt", variants=("full",))
    app = ViewerApp(port=free_port(), checkpoint_dir=ckpt, max_frames=6, variants=["full"])
    try:
        assert app.worker.wait_frames(6, timeout=90)
        plain = app.worker.caches["full"].frames[4]
        assert "projected_fraction" not in plain.metrics
        assert app.set_setting(projection="body+layers") is True
        assert app.controls.projection.value == "body+layers"
        assert app.worker.wait_frames(6, timeout=90)
        assert app.worker.scenario.setting.projection == "body+layers"
        projected = app.worker.caches["full"].frames[4]
        assert "projected_fraction" in projected.metrics
        # the skinned start penetrates the body in places: the projection must have moved something
        assert projected.metrics["projected_fraction"] > 0.0
        name, _ = app.export("full", "npz")
        assert name.endswith("_full_projection-body-layers.npz")
        with pytest.raises(ValueError, match="projection"):
            app.set_setting(projection="sideways")
        assert app.setting.projection == "body+layers"
    finally:
        app.stop()


def test_viewer_repulsion_layer_reading_setting(tmp_path):
    """The reading picker re-runs the full model with repulsion_pairing set on a copy (the loaded checkpoint keeps
    its own reading); a model without the layer is left as it is; a bad value is refused."""
    from app.server import ViewerApp

    ckpt = tiny_checkpoints(tmp_path / "ckpt")
    app = ViewerApp(port=free_port(), checkpoint_dir=ckpt, max_frames=4, variants=["full", "baseline"])
    try:
        assert app.worker.wait_frames(4, timeout=90)
        assert app.set_setting(reading="deeper") is True
        assert app.controls.reading.value == "deeper"
        assert app.worker.wait_frames(4, timeout=90)
        assert app.worker.scenario.setting.reading == "deeper"
        assert app.catalog.model("full", "deeper").config.repulsion_pairing == "deeper"
        assert app.catalog.model("full").config.repulsion_pairing == "vertex"  # the checkpoint's own, untouched
        assert app.catalog.model("baseline", "deeper") is app.catalog.model("baseline")  # no layer: no copy
        name, _ = app.export("full", "npz")
        assert name.endswith("_full_reading-deeper.npz")
        with pytest.raises(ValueError, match="reading"):
            app.set_setting(reading="sideways")
        assert app.setting.reading == "deeper"
    finally:
        app.stop()


def test_catalog_body_stage_readings(tmp_path):
    """The body-edge / body-nearest readings set body_pairing on a copy of a model with the body stage; the loaded
    model keeps its own; a model without the stage (or without the layer) is returned as it is."""
    from smln.checkpoint import save_checkpoint
    from smln.model.smln import SMLN, SMLNConfig

    save_checkpoint(f"{tmp_path / 'ckpt' / 'full'}/", SMLN(SMLNConfig(latent_size=16, body_repulsion=True)),
                    card={"variant": "full"})
    save_checkpoint(f"{tmp_path / 'ckpt' / 'baseline'}/", SMLN(SMLNConfig(latent_size=16, use_repulsion_layer=False)),
                    card={"variant": "baseline"})
    cat = Catalog(tmp_path / "ckpt", max_frames=4)
    base = cat.model("full")
    near = cat.model("full", "body-nearest")
    assert near is not base and near.config.body_pairing == "nearest"
    assert base.config.body_pairing == "edge" and cat.model("full", "body-edge") is base  # already edge: no copy
    assert near.config.repulsion_pairing == base.config.repulsion_pairing  # one field per reading
    for key, value in base.state_dict().items():
        assert torch.equal(near.state_dict()[key], value), key
    assert cat.model("baseline", "body-nearest") is cat.model("baseline")
    with pytest.raises(ValueError, match="reading"):
        cat.model("full", "body-sideways")
    # the layer stage's nearest pairing, alone and with the body stage's
    layer = cat.model("full", "layer-nearest")
    assert layer.config.repulsion_pairing == "nearest" and layer.config.body_pairing == "edge"
    both = cat.model("full", "all-nearest")
    assert (both.config.repulsion_pairing, both.config.body_pairing) == ("nearest", "nearest")
    assert base.config.repulsion_pairing == "vertex"  # the loaded model keeps its own reading
    assert cat.model("baseline", "all-nearest") is cat.model("baseline")
    inside = cat.model("full", "nearest-inside")
    assert (inside.config.repulsion_pairing, inside.config.body_pairing) == ("nearest", "edge_inside")
    assert cat.model("full", "body-inside").config.repulsion_pairing == base.config.repulsion_pairing
    trained = cat.model("full", "as-trained")
    assert (trained.config.repulsion_pairing, trained.config.body_pairing) == ("vertex", "edge")


def test_uploads_are_validated(tmp_path):
    store = UploadStore(tmp_path / "up")
    with pytest.raises(UploadError, match="expected a .bvh"):
        store.add_bvh("walk.txt", b"HIERARCHY", "female_average")
    with pytest.raises(UploadError, match="empty"):
        store.add_bvh("walk.bvh", b"", "female_average")
    with pytest.raises(UploadError, match="limit"):
        store.add_bvh("big.bvh", b"x" * (MAX_BVH_BYTES + 1), "female_average")
    with pytest.raises(UploadError, match="broken.bvh"):
        store.add_bvh("broken.bvh", b"HIERARCHY\nROOT Hips\n{\n", "female_average")
    with pytest.raises(UploadError, match="garment.obj"):
        store.add_obj("garment.obj", b"v 0 0 0\nv 1 0 0\nf 1 2 3\n", "female_average")
    assert store.clips() == [] and store.garments() == []
    assert list((tmp_path / "up").iterdir()) == []  # refused files are not kept

    from smln.motion.library import clip_path

    key = store.add_bvh("my_walk.bvh", clip_path("02_01_walk").read_bytes(), "female_average")
    assert store.clips() == [(key, "my_walk")]
    cat = Catalog(None, uploads=store, max_frames=5)
    assert ("my_walk (uploaded)", key) in cat.clips()
    scenario = cat.prepare(Setting("tshirt_jacket", key, "female_average"))
    assert scenario.num_frames == 5


def _coloured_fraction(png: Path, box: tuple[int, int, int, int]) -> float:
    """Fraction of saturated (garment-coloured) pixels in ``box`` = (x0, y0, x1, y1) of a screenshot."""
    from PIL import Image

    img = np.asarray(Image.open(png).convert("RGB")).astype(np.int16)
    x0, y0, x1, y1 = box
    region = img[y0:y1, x0:x1]
    sat = region.max(axis=2) - region.min(axis=2)
    return float((sat > 60).mean())


def _frame_number(page) -> int:
    text = page.get_by_text(re.compile(r"frame \d+ of \d+")).first.inner_text()
    return int(re.search(r"frame (\d+) of", text).group(1))


def _pick(page, name: str, option: str) -> None:
    page.get_by_role("combobox", name=name).click()
    page.get_by_role("option", name=option).click()


@pytest.mark.browser
def test_viewer_in_chromium(tmp_path):
    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium is missing (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    from app.server import ViewerApp

    shots = Path(os.environ.get(SHOTS_ENV) or tmp_path / "screenshots")
    shots.mkdir(parents=True, exist_ok=True)
    ckpt = tiny_checkpoints(tmp_path / "ckpt")
    app = ViewerApp(port=free_port(), checkpoint_dir=ckpt, max_frames=30, variants=["skinning"])
    canvas_box = (0, 0, 1000, 900)  # the 3-D view left of the control panel
    try:
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(app.url)
            page.wait_for_selector("canvas", timeout=30_000)
            page.get_by_text("Connected").wait_for(timeout=30_000)

            _pick(page, "Outfit", "tshirt_jacket (seen · train)")
            _pick(page, "Motion clip", "02_05_punch_strike (test)")
            deadline = time.monotonic() + 30
            while app.setting.clip != "02_05_punch_strike" and time.monotonic() < deadline:
                time.sleep(0.1)
            assert app.setting == Setting("tshirt_jacket", "02_05_punch_strike", "female_average")
            assert app.worker.wait_frames(12, timeout=30)

            page.get_by_role("button", name="Pause").click()
            page.get_by_role("button", name="Play").wait_for(timeout=5_000)
            first = _frame_number(page)
            page.get_by_role("button", name="Play").click()
            deadline = time.monotonic() + 5.0  # playing waits for the rollout where it has caught up: a busy CI core
            second = first
            while second == first and time.monotonic() < deadline:
                time.sleep(0.25)
                second = _frame_number(page)
            assert second != first, "the frame counter did not advance while playing"
            time.sleep(1.0)
            one = shots / "viewer_single.png"
            page.screenshot(path=str(one))
            assert _coloured_fraction(one, canvas_box) > 0.003, "no garment pixels in the 3-D view"

            page.get_by_role("checkbox", name="SMLN (full)").check()
            page.get_by_role("checkbox", name="baseline").check()
            deadline = time.monotonic() + 20
            while app.variants != ["full", "baseline", "skinning"] and time.monotonic() < deadline:
                time.sleep(0.1)
            assert app.variants == ["full", "baseline", "skinning"]
            assert app.worker.wait_frames(4, timeout=40)
            page.get_by_role("checkbox", name=re.compile("Inter-layer penetrations")).uncheck()
            time.sleep(0.5)
            assert app.display.show_layer_pen is False
            page.get_by_role("checkbox", name=re.compile("Inter-layer penetrations")).check()
            time.sleep(3.0)
            three = shots / "viewer_variants.png"
            page.screenshot(path=str(three))
            assert _coloured_fraction(three, canvas_box) > 0.003
            assert len(app.scene.views) == 3
            browser.close()
    finally:
        app.stop()
