""":class:`ViewerApp`: the viser server, its shared GUI and scene, playback and the wiring of every control.

Sharing model: **one scene, one GUI and one computation for all browsers.** Every control acts on the shared
state (a second browser sees the first one's choices and the same frame); the rollout worker computes each
(setting, variant) once, whoever asked. Cameras stay per browser (follow / reset move every browser's camera);
notifications and downloads go to the browser that asked.

Threads: viser's callback threads call the public methods (guarded by one lock); the
:class:`~app.rollout_worker.RolloutWorker` computes frames; a playback thread advances the frame index and
pushes the shown frame to the scene at the streaming rate. Every callback catches its errors and shows a
notification: bad input never stops the server or changes what was shown.
"""

from __future__ import annotations

import collections
import functools
import threading
import time
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser

from app.controls import Controls, build_controls, build_layer_controls
from app.extras import ExtraRollout, ExtraRolloutError, ExtraStore, is_extra
from app.plots import MetricsPanel
from app.rollout_worker import FrameCache, RolloutWorker
from app.scene import Display, SceneView, ViewSpec
from app.sources import FPS, MAX_FRAMES, PROJECTIONS, READINGS, VARIANT_LABELS, VARIANTS, Catalog, Scenario, Setting
from app.uploads import UploadError, UploadStore
from smln.export import export_bytes, rollout_from_frames

CAMERA_OFFSET = np.array([0.0, -2.8, 0.35])
"""Default camera position relative to the look-at point (in front of the body, which faces -Y), m."""


