"""The viewer server under load: many websocket clients while a rollout plays (issue 9).

- 10 concurrent websocket clients (viser's own protocol: a websocket on the page's port with the
  ``viser-v<version>`` subprotocol) for a bounded time, 8 reading every message and 2 that never read (a stalled
  browser tab), while the viewer computes and plays a rollout;
- meanwhile the page is served quickly over HTTP, a GUI action sent by a client over the websocket
  (a ``GuiUpdateMessage`` on the *Loop* checkbox) is answered, and the playback keeps moving;
- frame caches stay within their capacity and the process memory (RSS) stays bounded;
- the thread count returns to its baseline after the clients leave;
- binding to anything but localhost needs ``--allow-remote`` and prints a warning (``launch_viewer.py``);
- the upload size limits are the ones the README states.
"""

from __future__ import annotations

import asyncio
import re
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
CLIENTS = 10
STALLED = 2
"""Clients that connect and never read a message."""
LOAD_SECONDS = 15.0
MAX_RSS_GROWTH_MB = 400.0
"""Allowed growth of the viewer process's resident memory under load, MB."""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _proc_status(field: str) -> int:
    """A numeric field of /proc/self/status (``VmRSS`` in kB, ``Threads``)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def _python_threads() -> tuple[list[str], int]:
    """Names of the live Python threads outside thread pools, and the number of pool workers."""
    names = [t.name for t in threading.enumerate() if t.is_alive()]
    pool = [n for n in names if n.startswith("ThreadPoolExecutor")]
    return sorted(n for n in names if n not in pool and n != "load-probe"), len(pool)


def _tiny_full_checkpoint(directory: Path) -> Path:
    """An untrained small ``full`` checkpoint, so the model path (not only skinning) runs under load."""
    from smln.checkpoint import save_checkpoint
    from smln.model.smln import SMLN, SMLNConfig

    save_checkpoint(f"{directory / 'full'}/", SMLN(SMLNConfig(latent_size=16)), card={"variant": "full"})
    return directory


async def _client(url: str, seconds: float, read: bool, stats: dict[str, int], outbox: asyncio.Queue | None) -> None:
    """One viser websocket client: connect, read (or not) for ``seconds``, send queued messages, leave."""
    import viser
    from websockets.asyncio.client import connect

    async with connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None,
                       open_timeout=30) as ws:
        await ws.send(_camera_message())  # a browser reports its camera first; viser counts it connected then
        stats["connected"] += 1
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if outbox is not None and not outbox.empty():
                await ws.send(outbox.get_nowait())
            if not read:
                await asyncio.sleep(0.1)
                continue
            try:
                msg = await asyncio.wait_for(ws.recv(), timeout=0.2)
            except TimeoutError:
                continue
            stats["messages"] += 1
            stats["bytes"] += len(msg)


def _camera_message() -> bytes:
    """The first message a viser browser sends: its camera (viser registers the client on it)."""
    import msgspec

    return msgspec.msgpack.encode({
        "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, -3.0, 1.0], "fov": 1.0,
        "near": 0.01, "far": 100.0, "image_height": 720, "image_width": 1280, "look_at": [0.0, 0.0, 1.0],
        "up_direction": [0.0, 0.0, 1.0],
    })


def _gui_update(uuid: str, value: object) -> bytes:
    """A client -> server GUI change, encoded the way viser's web client sends it."""
    import msgspec

    return msgspec.msgpack.encode({"type": "GuiUpdateMessage", "uuid": uuid, "updates": {"value": value}})


