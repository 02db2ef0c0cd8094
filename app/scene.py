"""The 3-D scene: per variant a body, one mesh per garment layer, penetration overlays, repulsion vectors and a
label, all under a frame node offset along X so that enabled variants stand side by side.

Per displayed frame only vertex arrays and overlay points change (``handle.vertices = ...``, coalesced by
viser); the caller wraps :meth:`SceneView.show` in ``server.atomic()`` so each frame lands at once.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import viser

from app.extras import Geometry
from app.sources import VARIANT_LABELS, Scenario

VARIANT_SPACING = 1.2
"""Distance between neighbouring variants along X, meters."""

LAYER_COLOURS: tuple[tuple[int, int, int], ...] = ((70, 130, 220), (235, 150, 60), (90, 185, 110), (175, 95, 205))
"""Default colour per garment layer, inner -> outer (cycled)."""
BODY_COLOUR = (205, 195, 185)
LAYER_PEN_COLOUR = (255, 30, 30)
"""Overlay colour of vertices behind the layer beneath them (inter-layer penetration)."""
BODY_PEN_COLOUR = (255, 0, 230)
"""Overlay colour of vertices inside the body."""


@dataclass
class Display:
    """Display options shared by all variants.

    Attributes:
        show_body, wireframe: body visibility, garments drawn as wireframes.
        layer_visible, layer_colours: per garment layer (inner -> outer).
        show_layer_pen, show_body_pen: penetration overlays.
        show_vectors: repulsion accelerations as segments; vector_scale: drawn length per acceleration,
            m per (m/frame^2); vector_threshold: smallest |a| drawn, m/frame^2; max_vectors: the largest
            ``max_vectors`` are drawn at most.
        point_size: overlay point size, m.
    """

    show_body: bool = True
    wireframe: bool = False
    layer_visible: list[bool] = field(default_factory=list)
    layer_colours: list[tuple[int, int, int]] = field(default_factory=list)
    show_layer_pen: bool = True
    show_body_pen: bool = True
    show_vectors: bool = True
    vector_scale: float = 50.0
    vector_threshold: float = 1e-5
    max_vectors: int = 2000
    point_size: float = 0.008

    def colour(self, k: int) -> tuple[int, int, int]:
        if k < len(self.layer_colours):
            return self.layer_colours[k]
        return LAYER_COLOURS[k % len(LAYER_COLOURS)]

    def visible(self, k: int) -> bool:
        return self.layer_visible[k] if k < len(self.layer_visible) else True


def magnitude_colours(mag: np.ndarray, low: float, high: float) -> np.ndarray:
    """Yellow (low) -> red (high) colours for magnitudes: (N,) -> (N, 3) uint8."""
    s = np.clip((mag - low) / max(high - low, 1e-12), 0.0, 1.0)[:, None]
    return (np.array([255, 230, 40]) * (1 - s) + np.array([220, 20, 20]) * s).astype(np.uint8)


def repulsion_segments(
    x: np.ndarray, a: np.ndarray, scale: float, threshold: float, max_count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Line segments for repulsion accelerations.

    Args:
        x: (V, 3) positions, m; a: (V, 3) accelerations, m/frame^2; scale: m per (m/frame^2);
        threshold: smallest |a| kept; max_count: keep the largest ones only.

    Returns:
        points (N, 2, 3) float32 and colours (N, 2, 3) uint8 (N may be 0).
    """
    mag = np.linalg.norm(a, axis=1)
    idx = np.flatnonzero(mag > threshold)
    if len(idx) > max_count:
        idx = idx[np.argpartition(mag[idx], -max_count)[-max_count:]]
    pts = np.stack([x[idx], x[idx] + scale * a[idx]], axis=1).astype(np.float32)
    col = magnitude_colours(mag[idx], threshold, float(mag[idx].max()) if len(idx) else 1.0)
    return pts, np.repeat(col[:, None], 2, axis=1)


