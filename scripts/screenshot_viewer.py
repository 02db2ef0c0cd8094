"""Screenshot of the viewer on the shipped checkpoints, for the README (Playwright + Debian's Chromium).

    python scripts/screenshot_viewer.py --outfit leggings_skirt --clip 05_11_dance_sideways_steps_pirouette \
        --frame 68 --out docs/screenshots/viewer_trained.png

Starts :class:`app.server.ViewerApp` on a free port with ``checkpoints/`` and the ``--variants`` (default: all) and
``--projection`` setting, waits until
every variant has computed ``--frame`` + 1 frames, pauses there and saves a 1400x900 screenshot. Needs
``/usr/bin/chromium`` (``apt-get install chromium``) and ``pip install playwright`` (never ``playwright install``).
"""

from __future__ import annotations

import argparse
import socket
import time
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
FLAGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
         "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--outfit", default="leggings_skirt")
    p.add_argument("--clip", default="05_11_dance_sideways_steps_pirouette")
    p.add_argument("--shape", default="female_average")
    p.add_argument("--frame", type=int, default=68)
    p.add_argument("--checkpoints", default="checkpoints")
    p.add_argument("--out", default="docs/screenshots/viewer_trained.png")
    p.add_argument("--projection", default="off", choices=["off", "body", "body+layers"],
                   help="the viewer's collision projection setting (smln.projection)")
    p.add_argument("--variants", nargs="+", default=["full", "no_repulsion_layer", "baseline", "skinning"])
    a = p.parse_args()

    from playwright.sync_api import sync_playwright

    from app.server import ViewerApp
    from app.sources import Setting

    app = ViewerApp(port=free_port(), checkpoint_dir=a.checkpoints, max_frames=a.frame + 22,
                    setting=Setting(a.outfit, a.clip, a.shape, a.projection), variants=a.variants)
    try:
        if not app.worker.wait_frames(a.frame + 1, timeout=600):
            raise SystemExit("the variants did not compute the frame in 10 minutes")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(app.url)
            page.get_by_text("Connected").wait_for(timeout=60_000)
            page.get_by_role("button", name="Pause").click()
            page.get_by_role("button", name="Play").wait_for(timeout=10_000)
            app.controls.frame.value = a.frame  # the Frame slider, set from the server side
            time.sleep(4.0)
            Path(a.out).parent.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=a.out)
            browser.close()
        print(f"wrote {a.out}")
    finally:
        app.stop()


if __name__ == "__main__":
    main()