def _guarded(method: Callable[..., Any]) -> Callable[..., Any]:
    """Wrap a GUI callback: any exception becomes a notification to the browser that acted."""

    @functools.wraps(method)
    def wrapper(self: ViewerApp, event: Any = None, *args: Any, **kwargs: Any) -> Any:
        try:
            return method(self, event, *args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - never let a callback kill the server
            traceback.print_exc()
            self.notify("Error", f"{type(exc).__name__}: {exc}", client=getattr(event, "client", None))
            return None

    return wrapper


class ViewerApp:
    """The SMLN viewer.

    Args:
        host, port: where viser listens (``port=0`` is not supported by viser: pick a free port).
        checkpoint_dir: directory with ``full/``, ``no_repulsion_layer/``, ``baseline/`` checkpoints.
        device: torch device for the model variants.
        catalog: a prepared :class:`~app.sources.Catalog` (tests inject one); built from the arguments if None.
        setting: the first setting (default: the catalog's default).
        variants: variants enabled at start (default: the full model if present, else skinning).
        max_frames: cap on frames per rollout.
        verbose: viser's own logging.
        extras: saved rollouts (an :class:`~app.extras.ExtraStore`, validated already) shown as more,
            read-only variants; all of them are enabled at start.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        checkpoint_dir: str | Path | None = "checkpoints",
        device: str = "cpu",
        catalog: Catalog | None = None,
        setting: Setting | None = None,
        variants: list[str] | None = None,
        max_frames: int = MAX_FRAMES,
        verbose: bool = False,
        extras: ExtraStore | None = None,
    ) -> None:
        self.uploads = UploadStore()
        self.extras = extras if extras is not None else ExtraStore()
        self._extra_caches: dict[str, FrameCache] = {}
        self._extra_scenario: Scenario | None = None
        if catalog is None:
            catalog = Catalog(checkpoint_dir, self.uploads, device, max_frames)
        elif catalog.uploads is None:
            catalog.uploads = self.uploads
        self.catalog = catalog
        self._lock = threading.RLock()
        self.display = Display()
        self.frame_index = 0
        self.playing = True
        self.speed = 1.0
        self.loop = True
        self.follow = True
        self.stream_fps = 30.0
        self._scenario: Scenario | None = None
        self._dirty = True
        self._last_centre: np.ndarray | None = None
        self._needs_camera_reset = True
        self.frames_pushed = 0
        self.push_seconds: collections.deque[float] = collections.deque(maxlen=1000)
        """Wall time of the most recent frame pushes (scene, GUI, metrics, camera), s."""
        start_variants = variants or (["full"] if "full" in catalog.checkpoints else ["skinning"])
        if variants is None:
            start_variants = [*start_variants, *self.extras.keys()]
        self._variants = self._ordered(start_variants)
        setting = setting or catalog.default_setting()

        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.gui.configure_theme(control_width="large")
        self.scene = SceneView(self.server)
        self.controls: Controls = build_controls(self.server.gui, catalog, setting, self._computed(), self.display)
        with self.controls.metrics_folder:
            self.metrics = MetricsPanel(self.server.gui)
        self._wire()
        for extra in self.extras.items():
            self._add_extra_checkbox(extra)
        self._refresh_export_options()
        self.server.on_client_connect(self._on_connect)
        self.worker = RolloutWorker(catalog, self._on_worker_event)
        self.worker.configure(setting, tuple(self._computed()))
        self._stop = threading.Event()
        self._player = threading.Thread(target=self._play_loop, name="smln-viewer-playback", daemon=True)
        self._player.start()

    # ---- public API (also used by tests and the bench) -----------------------------------------------------
    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{host}:{self.server.get_port()}"

    @property
    def setting(self) -> Setting | None:
        return self.worker.setting

    @property
    def variants(self) -> list[str]:
        return list(self._variants)

    def set_setting(self, outfit: str | None = None, clip: str | None = None, shape: str | None = None,
                    projection: str | None = None, reading: str | None = None) -> bool:
        """Change the outfit / clip / body shape (keys) / collision projection / repulsion-layer reading; restarts
        the rollouts. Returns True if it changed."""
        with self._lock:
            cur = self.worker.setting or self.catalog.default_setting()
            new = Setting(outfit or cur.outfit, clip or cur.clip, shape or cur.shape, projection or cur.projection,
                          reading or cur.reading)
            if new == cur:
                return False
            if new.outfit not in dict((k, 1) for _, k in self.catalog.outfits()):
                raise ValueError(f"unknown outfit {new.outfit!r}")
            if new.clip not in dict((k, 1) for _, k in self.catalog.clips()):
                raise ValueError(f"unknown clip {new.clip!r}")
            if new.shape not in self.catalog.shapes():
                raise ValueError(f"unknown body shape {new.shape!r}")
            if new.projection not in PROJECTIONS:
                raise ValueError(f"unknown collision projection {new.projection!r} (one of {', '.join(PROJECTIONS)})")
            if new.reading not in READINGS:
                raise ValueError(f"unknown repulsion-layer reading {new.reading!r} (one of {', '.join(READINGS)})")
            self.frame_index = 0
            self._needs_camera_reset = True
            self.worker.configure(new, tuple(self._computed()))
            self._sync_pickers(new)
            return True

    def set_variants(self, variants: list[str]) -> None:
        """Enable exactly these variants (in display order: the computed ones, then saved rollouts); unknown or
        unavailable ones are refused."""
        bad = [v for v in variants if v not in self.catalog.available_variants() and v not in self.extras]
        if bad:
            raise ValueError(f"variant(s) not available: {', '.join(bad)}")
        with self._lock:
            self._variants = self._ordered(variants)
            for v, box in self.controls.variants.items():
                if box.value != (v in self._variants):
                    box.value = v in self._variants
            self._refresh_export_options()
            if self.worker.setting is not None:
                self.worker.configure(self.worker.setting, tuple(self._computed()))
            self._dirty = True

    def label(self, variant: str) -> str:
        """Display name of a variant (a saved rollout's comes from its meta)."""
        extra = self.extras.get(variant)
        return extra.label if extra is not None else VARIANT_LABELS.get(variant, variant)

    def add_extra(self, source: str | Path | bytes, name: str | None = None, enable: bool = True) -> ExtraRollout:
        """Validate a saved rollout (a path or an upload's bytes) and offer it as a read-only variant.

        Raises:
            ExtraRolloutError: the file was refused (one-line reason); nothing changes.
        """
        extra = self.extras.add(source, name)
        with self._lock:
            self._add_extra_checkbox(extra)
            if enable:
                self.set_variants([*self._variants, extra.key])
            else:
                self._refresh_export_options()
        return extra

    def caches(self) -> dict[str, FrameCache]:
        """Frame caches of the enabled variants: the worker's computed ones and the saved rollouts' (complete;
        empty with ``error`` "other scene" when a rollout was made on another scene)."""
        out = dict(self.worker.caches)
        out.update({k: c for k, c in self._extra_caches.items() if k in self._variants})
        return out

    def available_frames(self) -> int:
        """Frames playable on the shared timeline: computed by every enabled computed variant (a variant that
        stopped on an error no longer holds the others back; 0 before the scenario is ready). Saved rollouts do
        not hold the timeline back (past their length they hold their last frame); with only saved rollouts
        enabled it is the longest one (capped at the clip's length)."""
        if not self.worker.ready():
            return 0
        computed = self._computed()
        if not computed:
            scenario = self.worker.scenario
            self._sync_extra_caches(scenario)
            lengths = [len(self._extra_caches[v]) for v in self._variants if v in self._extra_caches]
            return min(max(lengths, default=0), scenario.num_frames)
        caches = [self.worker.caches.get(v) for v in computed]
        if any(c is None for c in caches):
            return 0
        running = [len(c) for c in caches if not c.error]
        return min(running) if running else max((len(c) for c in caches), default=0)

    def seek(self, index: int) -> int:
        """Show frame ``index`` (clamped to the computed frames); returns the frame shown."""
        with self._lock:
            self.frame_index = int(np.clip(index, 0, max(self.available_frames() - 1, 0)))
            self._dirty = True
            return self.frame_index

    def step(self, delta: int) -> int:
        """Pause and move ``delta`` frames (wrapping when looping)."""
        with self._lock:
            self.set_playing(False)
            n = self.available_frames()
            target = self.frame_index + delta
            if self.loop and n and self._all_done():
                target %= n
            return self.seek(target)

    def _all_done(self) -> bool:
        caches = self.worker.caches
        return self.worker.ready() and all(v in caches and caches[v].done for v in self._computed())

    def _computed(self) -> list[str]:
        """Enabled variants the worker computes (not saved rollouts)."""
        return [v for v in self._variants if not is_extra(v)]

    def _ordered(self, variants: list[str] | tuple[str, ...]) -> list[str]:
        return [v for v in VARIANTS if v in variants] + [k for k in self.extras.keys() if k in variants]

    def set_playing(self, playing: bool) -> None:
        self.playing = bool(playing)
        self.controls.play.label = "Pause" if self.playing else "Play"

    def export(self, variant: str, fmt: str) -> tuple[str, bytes]:
        """The computed frames of ``variant`` as a download: (file name, bytes) in ``fmt`` (npz/obj/pc2/glb);
        a saved rollout is converted whole from its own arrays."""
        extra = self.extras.get(variant)
        if extra is not None:
            suffix, data = export_bytes(extra.rollout, fmt, include_body=fmt == "glb")
            return Path(extra.source).stem + suffix, data
        scenario = self._scenario
        cache = self.worker.caches.get(variant)
        if scenario is None or cache is None or len(cache) == 0:
            raise ValueError(f"no computed frames for {self.label(variant)} yet")
        frames = list(cache.frames)
        s = scenario.setting
        meta = {"outfit": s.outfit, "clip": s.clip, "shape": s.shape, "variant": variant, "complete": cache.done,
                "projection": s.projection, "reading": s.reading}
        r = rollout_from_frames(frames, scenario.cloth.faces, scenario.cloth.layer_index, scenario.body_faces,
                                scenario.layer_names, fps=FPS, meta=meta)
        suffix, data = export_bytes(r, fmt, include_body=fmt == "glb")
        stem = "_".join(x.replace("upload:", "upload-").replace(":", "-") for x in (s.outfit, s.clip, variant))
        if s.projection != "off":
            stem += "_projection-" + s.projection.replace("+", "-")
        if s.reading != "checkpoint":
            stem += "_reading-" + s.reading
        return stem + suffix, data

    def notify(self, title: str, body: str, client: Any = None, error: bool = True) -> None:
        """A notification to one browser (or all when ``client`` is None)."""
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for c in clients:
            try:
                c.add_notification(title, body, color="red" if error else "blue", auto_close_seconds=10.0)
            except Exception:  # noqa: BLE001 - a browser that just left
                pass

    def stop(self) -> None:
        """Stop playback, the worker and the server; remove uploads."""
        self._stop.set()
        self._player.join(5.0)
        self.worker.stop()
        self.server.stop()
        self.uploads.close()

    # ---- wiring ----------------------------------------------------------------------------------------------
    def _wire(self) -> None:
        c = self.controls
        c.outfit.on_update(self._on_outfit)
        c.clip.on_update(self._on_clip)
        c.shape.on_update(self._on_shape)
        c.projection.on_update(self._on_projection)
        if c.reading is not None:
            c.reading.on_update(self._on_reading)
        c.upload_bvh.on_upload(self._on_upload_bvh)
        c.upload_obj.on_upload(self._on_upload_obj)
        c.upload_rollout.on_upload(self._on_upload_rollout)
        c.play.on_click(self._on_play)
        c.frame.on_update(self._on_frame)
        c.steps.on_click(self._on_step)
        c.speed.on_click(self._on_speed)
        c.loop.on_update(self._on_loop)
        c.stream_fps.on_update(self._on_stream_fps)
        c.follow.on_update(self._on_follow)
        c.reset_camera.on_click(self._on_reset_camera)
        for box in c.variants.values():
            box.on_update(self._on_variant)
        for h in (c.layer_pen, c.body_pen, c.vectors, c.vector_scale, c.vector_threshold, c.wireframe, c.body):
            h.on_update(self._on_display)
        for fmt, button in c.downloads.items():
            button.on_click(functools.partial(self._on_download, fmt=fmt))

    @_guarded
    def _on_outfit(self, event: Any) -> None:
        if event.client is not None:
            self._apply_picker(outfit=self.controls.outfit_keys[self.controls.outfit.value])

    @_guarded
    def _on_clip(self, event: Any) -> None:
        if event.client is not None:
            self._apply_picker(clip=self.controls.clip_keys[self.controls.clip.value])

    @_guarded
    def _on_shape(self, event: Any) -> None:
        if event.client is not None:
            self._apply_picker(shape=self.controls.shape.value)

    @_guarded
    def _on_projection(self, event: Any) -> None:
        if event.client is not None:
            self._apply_picker(projection=self.controls.projection.value)

    @_guarded
    def _on_reading(self, event: Any) -> None:
        if event.client is not None:
            self._apply_picker(reading=self.controls.reading.value)

    def _apply_picker(self, **kwargs: str) -> None:
        try:
            self.set_setting(**kwargs)
        except Exception:
            self._sync_pickers(self.worker.setting)
            raise

    def _sync_pickers(self, s: Setting | None) -> None:
        """Show ``s`` in the pickers (after a programmatic change or a refused one)."""
        if s is None:
            return
        c = self.controls
        lab = c.outfit_label(s.outfit)
        if lab is not None and c.outfit.value != lab:
            c.outfit.value = lab
        lab = c.clip_label(s.clip)
        if lab is not None and c.clip.value != lab:
            c.clip.value = lab
        if c.shape.value != s.shape:
            c.shape.value = s.shape
        if c.projection is not None and c.projection.value != s.projection:
            c.projection.value = s.projection
        if c.reading is not None and c.reading.value != s.reading:
            c.reading.value = s.reading

    @_guarded
    def _on_upload_bvh(self, event: Any) -> None:
        f = event.target.value
        shape = (self.worker.setting or self.catalog.default_setting()).shape
        try:
            key = self.uploads.add_bvh(f.name, f.content, shape)
        except UploadError as exc:
            self.notify("Clip refused", str(exc), client=event.client)
            return
        self._refresh_options()
        self.set_setting(clip=key)
        self.notify("Clip loaded", f"{f.name} is now playing", client=event.client, error=False)

    @_guarded
    def _on_upload_obj(self, event: Any) -> None:
        f = event.target.value
        shape = (self.worker.setting or self.catalog.default_setting()).shape
        try:
            key = self.uploads.add_obj(f.name, f.content, shape)
        except UploadError as exc:
            self.notify("Garment refused", str(exc), client=event.client)
            return
        self._refresh_options()
        self.set_setting(outfit=key)
        note = self.uploads.note(key)
        self.notify("Garment loaded", f"{f.name} is now shown" + (f" ({note})" if note else ""), client=event.client,
                    error=False)

    @_guarded
    def _on_upload_rollout(self, event: Any) -> None:
        f = event.target.value
        try:
            extra = self.add_extra(f.content, f.name)
        except ExtraRolloutError as exc:
            self.notify("Rollout refused", str(exc), client=event.client)
            return
        where = ("" if extra.matches(self.setting) else
                 f"; it was made on {extra.scene_text()}: pick that scene to see it")
        self.notify("Rollout loaded", f"{f.name}: {extra.num_frames} frames, shown as “{extra.label}”{where}",
                    client=event.client, error=False)

    def _add_extra_checkbox(self, extra: ExtraRollout) -> None:
        """A Variants checkbox for a saved rollout (under the upload button)."""
        with self.controls.variants_folder:
            box = self.server.gui.add_checkbox(
                extra.label, extra.key in self._variants,
                hint=f"saved rollout {extra.source}: {extra.num_frames} frames on {extra.scene_text()} (read-only)")
        box.on_update(self._on_variant)
        self.controls.variants[extra.key] = box

    def _refresh_export_options(self) -> None:
        labels = [self.label(v) for v in self._variants] or ["—"]
        if list(self.controls.export_variant.options) != labels:
            self.controls.export_variant.options = labels

    def _refresh_options(self) -> None:
        c = self.controls
        c.outfit_keys = dict(self.catalog.outfits())
        c.clip_keys = dict(self.catalog.clips())
        c.outfit.options = list(c.outfit_keys)
        c.clip.options = list(c.clip_keys)

    @_guarded
    def _on_play(self, event: Any) -> None:
        self.set_playing(not self.playing)

    @_guarded
    def _on_frame(self, event: Any) -> None:
        if event.client is not None:  # a browser scrubbed (programmatic updates come from playback)
            self.seek(int(self.controls.frame.value))

    @_guarded
    def _on_step(self, event: Any) -> None:
        self.step(int(str(self.controls.steps.value).strip("◀▶ ")))

    @_guarded
    def _on_speed(self, event: Any) -> None:
        self.speed = float(str(self.controls.speed.value).rstrip("x"))

    @_guarded
    def _on_loop(self, event: Any) -> None:
        self.loop = bool(self.controls.loop.value)

    @_guarded
    def _on_stream_fps(self, event: Any) -> None:
        self.stream_fps = float(self.controls.stream_fps.value)

    @_guarded
    def _on_follow(self, event: Any) -> None:
        self.follow = bool(self.controls.follow.value)
        self._last_centre = None

    @_guarded
    def _on_reset_camera(self, event: Any) -> None:
        self._needs_camera_reset = True

    @_guarded
    def _on_variant(self, event: Any) -> None:
        if event.client is None:
            return
        wanted = [v for v, box in self.controls.variants.items() if box.value]
        self.set_variants(wanted)

    @_guarded
    def _on_display(self, event: Any) -> None:
        c, d = self.controls, self.display
        d.show_layer_pen, d.show_body_pen, d.show_vectors = c.layer_pen.value, c.body_pen.value, c.vectors.value
        d.vector_scale, d.vector_threshold = float(c.vector_scale.value), max(float(c.vector_threshold.value), 0.0)
        d.wireframe, d.show_body = c.wireframe.value, c.body.value
        for k, (vis, rgb) in enumerate(c.layer_handles):
            d.layer_visible[k] = bool(vis.value)
            d.layer_colours[k] = tuple(int(x) for x in rgb.value)
        self._dirty = True

    @_guarded
    def _on_download(self, event: Any, fmt: str) -> None:
        label = self.controls.export_variant.value
        variant = next((v for v in self._variants if self.label(v) == label), None)
        if variant is None:
            raise ValueError("enable a variant to export")
        note = event.client.add_notification("Exporting", f"{label} as {fmt.upper()} …", loading=True,
                                             with_close_button=False) if event.client else None
        try:
            name, data = self.export(variant, fmt)
        finally:
            if note is not None:
                note.remove()
        if event.client is not None:
            event.client.send_file_download(name, data)

    def _on_connect(self, client: viser.ClientHandle) -> None:
        try:
            centre = self._last_centre if self._last_centre is not None else np.array([0.0, 0.0, 1.0])
            self._place_camera(client, centre)
        except Exception:  # noqa: BLE001
            traceback.print_exc()

    def _on_worker_event(self, event: str, info: dict[str, Any]) -> None:
        if event == "error":
            self.notify("Rollout problem", info.get("message", "unknown error"))
        self._dirty = True

    # ---- playback --------------------------------------------------------------------------------------------
    def _play_loop(self) -> None:
        last = time.monotonic()
        clock = 0.0
        while not self._stop.is_set():
            period = 1.0 / max(self.stream_fps, 1.0)
            time.sleep(max(0.0, period - (time.monotonic() - last)))
            now = time.monotonic()
            dt, last = now - last, now
            try:
                with self._lock:
                    clock = self._tick(dt, clock)
            except Exception:  # noqa: BLE001 - keep playing whatever happens
                traceback.print_exc()
                time.sleep(0.5)

    def _tick(self, dt: float, clock: float) -> float:
        """Advance playback by ``dt`` seconds and push the shown frame if anything changed."""
        scenario = self.worker.scenario if self.worker.ready() else None
        if scenario is not self._scenario:
            self._on_new_scenario(scenario)
        if scenario is None:
            self.controls.status.content = "loading the outfit and the clip …"
            return clock
        variants = self._shown(scenario)
        if [v for v in self.scene.views] != variants:
            self.scene.sync(scenario, variants, self.display, self._specs(scenario))
            self.metrics.rebuild(variants, scenario.num_frames, self._labels())
            self._dirty = True
        caches = self.caches()
        n = self.available_frames()
        all_done = all(v in caches and caches[v].done for v in variants)
        if self.frame_index > max(n - 1, 0):  # a variant was added: wait for it on the shared timeline
            self.frame_index = max(n - 1, 0)
            self._dirty = True
        if self.playing and n:
            clock += dt * FPS * self.speed
            steps = int(clock)
            clock -= steps
            if steps:
                target = self.frame_index + steps
                if target >= n:
                    target = (target % n) if (self.loop and all_done) else n - 1
                if target != self.frame_index:
                    self.frame_index = target
                    self._dirty = True
        else:
            clock = 0.0
        self._update_status(scenario, caches, list(self._variants), n)
        self.metrics.update(caches, self.frame_index, count=n)  # throttled; catches up on computed frames
        if not self._dirty:
            return clock
        self._dirty = False
        t0 = time.perf_counter()
        idx = self.frame_index
        frames = {v: caches[v].get(idx) if v in caches else None for v in variants}
        status = {v: self._extra_status(v, idx) if is_extra(v) else
                  self._variant_status(caches.get(v), idx, scenario.num_frames) for v in variants}
        with self.server.atomic():
            self.scene.apply_display(self.display)
            self.scene.show(frames, self.display, status)
            if self.controls.frame.value != idx:
                self.controls.frame.value = idx
        self._camera(frames)
        self.frames_pushed += 1
        self.push_seconds.append(time.perf_counter() - t0)
        return clock

    def _sync_extra_caches(self, scenario: Scenario | None) -> None:
        """One complete cache per saved rollout for ``scenario`` (empty if the rollout is of another scene)."""
        if scenario is not self._extra_scenario:
            self._extra_caches, self._extra_scenario = {}, scenario
        for extra in self.extras.items():
            if extra.key in self._extra_caches:
                continue
            ok = extra.matches(scenario.setting) if scenario is not None else False
            self._extra_caches[extra.key] = FrameCache(extra.key, extra.num_frames, list(extra.frames) if ok else [],
                                                       done=True, error="" if ok else "other scene")

    def _shown(self, scenario: Scenario | None) -> list[str]:
        """Enabled variants drawn on ``scenario``: a saved rollout of another scene is hidden (the status line
        and its checkbox's hint say which scene it is for)."""
        self._sync_extra_caches(scenario)
        return [v for v in self._variants if not is_extra(v) or not self._extra_caches[v].error]

    def _specs(self, scenario: Scenario) -> dict[str, ViewSpec]:
        """How to draw the saved rollouts (from their own arrays)."""
        return {e.key: ViewSpec(e.label, e.geometry) for e in self.extras.items()}

    def _labels(self) -> dict[str, str]:
        return {e.key: e.label for e in self.extras.items()}

    def _extra_status(self, variant: str, idx: int) -> str:
        extra = self.extras.get(variant)
        if extra is None:
            return ""
        note = f"{extra.note}\n" if extra.note else ""
        if idx >= extra.num_frames:
            return note + f"saved rollout: holding its last frame ({extra.num_frames - 1})"
        return note + f"saved rollout ({extra.num_frames} frames)"

    def _on_new_scenario(self, scenario: Scenario | None) -> None:
        self._scenario = scenario
        shown = self._shown(scenario)
        self.scene.sync(scenario, shown, self.display, self._specs(scenario) if scenario is not None else None)
        c = self.controls
        for vis, rgb in c.layer_handles:
            vis.remove()
            rgb.remove()
        c.layer_handles = []
        if scenario is None:
            return
        c.layer_handles = build_layer_controls(self.server.gui, c.layers_folder, scenario.layer_names, self.display)
        for vis, rgb in c.layer_handles:
            vis.on_update(self._on_display)
            rgb.on_update(self._on_display)
        c.frame.max = max(scenario.num_frames - 1, 1)
        self.metrics.rebuild(shown, scenario.num_frames, self._labels())
        self.frame_index = 0
        self._dirty = True

    @staticmethod
    def _variant_status(cache: Any, idx: int, total: int) -> str:
        if cache is None:
            return "starting …"
        if cache.error:
            return f"stopped at frame {len(cache)}: {cache.error[:60]}"
        frame = cache.get(idx)
        if frame is not None and frame.fallback:
            return "diverged: skinning fallback"
        if idx >= len(cache) and not cache.done:
            return f"computing {len(cache)}/{total}"
        return ""

    def _update_status(self, scenario: Scenario, caches: dict[str, Any], variants: list[str], n: int) -> None:
        computed = [v for v in variants if not is_extra(v)]
        total = scenario.num_frames * max(len(computed), 1)
        done = sum(min(len(caches[v]), scenario.num_frames) if v in caches else 0 for v in computed)
        if not computed:
            done = total
        value = 100.0 * done / max(total, 1)
        c = self.controls
        if abs(c.progress.value - value) > 0.5 or (value >= 100.0 and c.progress.value < 100.0):
            c.progress.value = value
            c.progress.animated = value < 100.0
        parts = [f"{VARIANT_LABELS[v]} {len(caches[v]) if v in caches else 0}/{scenario.num_frames}"
                 for v in computed]
        for v in variants:
            if is_extra(v):
                e = self.extras.get(v)
                parts.append(f"{e.label} saved, {e.num_frames} frames" if e.matches(scenario.setting)
                             else f"{e.label} hidden: made on {e.scene_text()}")
        text = f"frame **{self.frame_index}** of {scenario.num_frames} · computed: " + ", ".join(parts)
        if c.status.content != text:
            c.status.content = text

    # ---- camera ----------------------------------------------------------------------------------------------
    def _spread(self) -> float:
        """Camera distance factor: wider for more variants side by side."""
        return 1.0 + 0.3 * max(len(self.scene.views) - 1, 0)

    def _place_camera(self, client: viser.ClientHandle, centre: np.ndarray) -> None:
        look = centre + np.array([0.0, 0.0, -0.05])
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = tuple(look + CAMERA_OFFSET * self._spread())
            client.camera.look_at = tuple(look)

    def _camera(self, frames: dict[str, Any]) -> None:
        centre = self.scene.centre(frames)
        if centre is None:
            return
        if self._needs_camera_reset:
            self._needs_camera_reset = False
            for client in self.server.get_clients().values():
                self._place_camera(client, centre)
            self._last_centre = centre
            return
        if self.follow and self._last_centre is not None:
            delta = centre - self._last_centre
            if np.abs(delta[:2]).max() > 1e-3:
                look = centre + np.array([0.0, 0.0, -0.05])
                orbit = CAMERA_OFFSET * self._spread()  # follow keeps the default view (turn it off to orbit)
                for client in self.server.get_clients().values():
                    cam = client.camera
                    with client.atomic(), warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # a browser that is just leaving
                        cam.look_at = tuple(look)
                        cam.position = tuple(look + orbit)
                self._last_centre = centre
            return
        self._last_centre = centre
