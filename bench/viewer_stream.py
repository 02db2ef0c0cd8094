"""Viewer streaming benchmark: frames streamed per second and bytes per frame, one and three variants.

    python bench/viewer_stream.py [--json OUT] [--seconds 4] [--windows 3] [--frames 60]

Plays back *cached* frames (the target is 30 fps) of the default outfit and clip to one connected websocket
client (a raw viser client that only counts bytes, no rendering). Streaming cost does not depend on how frames
were computed, so the three-variant case uses skinning frames under three variant names, with a synthetic
repulsion acceleration on ~2,000 vertices so that vectors are drawn as they would be for a model with the
repulsion layer. Reports the median over ``--windows`` windows of: frames pushed per second, bytes received
per frame, MB/s, and the server-side push time per frame (scene + GUI + metrics + camera).
"""

from __future__ import annotations

import argparse
import json
import statistics
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import viser
from websockets.sync.client import connect

from app.server import ViewerApp
from app.sources import VARIANTS, Catalog, Scenario, skinning_frames


class StreamCatalog(Catalog):
    """Every variant yields skinning frames (plus synthetic repulsion vectors for the model variants)."""

    def available_variants(self) -> list[str]:
        return list(VARIANTS)

    def frames(self, variant: str, scenario: Scenario) -> Any:
        rng = np.random.default_rng(0)
        n = scenario.cloth.num_vertices
        pick = rng.choice(n, size=min(2000, n), replace=False)
        for f in skinning_frames(scenario):
            if variant != "skinning":
                a = np.zeros((n, 3), np.float32)
                a[pick] = rng.normal(scale=2e-4, size=(len(pick), 3)).astype(np.float32)
                f.repulsion_acceleration = a
            yield f


class ByteCounter:
    """A raw viser websocket client in a thread that counts the bytes it receives."""

    def __init__(self, url: str) -> None:
        self.bytes = 0
        self.messages = 0
        self._stop = threading.Event()
        self._ws = connect(url.replace("http", "ws"), subprotocols=[f"viser-v{viser.__version__}"],
                           max_size=None, compression=None)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self._ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            except Exception:  # noqa: BLE001 - closed
                return
            self.bytes += len(msg)
            self.messages += 1

    def close(self) -> None:
        self._stop.set()
        self._ws.close()
        self._thread.join(2.0)


def measure(app: ViewerApp, counter: ByteCounter, seconds: float, windows: int) -> dict[str, float]:
    """Median streaming figures over ``windows`` windows of ``seconds`` seconds of looping playback."""
    app.set_playing(True)
    time.sleep(1.0)  # settle
    fps, bpf, mbs, push = [], [], [], []
    for _ in range(windows):
        f0, b0 = app.frames_pushed, counter.bytes
        app.push_seconds.clear()
        t0 = time.monotonic()
        time.sleep(seconds)
        dt = time.monotonic() - t0
        frames, nbytes = app.frames_pushed - f0, counter.bytes - b0
        fps.append(frames / dt)
        bpf.append(nbytes / max(frames, 1))
        mbs.append(nbytes / dt / 1e6)
        push.append(1e3 * statistics.median(app.push_seconds) if app.push_seconds else float("nan"))
    return {
        "fps_median": round(statistics.median(fps), 2),
        "bytes_per_frame_median": int(statistics.median(bpf)),
        "mb_per_s_median": round(statistics.median(mbs), 2),
        "push_ms_median": round(statistics.median(push), 2),
        "fps_windows": [round(x, 2) for x in fps],
    }


def main(argv: list[str] | None = None) -> dict[str, Any]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", default=None, help="write the results to this JSON file")
    p.add_argument("--seconds", type=float, default=4.0, help="length of one measuring window, s")
    p.add_argument("--windows", type=int, default=3)
    p.add_argument("--frames", type=int, default=60, help="cached frames played in a loop")
    p.add_argument("--port", type=int, default=8091)
    args = p.parse_args(argv)

    catalog = StreamCatalog(None, max_frames=args.frames)
    app = ViewerApp(port=args.port, catalog=catalog, variants=["skinning"])
    results: dict[str, Any] = {"setting": str(app.setting), "target_fps": 30, "cached_frames": args.frames}
    counter = ByteCounter(app.url)
    try:
        for label, variants in (("one_variant", ["skinning"]), ("three_variants", ["full", "baseline", "skinning"])):
            app.set_variants(variants)
            if not app.worker.wait_frames(args.frames, timeout=300):
                raise RuntimeError("frames were not computed in time")
            scenario = app.worker.scenario
            results[label] = measure(app, counter, args.seconds, args.windows)
            results[label]["garment_vertices"] = scenario.cloth.num_vertices
            results[label]["body_vertices"] = int(scenario.sequence.vertices.shape[1])
            print(label, json.dumps(results[label]), flush=True)
    finally:
        counter.close()
        app.stop()
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