@pytest.mark.slow
def test_ten_clients_while_a_rollout_plays(tmp_path: Path) -> None:
    from app.server import ViewerApp

    baseline_py = {t.ident for t in threading.enumerate()}
    app = ViewerApp(port=_free_port(), checkpoint_dir=_tiny_full_checkpoint(tmp_path / "ck"), max_frames=60,
                    variants=["full", "skinning"])
    ws_url = app.url.replace("http://", "ws://")
    try:
        assert app.worker.wait_frames(3, timeout=120), "no frames computed"
        time.sleep(1.0)
        threads_before = _proc_status("Threads")
        others_before, pool_before = _python_threads()
        rss_before = _proc_status("VmRSS") / 1024
        loop_uuid = app.controls.loop._impl.uuid  # viser keeps the wire id there
        assert app.loop is True

        stats = [{"connected": 0, "messages": 0, "bytes": 0} for _ in range(CLIENTS)]
        outbox_holder: dict[str, asyncio.Queue] = {}
        samples: dict[str, list[float]] = {"http_s": [], "rss_mb": [], "frame_looping": [], "clients": []}
        pushed_before = app.frames_pushed
        answered: dict[str, float] = {}

        async def load() -> None:
            outbox_holder["q"] = asyncio.Queue()
            tasks = [asyncio.create_task(_client(ws_url, LOAD_SECONDS, i >= STALLED, stats[i],
                                                 outbox_holder["q"] if i == CLIENTS - 1 else None))
                     for i in range(CLIENTS)]
            await asyncio.gather(*tasks)

        def probe() -> None:
            """While loaded: time the page, sample memory and the shown frame, send one GUI action."""
            time.sleep(3.0)
            end = time.monotonic() + LOAD_SECONDS - 5.0
            sent = False
            while time.monotonic() < end:
                t0 = time.perf_counter()
                with urllib.request.urlopen(app.url, timeout=10) as resp:
                    assert resp.status == 200 and resp.read(100)
                samples["http_s"].append(time.perf_counter() - t0)
                samples["rss_mb"].append(_proc_status("VmRSS") / 1024)
                samples["clients"].append(len(app.server.get_clients()))
                if not sent:
                    samples["frame_looping"].append(app.frame_index)
                # the Loop change goes out after a few samples of the looping playback: turned off, the playback
                # may rest on the last frame, so "it moved" is judged on the samples taken before
                if not sent and "q" in outbox_holder and len(samples["frame_looping"]) >= 5:
                    t_sent = time.perf_counter()
                    outbox_holder["q"].put_nowait(_gui_update(loop_uuid, False))
                    sent = True
                    while time.perf_counter() - t_sent < 5.0 and app.loop:
                        time.sleep(0.02)
                    if not app.loop:
                        answered["loop_s"] = time.perf_counter() - t_sent
                time.sleep(0.5)

        prober = threading.Thread(target=probe, name="load-probe")
        prober.start()
        asyncio.run(load())
        prober.join(30)

        assert all(s["connected"] == 1 for s in stats), stats
        assert max(samples["clients"]) == CLIENTS, samples["clients"]
        readers = stats[STALLED:]
        # every reading client got the stream (viser batches updates into windows: count bytes, not messages),
        # and the two stalled ones did not hold it back
        assert all(s["messages"] >= 3 and s["bytes"] > 500_000 for s in readers), readers
        # responsive: the page within 2 s every time, the GUI action answered within 5 s, playback moved
        assert samples["http_s"] and max(samples["http_s"]) < 2.0, samples["http_s"]
        assert "loop_s" in answered, "the Loop checkbox change sent by a client was not applied"
        looping = samples["frame_looping"]
        assert len(set(looping)) > 1 and app.frames_pushed > pushed_before, looping
        # bounded: caches within capacity, memory growth bounded
        for cache in app.worker.caches.values():
            assert len(cache) <= cache.capacity <= 60
        rss_peak = max(samples["rss_mb"])
        assert rss_peak - rss_before < MAX_RSS_GROWTH_MB, (rss_before, rss_peak)

        # clients gone: every thread but viser's bounded callback pool is back to the baseline, and the pool
        # (which starts its workers lazily) stays within its size: no thread per client
        deadline = time.monotonic() + 10.0
        while len(app.server.get_clients()) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(app.server.get_clients()) == 0
        pool_max = app.server._thread_executor._max_workers
        threads_after = _proc_status("Threads")
        others_after, pool_after = _python_threads()
        assert others_after == others_before, (others_before, others_after)
        assert pool_after <= pool_max
        assert threads_after <= threads_before + (pool_max - pool_before), (threads_before, threads_after)
        print(f"\nload: {CLIENTS} clients ({STALLED} stalled) for {LOAD_SECONDS:.0f} s; "
              f"messages/reader {[s['messages'] for s in readers]}, MB/reader "
              f"{[round(s['bytes'] / 1e6, 1) for s in readers]}; HTTP max {max(samples['http_s']) * 1000:.0f} ms; "
              f"GUI action answered in {answered['loop_s'] * 1000:.0f} ms; RSS {rss_before:.0f} -> peak "
              f"{rss_peak:.0f} MB; threads {threads_before} -> {threads_after} (pool {pool_before} -> {pool_after} "
              f"of {pool_max}); frames pushed "
              f"{app.frames_pushed - pushed_before}, shown while looping {looping}")
    finally:
        app.stop()
    time.sleep(0.3)
    leaked = [t for t in threading.enumerate() if t.ident not in baseline_py and t.is_alive() and not t.daemon]
    assert not leaked, leaked


