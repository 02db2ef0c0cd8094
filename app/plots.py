"""Live metrics: a markdown table for the current frame and uPlot curves over the clip with a cursor line.

uPlot's scales break on NaN, so the curves hold only the frames every variant has computed (the shared
timeline) and the x axis is fixed to the whole clip. The cursor is a vertical segment: two extra samples at
x = current frame are inserted into the (sorted) x axis; the variant curves repeat their value there and the
cursor series, flat at the plot's lower bound elsewhere, rises to the upper bound at the first inserted sample.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import viser
from viser import uplot

from app.sources import VARIANT_LABELS

PLOT_METRICS: tuple[tuple[str, str, float], ...] = (
    ("l_coll", "L-Coll (%)", 1.0),
    ("h_coll", "H-Coll (%)", 1.0),
    ("strain_mean", "mean strain (%)", 100.0),
    ("repulsion_mean", "mean |a| (mm/frame^2)", 1000.0),
)
"""(metric key, title with unit, factor from the frame's unit to the displayed one)."""

VARIANT_STROKES: dict[str, str] = {
    "full": "#1f77b4",
    "no_repulsion_layer": "#d62728",
    "baseline": "#9467bd",
    "skinning": "#7f7f7f",
}
EXTRA_STROKES: tuple[str, ...] = ("#2ca02c", "#ff7f0e", "#17becf", "#8c564b")
"""Curve colours of saved rollouts (cycled)."""


def metric_series(frames: list[Any], count: int, key: str, factor: float) -> np.ndarray:
    """(count,) float64 values of one metric over the first ``count`` frames (non-finite values -> 0; a shorter
    list, e.g. a saved rollout, holds its last value; no frames at all -> zeros)."""
    values = np.array([f.metrics.get(key, 0.0) for f in frames[:count]], dtype=np.float64) * factor
    if len(values) < count:
        values = np.concatenate([values, np.full(count - len(values), values[-1] if len(values) else 0.0)])
    return np.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0)


def with_cursor(x: np.ndarray, ys: list[np.ndarray], index: int) -> tuple[np.ndarray, ...]:
    """uPlot data with a vertical cursor at frame ``index`` (no NaN anywhere).

    Args:
        x: (n,) frame numbers, n >= 1; ys: per variant (n,) values; index: current frame.

    Returns:
        (x', y'_1, ..., y'_k, cursor), each of length n + 2.
    """
    i = int(np.clip(index, 0, len(x) - 1))
    values = np.concatenate([*ys, np.zeros(1)])
    lo, hi = float(values.min()), float(values.max())
    hi = hi if hi > lo else lo + 1.0
    xs = np.insert(x.astype(np.float64), i + 1, [x[i], x[i]])
    curves = [np.insert(y, i + 1, [y[i], y[i]]) for y in ys]
    cursor = np.full(len(xs), lo)
    cursor[i + 1] = hi
    return (xs, *curves, cursor)


class MetricsPanel:
    """The metric table and curves, in the GUI container current at construction (a folder)."""

    def __init__(self, gui: viser.GuiApi, min_interval: float = 0.1) -> None:
        self.gui = gui
        self.table = gui.add_markdown("*no frames yet*")
        self.plots: dict[str, Any] = {}
        self.variants: tuple[str, ...] = ()
        self.total = 0
        self.min_interval = min_interval
        self._last = 0.0
        self._last_key: tuple = ()
        self.labels: dict[str, str] = {}

    def label(self, v: str) -> str:
        return self.labels.get(v) or VARIANT_LABELS.get(v, v)

    def rebuild(self, variants: list[str], total: int, labels: dict[str, str] | None = None) -> None:
        """Recreate the plots for a new set of variants or clip length (``labels``: names of variants that are
        not in :data:`~app.sources.VARIANT_LABELS`, e.g. saved rollouts)."""
        self.labels = dict(labels or {})
        if tuple(variants) == self.variants and total == self.total and self.plots:
            return
        for h in self.plots.values():
            h.remove()
        self.variants, self.total = tuple(variants), total
        x = np.zeros(1)
        series = (
            uplot.Series(label="frame"),
            *[uplot.Series(label=self.label(v), stroke=VARIANT_STROKES.get(v, EXTRA_STROKES[i % len(EXTRA_STROKES)]),
                           width=2, spanGaps=True) for i, v in enumerate(variants)],
            uplot.Series(label="now", stroke="#999999", width=1),
        )
        self.plots = {}
        for key, title, _ in PLOT_METRICS:
            data = with_cursor(x, [np.zeros(1) for _ in variants], 0)
            x_range = uplot.Scale(time=False, auto=False, range=(0.0, float(max(total - 1, 1))))
            self.plots[key] = self.gui.add_uplot(data, series, title=title, aspect=2.0, scales={"x": x_range})
        self._last_key = ()

    def update(self, caches: dict[str, Any], index: int, force: bool = False, count: int | None = None) -> None:
        """Refresh the table for frame ``index`` and the curves (at most every ``min_interval`` s).

        ``count``: frames on the shared timeline (default: the fewest any variant has); a variant with fewer
        frames (a saved rollout) holds its last value on the curves."""
        counts = tuple(len(caches[v]) if v in caches else 0 for v in self.variants)
        key = (index, counts, count)
        now = time.monotonic()
        if not force and (key == self._last_key or now - self._last < self.min_interval):
            return
        self._last, self._last_key = now, key
        self.table.content = self.table_markdown(caches, index)
        if not self.variants or not self.total:
            return
        if count is None:
            count = min(counts) if counts else 0
        count = min(count, self.total)
        if count == 0:
            return
        x = np.arange(count, dtype=np.float64)
        for mkey, _, factor in PLOT_METRICS:
            ys = [metric_series(caches[v].frames if v in caches else [], count, mkey, factor)
                  for v in self.variants]
            self.plots[mkey].data = with_cursor(x, ys, index)

    def table_markdown(self, caches: dict[str, Any], index: int) -> str:
        """Markdown table: one row per variant, L-Coll, H-Coll, strain and mean |a| at frame ``index``."""
        head = "| variant | L-Coll % | H-Coll % | strain % | mean \\|a\\| mm/f² |\n|---|---:|---:|---:|---:|\n"
        rows = []
        for v in self.variants:
            cache = caches.get(v)
            f = cache.frames[index] if cache is not None and index < len(cache) else None
            note = " (fallback)" if f is not None and f.fallback else ""
            if f is None and cache is not None and cache.done and len(cache):  # a finished saved rollout: hold
                f, note = cache.frames[-1], f" (frame {len(cache) - 1})"
            if f is None:
                text = cache.error[:30] if cache is not None and cache.error else "…"
                rows.append(f"| {self.label(v)} | {text} | … | … | … |")
                continue
            m = f.metrics
            rows.append(
                f"| {self.label(v)}{note} | {m.get('l_coll', np.nan):.2f} | "
                f"{m.get('h_coll', np.nan):.2f} | {100 * m.get('strain_mean', np.nan):.2f} | "
                f"{1000 * m.get('repulsion_mean', np.nan):.3f} |"
            )
        return f"**frame {index}**\n\n" + head + "\n".join(rows)
