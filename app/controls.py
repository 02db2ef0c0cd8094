"""The viewer's GUI panel (built once, shared by every connected browser).

:func:`build_controls` lays out the folders and returns the handles in a :class:`Controls`; the wiring to
actions lives in :mod:`app.server`. Per-layer controls depend on the outfit and are rebuilt by
:func:`build_layer_controls`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import viser

from app.extras import MAX_ROLLOUT_UPLOAD_BYTES
from app.scene import LAYER_COLOURS, Display
from app.sources import PROJECTIONS, READINGS, VARIANT_LABELS, VARIANTS, Catalog, Setting
from app.uploads import MAX_BVH_BYTES, MAX_OBJ_BYTES

SPEEDS: tuple[str, ...] = ("0.25x", "0.5x", "1x", "2x")
STEPS: tuple[str, ...] = ("◀ -10", "◀ -1", "+1 ▶", "+10 ▶")


@dataclass
class Controls:
    """Handles of the GUI (see :func:`build_controls` for what each does)."""

    outfit: Any
    clip: Any
    shape: Any
    upload_bvh: Any
    upload_obj: Any
    checkpoint_note: Any
    play: Any
    frame: Any
    steps: Any
    speed: Any
    loop: Any
    stream_fps: Any
    progress: Any
    status: Any
    follow: Any
    reset_camera: Any
    variants: dict[str, Any]
    layer_pen: Any
    body_pen: Any
    vectors: Any
    vector_scale: Any
    vector_threshold: Any
    wireframe: Any
    body: Any
    layers_folder: Any
    metrics_folder: Any
    export_variant: Any
    downloads: dict[str, Any]
    outfit_keys: dict[str, str] = field(default_factory=dict)
    clip_keys: dict[str, str] = field(default_factory=dict)
    layer_handles: list[tuple[Any, Any]] = field(default_factory=list)
    variants_folder: Any = None
    upload_rollout: Any = None
    projection: Any = None
    reading: Any = None

    def outfit_label(self, key: str) -> str | None:
        return next((lab for lab, k in self.outfit_keys.items() if k == key), None)

    def clip_label(self, key: str) -> str | None:
        return next((lab for lab, k in self.clip_keys.items() if k == key), None)


def build_controls(gui: viser.GuiApi, catalog: Catalog, setting: Setting, variants: list[str],
                   display: Display) -> Controls:
    """Lay out the panel.

    Folders: *Scene* (outfit, clip, body-shape pickers; BVH / OBJ uploads), *Playback* (play/pause, frame
    slider, steps, speed, loop, streaming rate, progress, camera), *Variants* (the ablation checkboxes, the
    rollout NPZ upload; saved rollouts' checkboxes are added below it by the server),
    *Inspect* (overlays, vectors, wireframe, body, layers), *Metrics* and *Export*.
    """
    outfit_keys = dict(catalog.outfits())
    clip_keys = dict(catalog.clips())
    with gui.add_folder("Scene"):
        outfit = gui.add_dropdown("Outfit", list(outfit_keys), initial_value=_label(outfit_keys, setting.outfit),
                                  hint="seen/unseen: whether the outfit's garments were used in training")
        clip = gui.add_dropdown("Motion clip", list(clip_keys), initial_value=_label(clip_keys, setting.clip),
                                hint="train/test: the clip split of the motion library")
        shape = gui.add_dropdown("Body shape", catalog.shapes(), initial_value=setting.shape)
        projection = gui.add_dropdown(
            "Collision projection", list(PROJECTIONS), initial_value=setting.projection,
            hint="off: the learned model alone (as evaluated in the paper); body / body+layers: move penetrating "
                 "vertices back out after every network step (smln.projection)")
        reading = gui.add_dropdown(
            "Repulsion layer reading", list(READINGS), initial_value=setting.reading,
            hint="checkpoint: as its card says; vertex: each outer vertex against its nearest inner vertex (paper "
                 "Eq. 14); deeper: also against the closest inner triangle point, the deeper reading pushes "
                 "(SMLNConfig.repulsion_pairing); layer-nearest: against the inner vertex nearest to the prediction "
                 "at t+1 (the L-Coll metric's pairing); body-edge / body-nearest: the body stage against the body "
                 "vertex nearest at t / nearest to the prediction at t+1 (SMLNConfig.body_pairing); all-nearest: "
                 "both stages nearest at t+1; body-inside: body edge pairs, then the nearest reading for vertices "
                 "still inside the body; nearest-inside: layer-nearest and body-inside; as-trained: vertex and "
                 "body-edge; same weights")
        upload_bvh = gui.add_upload_button("Upload BVH clip", icon=None, mime_type=".bvh",
                                           hint=f"CMU-style BVH, at most {MAX_BVH_BYTES // 2**20} MB")
        upload_obj = gui.add_upload_button("Upload OBJ garment", icon=None, mime_type=".obj",
                                           hint=f"one garment in meters in the T-pose frame (Z up, facing -Y), "
                                                f"at most {MAX_OBJ_BYTES // 2**20} MB")
        checkpoint_note = gui.add_markdown(checkpoint_text(catalog))
    with gui.add_folder("Playback"):
        play = gui.add_button("Pause", icon=None)
        frame = gui.add_slider("Frame", min=0, max=1, step=1, initial_value=0)
        steps = gui.add_button_group("Step", STEPS)
        speed = gui.add_button_group("Speed", SPEEDS)
        loop = gui.add_checkbox("Loop", True)
        stream_fps = gui.add_slider("Stream fps", min=5, max=30, step=5, initial_value=30,
                                    hint="frames sent to the browsers per second (lower it on remote links)")
        progress = gui.add_progress_bar(0.0, animated=True)
        status = gui.add_markdown("loading …")
        follow = gui.add_checkbox("Camera follows body", True)
        reset_camera = gui.add_button("Reset camera")
    with gui.add_folder("Variants") as variants_folder:
        boxes = {}
        for v in VARIANTS:
            ok = v in catalog.available_variants()
            boxes[v] = gui.add_checkbox(
                VARIANT_LABELS[v], v in variants, disabled=not ok,
                hint=None if ok else f"no checkpoint found in {catalog.checkpoint_dir}/{v}/",
            )
        upload_rollout = gui.add_upload_button(
            "Upload rollout NPZ", icon=None, mime_type=".npz",
            hint=f"a saved rollout (smln rollout, bench/physics_reference.py, the viewer's NPZ export), at most "
                 f"{MAX_ROLLOUT_UPLOAD_BYTES // 2**20} MB; shown as one more read-only variant on its own scene")
    with gui.add_folder("Inspect"):
        layer_pen = gui.add_checkbox("Inter-layer penetrations (red)", display.show_layer_pen)
        body_pen = gui.add_checkbox("Body penetrations (magenta)", display.show_body_pen)
        vectors = gui.add_checkbox(
            "Repulsion vectors", display.show_vectors,
            hint="the repulsion layer's push a at each garment vertex: out of the layer beneath, and out of the body "
                 "for checkpoints whose layer has the body stage (SMLNConfig.body_repulsion)")
        vector_scale = gui.add_slider("Vector scale (m per m/frame²)", min=1.0, max=500.0, step=1.0,
                                      initial_value=display.vector_scale)
        vector_threshold = gui.add_number("Vector threshold (m/frame²)", display.vector_threshold, min=0.0,
                                          step=1e-5)
        wireframe = gui.add_checkbox("Wireframe", display.wireframe)
        body = gui.add_checkbox("Show body", display.show_body)
        layers_folder = gui.add_folder("Layers")
    metrics_folder = gui.add_folder("Metrics")
    with gui.add_folder("Export"):
        export_variant = gui.add_dropdown("Variant to export", [VARIANT_LABELS[v] for v in variants] or ["—"])
        downloads = {fmt: gui.add_button(text) for fmt, text in
                     (("npz", "Download NPZ"), ("obj", "Download OBJ zip"), ("pc2", "Download PC2"),
                      ("glb", "Download GLB zip"))}
    return Controls(outfit, clip, shape, upload_bvh, upload_obj, checkpoint_note, play, frame, steps, speed, loop,
                    stream_fps, progress, status, follow, reset_camera, boxes, layer_pen,
                    body_pen, vectors, vector_scale, vector_threshold, wireframe, body, layers_folder,
                    metrics_folder, export_variant, downloads, outfit_keys, clip_keys,
                    variants_folder=variants_folder, upload_rollout=upload_rollout, projection=projection,
                    reading=reading)


def _label(keys: dict[str, str], key: str) -> str:
    return next((lab for lab, k in keys.items() if k == key), next(iter(keys)))


def checkpoint_text(catalog: Catalog) -> str:
    """One line on which checkpoints were found."""
    if not catalog.checkpoints:
        return (f"**No checkpoint found** in `{catalog.checkpoint_dir}`: showing skinning-only rollouts. "
                "Train one with `smln train`.")
    found = ", ".join(VARIANT_LABELS[v] for v in catalog.checkpoints)
    return f"Checkpoints: {found}."


def build_layer_controls(gui: viser.GuiApi, folder: Any, names: list[str], display: Display) -> list[tuple[Any, Any]]:
    """Per garment layer a visibility checkbox and a colour picker, inside ``folder``; resets
    ``display.layer_visible`` / ``layer_colours`` to match."""
    display.layer_visible = [True] * len(names)
    display.layer_colours = [LAYER_COLOURS[k % len(LAYER_COLOURS)] for k in range(len(names))]
    handles = []
    with folder:
        for k, name in enumerate(names):
            vis = gui.add_checkbox(f"{k}: {name}", True)
            rgb = gui.add_rgb(f"{k}: colour", display.layer_colours[k])
            handles.append((vis, rgb))
    return handles