@dataclass
class ViewSpec:
    """How one variant is drawn: its label and its meshes."""

    label: str
    geometry: Geometry


def scenario_geometry(scenario: Scenario) -> Geometry:
    """The meshes of a computed variant: the scenario's cloth layers (rest shape) and its body (frame 0)."""
    return Geometry(list(scenario.layer_slices), scenario.layer_faces, scenario.body_faces,
                    scenario.cloth.rest_vertices.numpy(), scenario.sequence.vertices[0].numpy())


class VariantView:
    """The scene nodes of one variant (under ``/variants/<variant>``)."""

    def __init__(self, scene: viser.SceneApi, variant: str, scenario: Scenario, offset: float,
                 display: Display, spec: ViewSpec | None = None) -> None:
        self.variant = variant
        self.scenario = scenario
        spec = spec or ViewSpec(VARIANT_LABELS.get(variant, variant), scenario_geometry(scenario))
        self.spec = spec
        g = spec.geometry
        self.layer_vertices = g.layer_vertices
        root = f"/variants/{variant}"
        self.root = scene.add_frame(root, show_axes=False, position=(offset, 0.0, 0.0))
        self.body = scene.add_mesh_simple(f"{root}/body", g.body0, g.body_faces, color=BODY_COLOUR,
                                          visible=display.show_body)
        self.layers = [
            scene.add_mesh_simple(f"{root}/layer_{k}", g.garment0[s], f, color=display.colour(k), side="double",
                                  wireframe=display.wireframe, visible=display.visible(k))
            for k, (s, f) in enumerate(zip(g.layer_vertices, g.layer_faces, strict=True))
        ]
        one = np.zeros((1, 3), np.float32)
        self.layer_pen = scene.add_point_cloud(f"{root}/layer_penetration", one, LAYER_PEN_COLOUR,
                                               point_size=display.point_size, point_shape="circle", visible=False)
        self.body_pen = scene.add_point_cloud(f"{root}/body_penetration", one, BODY_PEN_COLOUR,
                                              point_size=display.point_size, point_shape="circle", visible=False)
        self.vectors = scene.add_line_segments(f"{root}/repulsion", np.zeros((1, 2, 3), np.float32),
                                               (255, 200, 0), thickness=0.003, visible=False)
        self.label = scene.add_label(f"{root}/label", spec.label, position=(0.0, 0.0, 2.0),
                                     anchor="bottom-center", font_screen_scale=1.2)
        self.shown_index = -1
        self._label_text = ""

    def set_offset(self, offset: float) -> None:
        self.root.position = (offset, 0.0, 0.0)

    def apply_display(self, d: Display) -> None:
        """Visibility, colours and wireframe (only properties that changed are sent)."""
        _set(self.body, "visible", d.show_body)
        for k, mesh in enumerate(self.layers):
            _set(mesh, "visible", d.visible(k))
            _set(mesh, "color", tuple(int(c) for c in d.colour(k)))
            _set(mesh, "wireframe", d.wireframe)
        for pc in (self.layer_pen, self.body_pen):
            _set(pc, "point_size", d.point_size)

    def show(self, frame: Any, d: Display, status: str = "") -> None:
        """Show one :class:`smln.rollout.RolloutFrame` (or nothing yet if None)."""
        label = self.spec.label + (f"\n{status}" if status else "")
        if label != self._label_text:
            self.label.text = label
            self._label_text = label
        if frame is None:
            return
        x = frame.garment_positions
        body = frame.body_vertices
        self.body.vertices = body
        for k, (mesh, s) in enumerate(zip(self.layers, self.layer_vertices, strict=True)):
            if d.visible(k):
                mesh.vertices = x[s]
        visible_v = np.ones(len(x), dtype=bool)
        for k, s in enumerate(self.layer_vertices):
            visible_v[s] = d.visible(k)
        _points(self.layer_pen, x[frame.layer_penetration & visible_v], d.show_layer_pen, LAYER_PEN_COLOUR)
        _points(self.body_pen, x[frame.body_penetration & visible_v], d.show_body_pen, BODY_PEN_COLOUR)
        if d.show_vectors:
            a = np.where(visible_v[:, None], frame.repulsion_acceleration, 0.0)
            pts, col = repulsion_segments(x, a, d.vector_scale, d.vector_threshold, d.max_vectors)
            if len(pts):
                self.vectors.points = pts
                self.vectors.colors = col
            _set(self.vectors, "visible", bool(len(pts)))
        else:
            _set(self.vectors, "visible", False)
        # above the body's centroid (the bounding-box centre moves toward an outstretched arm)
        centroid = body.mean(axis=0)
        self.label.position = (float(centroid[0]), float(centroid[1]), float(body[:, 2].max() + 0.25))
        self.shown_index = int(frame.index)

    def remove(self) -> None:
        self.root.remove()


