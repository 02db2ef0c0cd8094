"""A/B of the metrics and the loss against an earlier commit's whole ``smln`` package, interleaved in one process.

    python bench/ab_commit.py [--old-commit fb0dcb0] [--repeats 30] [--threads 2] [--json OUT]

Exports ``smln/`` of ``--old-commit`` (``git archive``) into a temporary directory as the package ``smln_old``
(imports rewritten), so that the old code runs with its own dependencies (e.g. scipy's cKDTree before session 4's
pykdtree). Both versions then time, alternating old and new on the same machine and load, on the synthetic
2-layer 5,000-vertex cloth and 12,804-vertex body of ``bench/losses_metrics.py``:

- ``metrics``: :func:`frame_metrics`, self-contained (``body_faces`` only);
- ``loss``: :func:`total_loss` forward + backward with a prebuilt ``BodyStep`` (layer pairs found inside).

Prints (and writes with ``--json``) the medians, the ratios new / old and whether the values agree (metrics to
1e-5 relative, loss terms to 1e-5 relative, gradients to 1e-4 of their largest entry).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from losses_metrics import make_body, make_cloth  # noqa: E402

import smln.losses as new_losses  # noqa: E402
import smln.metrics as new_metrics  # noqa: E402
from smln.geometry import set_threads  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def export_old(commit: str) -> Path:
    """Write ``smln/`` of ``commit`` as ``<tmp>/smln_old`` with its ``smln`` imports renamed; returns <tmp>."""
    tar = subprocess.run(["git", "archive", commit, "smln"], cwd=ROOT, capture_output=True, check=True).stdout
    tmp = Path(tempfile.mkdtemp())
    with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
        tf.extractall(tmp, filter="data")
    (tmp / "smln").rename(tmp / "smln_old")
    for py in (tmp / "smln_old").rglob("*.py"):
        src = py.read_text()
        src = re.sub(r"\bsmln\.", "smln_old.", src)
        src = re.sub(r"^(\s*)from smln import", r"\1from smln_old import", src, flags=re.M)
        src = re.sub(r"^(\s*)import smln$", r"\1import smln_old", src, flags=re.M)
        py.write_text(src)
    return tmp


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--old-commit", default="fb0dcb0", help="the commit to compare with (default: end of session 3)")
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json")
    a = p.parse_args()
    sys.path.insert(0, str(export_old(a.old_commit)))
    import smln_old.losses as old_losses
    import smln_old.metrics as old_metrics

    set_threads(a.threads)
    torch.manual_seed(0)
    bv, bf = make_body()
    body, faces = torch.as_tensor(bv), torch.as_tensor(bf)
    body_next = body + torch.tensor([0.003, 0.0, 0.001])
    cloth = make_cloth()
    x_prev = cloth.rest_vertices.clone()
    x_cur = x_prev + 0.001
    x_next = x_cur + 0.001 + 0.0005 * torch.randn_like(x_cur)
    x_next[cloth.pinned] = x_cur[cloth.pinned]
    x_np = x_next.numpy()

    setups = {}
    for name, losses, metrics in (("old", old_losses, old_metrics), ("new", new_losses, new_metrics)):
        rest = losses.ClothRest.from_cloth(cloth)
        step = losses.BodyStep.from_vertices(body, body_next, faces)

        def loss_fb(losses=losses, rest=rest, step=step):
            x = x_next.clone().requires_grad_(True)
            loss, terms = losses.total_loss(x_prev, x_cur, x, step, rest)
            loss.backward()
            return terms, x.grad

        def metrics_call(metrics=metrics, rest=rest):
            return metrics.frame_metrics(x_np, body_next, rest, body_faces=faces).values

        setups[name] = {"metrics": metrics_call, "loss": loss_fb}
    times: dict[str, list[float]] = {f"{k}_{n}": [] for n in setups for k in ("metrics", "loss")}
    for r in range(3 + a.repeats):  # 3 warm-up rounds
        for n, fns in setups.items():
            for k, fn in fns.items():
                t = time.perf_counter()
                fn()
                if r >= 3:
                    times[f"{k}_{n}"].append(time.perf_counter() - t)
    med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    mo, mn = setups["old"]["metrics"](), setups["new"]["metrics"]()
    (to, go), (tn, gn) = setups["old"]["loss"](), setups["new"]["loss"]()
    out = {
        "old_commit": a.old_commit, "threads": a.threads, "repeats": a.repeats,
        "metrics_ms": {"old": round(med["metrics_old"], 2), "new": round(med["metrics_new"], 2),
                       "ratio": round(med["metrics_new"] / med["metrics_old"], 3)},
        "loss_fwd_bwd_ms": {"old": round(med["loss_old"], 2), "new": round(med["loss_new"], 2),
                            "ratio": round(med["loss_new"] / med["loss_old"], 3)},
        "metrics_agree": all(abs(mo[k] - mn[k]) <= 1e-5 * max(1.0, abs(mo[k])) for k in mo),
        "loss_terms_agree": all(abs(to[k] - tn[k]) <= 1e-5 * max(1e-9, abs(to[k])) for k in to),
        "gradient_max_abs_diff": float((go - gn).abs().max()),
        "gradients_agree": bool((go - gn).abs().max() <= 1e-4 * go.abs().max()),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    text = json.dumps(out, indent=2)
    print(text)
    if a.json:
        Path(a.json).write_text(text + "\n")


if __name__ == "__main__":
    main()
