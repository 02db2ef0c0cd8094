"""Background computation of rollouts into capped frame caches.

One :class:`RolloutWorker` thread serves the whole viewer (all browsers share it): it holds the current
setting and the set of enabled variants, loads the setting once, and advances the enabled variants' frame
iterators in turn (the variant with the fewest frames first), so all variants grow together along one
timeline. Asking again for the same setting and variants is a no-op (no doubled rollouts); changing the setting
cancels the running computation between two frames and drops the caches; disabling a variant drops its cache.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from app.sources import Catalog, Scenario, Setting


@dataclass
class FrameCache:
    """Frames of one variant on one scenario, appended by the worker, read by the viewer.

    Attributes:
        variant: variant key; capacity: frames the rollout will produce at most.
        frames: the computed :class:`smln.rollout.RolloutFrame` objects, in order (list append is atomic).
        done: the iterator is exhausted (or failed); error: one-line failure message, else "".
        seconds: wall time spent computing, s.
    """

    variant: str
    capacity: int
    frames: list[Any] = field(default_factory=list)
    done: bool = False
    error: str = ""
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.frames)

    def get(self, index: int) -> Any | None:
        """Frame ``index``, or the last computed one if it is not there yet (None if empty)."""
        frames = self.frames
        if not frames:
            return None
        return frames[min(index, len(frames) - 1)]


Listener = Callable[[str, dict[str, Any]], None]
"""Called from the worker thread as ``listener(event, info)``: events "scenario", "frame", "error", "done"."""


class RolloutWorker:
    """The viewer's single computation thread (see the module docstring).

    Args:
        catalog: loads settings and makes frame iterators.
        listener: event callback (must not block).
    """

    def __init__(self, catalog: Catalog, listener: Listener | None = None) -> None:
        self.catalog = catalog
        self.listener = listener or (lambda event, info: None)
        self._cond = threading.Condition()
        self._setting: Setting | None = None
        self._variants: tuple[str, ...] = ()
        self._generation = 0
        self._stop = False
        self.scenario: Scenario | None = None
        self.caches: dict[str, FrameCache] = {}
        self._iters: dict[str, Iterator[Any]] = {}
        self._thread = threading.Thread(target=self._run, name="smln-rollout-worker", daemon=True)
        self._thread.start()

    # ---- requests (any thread) -----------------------------------------------------------------------------
    def configure(self, setting: Setting, variants: tuple[str, ...] | list[str]) -> bool:
        """Ask for ``setting`` with ``variants``; returns True if anything changed (else a no-op)."""
        variants = tuple(variants)
        with self._cond:
            if setting == self._setting and variants == self._variants:
                return False
            if setting != self._setting:
                self._generation += 1
            self._setting, self._variants = setting, variants
            self._cond.notify_all()
            return True

    @property
    def setting(self) -> Setting | None:
        return self._setting

    @property
    def variants(self) -> tuple[str, ...]:
        return self._variants

    def ready(self) -> bool:
        """The loaded scenario matches the requested setting."""
        s = self.scenario
        return s is not None and s.setting == self._setting

    def busy(self) -> bool:
        """Some enabled variant is still being computed."""
        if not self.ready():
            return True
        return any(v not in self.caches or not self.caches[v].done for v in self._variants)

    def wait_frames(self, count: int, timeout: float = 60.0, variants: tuple[str, ...] | None = None) -> bool:
        """Block until every enabled (or given) variant has ``count`` frames or is done; True on success."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.ready():
                vs = variants or self._variants
                caches = [self.caches.get(v) for v in vs]
                if all(c is not None and (len(c) >= count or c.done) for c in caches):
                    return True
            time.sleep(0.02)
        return False

    def stop(self, timeout: float = 10.0) -> None:
        """Cancel and join the thread."""
        with self._cond:
            self._stop = True
            self._generation += 1
            self._cond.notify_all()
        self._thread.join(timeout)

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    # ---- the thread ----------------------------------------------------------------------------------------
    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._stop and not self._has_work():
                    self._cond.wait(0.5)
                if self._stop:
                    self._iters.clear()
                    return
                setting, variants, generation = self._setting, self._variants, self._generation
            try:
                self._step(setting, variants, generation)
            except Exception as exc:  # noqa: BLE001 - the thread must survive anything
                traceback.print_exc()
                self.listener("error", {"message": f"{type(exc).__name__}: {exc}"})
                time.sleep(0.2)

    def _has_work(self) -> bool:
        if self._setting is None:
            return False
        if self.scenario is None or self.scenario.setting != self._setting:
            return True
        for v in self._variants:
            if v not in self.caches or not self.caches[v].done:
                return True
        return any(v not in self._variants for v in self.caches)

    def _step(self, setting: Setting, variants: tuple[str, ...], generation: int) -> None:
        if self.scenario is None or self.scenario.setting != setting:
            self._iters.clear()
            self.caches = {}
            try:
                scenario = self.catalog.prepare(setting)
            except Exception as exc:  # noqa: BLE001
                self.listener("error", {"message": f"could not load {setting}: {exc}", "setting": setting})
                with self._cond:  # wait for a new request instead of retrying the broken one
                    while not self._stop and self._generation == generation:
                        self._cond.wait(0.5)
                return
            if generation != self._generation:
                return
            self.scenario = scenario
            self.listener("scenario", {"scenario": scenario})
        # drop disabled variants, start new ones
        caches = dict(self.caches)
        for v in [v for v in caches if v not in variants]:
            caches.pop(v)
            self._iters.pop(v, None)
        for v in variants:
            if v not in caches:
                caches[v] = FrameCache(v, self.scenario.num_frames)
                try:
                    self._iters[v] = self.catalog.frames(v, self.scenario)
                except Exception as exc:  # noqa: BLE001
                    caches[v].done, caches[v].error = True, f"{type(exc).__name__}: {exc}"
                    self.listener("error", {"message": f"{v}: {caches[v].error}", "variant": v})
        self.caches = caches
        pending = [v for v in variants if not caches[v].done]
        if not pending:
            return
        v = min(pending, key=lambda k: len(caches[k]))
        cache = caches[v]
        t0 = time.perf_counter()
        try:
            frame = next(self._iters[v])
        except StopIteration:
            cache.done = True
            self._iters.pop(v, None)
            self.listener("done", {"variant": v})
            return
        except Exception as exc:  # noqa: BLE001 - a diverged or broken model: keep what was computed
            cache.done, cache.error = True, f"{type(exc).__name__}: {exc}"
            self._iters.pop(v, None)
            self.listener("error", {"message": f"{v}: {cache.error}", "variant": v})
            return
        cache.seconds += time.perf_counter() - t0
        if generation != self._generation or self.caches.get(v) is not cache:
            return  # cancelled while computing: drop the frame
        seq = self.scenario.sequence
        if 0 <= frame.index < seq.num_frames:  # share the body with the scenario (a view, no copy per variant)
            frame.body_vertices = seq.vertices[frame.index].numpy()
        cache.frames.append(frame)
        if len(cache) >= cache.capacity:
            cache.done = True
            self._iters.pop(v, None)
        self.listener("frame", {"variant": v, "count": len(cache)})