def _set(handle: Any, name: str, value: Any) -> None:
    """Set a handle property only if it changed (saves messages)."""
    if getattr(handle, name) != value:
        setattr(handle, name, value)


def _points(handle: Any, pts: np.ndarray, enabled: bool, colour: tuple[int, int, int]) -> None:
    """Update an overlay point cloud with (N, 3) points in one colour; hide it when empty or disabled."""
    if enabled and len(pts):
        handle.points = pts.astype(np.float32)
        handle.colors = np.tile(np.array(colour, dtype=np.uint8), (len(pts), 1))
        _set(handle, "visible", True)
    else:
        _set(handle, "visible", False)


class SceneView:
    """All variants' nodes, laid out side by side along X (centred on x = 0)."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self.views: dict[str, VariantView] = {}
        self.scenario: Scenario | None = None
        server.scene.set_up_direction("+z")
        server.scene.add_grid("/floor", width=12.0, height=12.0, plane="xy", cell_size=0.5, section_size=1.0)

    @staticmethod
    def offsets(variants: list[str]) -> dict[str, float]:
        """X offset per variant (m), in the given order, centred on 0."""
        n = len(variants)
        return {v: (i - 0.5 * (n - 1)) * VARIANT_SPACING for i, v in enumerate(variants)}

    def sync(self, scenario: Scenario | None, variants: list[str], display: Display,
             specs: dict[str, ViewSpec] | None = None) -> None:
        """Create, remove and re-place variant nodes to match ``variants`` on ``scenario`` (``specs``: how to draw
        variants that do not use the scenario's meshes, e.g. saved rollouts)."""
        if scenario is not self.scenario:
            for view in self.views.values():
                view.remove()
            self.views = {}
            self.scenario = scenario
        if scenario is None:
            return
        offsets = self.offsets(variants)
        for v in [v for v in self.views if v not in offsets]:
            self.views.pop(v).remove()
        for v, off in offsets.items():
            if v in self.views:
                self.views[v].set_offset(off)
            else:
                self.views[v] = VariantView(self.server.scene, v, scenario, off, display, (specs or {}).get(v))

    def apply_display(self, display: Display) -> None:
        for view in self.views.values():
            view.apply_display(display)

    def show(self, frames: dict[str, Any], display: Display, status: dict[str, str]) -> None:
        """Show each variant's frame (``frames[variant]`` may be None while nothing is computed)."""
        for v, view in self.views.items():
            view.show(frames.get(v), display, status.get(v, ""))

    def centre(self, frames: dict[str, Any]) -> np.ndarray | None:
        """(3,) centre of the row of bodies, m; None before the first frame.

        Every variant moves the same body and the row is laid out centred on x = 0, so the centre is the body's
        centroid whichever variants already have the frame. (Averaging only the variants that have it moved the
        camera sideways by up to half the row whenever one variant was slower than another.)
        """
        pts = [f.body_vertices.mean(axis=0) for v, f in frames.items() if f is not None and v in self.views]
        return np.mean(pts, axis=0) if pts else None