def test_remote_binding_needs_a_flag(capsys: pytest.CaptureFixture[str]) -> None:
    """``--host 0.0.0.0`` without ``--allow-remote`` is refused before anything starts."""
    sys.path.insert(0, str(ROOT))
    try:
        import launch_viewer
    finally:
        sys.path.remove(str(ROOT))
    for host in ("0.0.0.0", "192.168.1.10", "::"):
        assert launch_viewer.main(["--host", host, "--port", str(_free_port())]) == 2
        err = capsys.readouterr().err
        assert "refusing" in err and "--allow-remote" in err and err.strip().count("\n") == 0
    assert launch_viewer.parse_args([]).host == "127.0.0.1"


def test_the_starting_reading_flag(capsys: pytest.CaptureFixture[str]) -> None:
    """``--reading`` sets the first scene's repulsion-layer reading; an unknown one is refused before the server."""
    from types import SimpleNamespace

    from app.sources import Setting

    sys.path.insert(0, str(ROOT))
    try:
        import launch_viewer
    finally:
        sys.path.remove(str(ROOT))
    assert launch_viewer.main(["--reading", "sideways", "--port", str(_free_port())]) == 2
    assert "--reading must be one of" in capsys.readouterr().err
    assert launch_viewer.parse_args([]).reading == "checkpoint"
    catalog = SimpleNamespace(default_setting=lambda: Setting("tshirt_jacket", "02_01_walk"))
    assert launch_viewer.with_reading(None, "checkpoint", catalog) is None
    chosen = Setting("leggings_skirt", "09_01_run", "male_average")
    assert launch_viewer.with_reading(chosen, "checkpoint", catalog) is chosen
    assert launch_viewer.with_reading(None, "all-nearest", catalog) == Setting("tshirt_jacket", "02_01_walk",
                                                                               reading="all-nearest")
    assert launch_viewer.with_reading(chosen, "layer-nearest", catalog) == Setting(
        "leggings_skirt", "09_01_run", "male_average", reading="layer-nearest")


@pytest.mark.slow
def test_remote_binding_with_flag_warns(tmp_path: Path) -> None:
    """With ``--allow-remote`` the viewer starts and prints a warning about the missing authentication."""
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "launch_viewer.py"), "--host", "0.0.0.0", "--allow-remote", "--port", str(port),
         "--checkpoints", str(tmp_path / "none"), "--max-frames", "5"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        ready = False
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            line = proc.stdout.readline()
            if "ready" in line:
                ready = True
                break
        assert ready, f"viewer did not start (exit {proc.poll()})"
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=10) as resp:
            assert resp.status == 200
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    assert "WARNING" in err and "0.0.0.0" in err, err


def test_upload_limits_match_the_readme() -> None:
    """The README states the upload limits; the code enforces the same numbers."""
    from app.uploads import MAX_BVH_BYTES, MAX_OBJ_BYTES
    from smln.garments.obj_import import MAX_VERTICES

    readme = (ROOT / "README.md").read_text()
    m = re.search(r"BVH (\d+) MB, OBJ (\d+) MB \(and the importer's (\d+)k vertices\)", readme)
    assert m, "README no longer states the upload limits"
    assert int(m.group(1)) * 2**20 == MAX_BVH_BYTES and int(m.group(2)) * 2**20 == MAX_OBJ_BYTES
    assert int(m.group(3)) * 1000 == MAX_VERTICES
