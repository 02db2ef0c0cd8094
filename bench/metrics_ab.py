"""A/B of ``frame_metrics`` against an earlier commit's version, interleaved in one process (same machine, same load).

    python bench/metrics_ab.py [--old-commit 1f2aa24] [--repeats 30]

Loads ``smln/metrics.py`` of ``--old-commit`` (via ``git show``) beside the current one, times both on the
synthetic 2-layer 5,000-vertex cloth and 12,804-vertex body of ``bench/losses_metrics.py`` (self-contained calls,
2 torch threads), alternating old and new, and prints the medians, their ratio and whether the values agree.
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from losses_metrics import make_body, make_cloth  # noqa: E402

from smln.losses import ClothRest  # noqa: E402
from smln.metrics import frame_metrics as new_metrics  # noqa: E402


def load_old(commit: str):
    """``frame_metrics`` of ``smln/metrics.py`` at ``commit``."""
    root = Path(__file__).resolve().parents[1]
    src = subprocess.run(["git", "show", f"{commit}:smln/metrics.py"], cwd=root, capture_output=True, text=True,
                         check=True).stdout
    path = Path(tempfile.mkdtemp()) / "old_metrics.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("old_metrics", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["old_metrics"] = mod
    spec.loader.exec_module(mod)
    return mod.frame_metrics


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--old-commit", default="1f2aa24", help="a commit before the numpy rewrite of the metrics")
    p.add_argument("--repeats", type=int, default=30)
    a = p.parse_args()
    torch.set_num_threads(2)
    torch.manual_seed(0)
    old = load_old(a.old_commit)
    bv, bf = make_body()
    body, faces = torch.as_tensor(bv), torch.as_tensor(bf)
    cloth = make_cloth()
    rest = ClothRest.from_cloth(cloth)
    x = (cloth.rest_vertices + 0.001 + 0.0005 * torch.randn_like(cloth.rest_vertices)).numpy()
    for f in (old, new_metrics):
        for _ in range(3):
            f(x, body, rest, body_faces=faces)
    t_old, t_new = [], []
    for _ in range(a.repeats):
        t = time.perf_counter()
        old(x, body, rest, body_faces=faces)
        t_old.append(time.perf_counter() - t)
        t = time.perf_counter()
        new_metrics(x, body, rest, body_faces=faces)
        t_new.append(time.perf_counter() - t)
    mo, mn = 1e3 * statistics.median(t_old), 1e3 * statistics.median(t_new)
    va = old(x, body, rest, body_faces=faces).values
    vb = new_metrics(x, body, rest, body_faces=faces).values
    same = all(abs(va[k] - vb[k]) <= 1e-6 * max(1.0, abs(va[k])) for k in va)
    print(f"frame_metrics self-contained, median of {a.repeats} interleaved: {a.old_commit} {mo:.2f} ms, "
          f"current {mn:.2f} ms, ratio {mn / mo:.2f}; same values: {same}")


if __name__ == "__main__":
    main()
