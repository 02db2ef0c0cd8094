"""Step a model autoregressively through a body clip (the RolloutFrame contract of docs/ARCHITECTURE.md).

Initial state (paper §3.1: "the first three frames of rigid deformation"): the garments are skinned onto the
body with the cloth's skin weights (``smln.body.lbs``). With ``initial_velocity="skinned"`` (default) frames 0
and 1 are the skinned frames (x_prev, x_cur) and the network predicts from frame 2 on, so the cloth starts
with the body's velocity; with ``"zero"`` frame 0 is used twice (zero velocity) and the network predicts from
frame 1 (DESIGN.md notes that a zero-velocity start on a moving body makes the worst samples).

Per predicted frame: ``x_{t+1} = x_t + v_t + p + a`` (Eq. 16), pinned vertices set to their skinned positions,
then masks and metrics (:func:`smln.metrics.frame_metrics`). Divergence (non-finite positions, a vertex more
than ``max_body_distance`` from the body or more than ``max_distance`` from its skinned position (with
``skin_guard="symptomatic"``: only together with a symptom of a tangle), or max edge strain above
``max_strain``) raises :class:`RolloutError` naming the frame, or with ``fallback=True`` replaces the frame by
skinning (velocity reset to the skinned velocity) and marks it ``fallback=True``.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from smln.body import lbs
from smln.cloth import Cloth
from smln.geometry import PointTree, build_tree, vertex_normals
from smln.losses.rest import ClothRest
from smln.metrics import _np_index, frame_metrics
from smln.model.compiled import with_compiled_processor
from smln.model.precision import with_processor_dtype
from smln.model.smln import SMLN
from smln.projection import project

MAX_BODY_DISTANCE = 0.45
"""Default divergence bound on the distance of any garment vertex from its nearest body vertex, m (within the
reliability contract's 0.5 m, ``bench/long_runs.py``). A skirt's hem in a pirouette stays within 0.21-0.30 m."""

MAX_SKIN_DISTANCE = 0.4
"""Default divergence bound on the distance of any garment vertex from its skinned position, m. Session 7 tried
the body bound alone (this one at 1 m): the fallback frames of the full model on the test clips fell from 55 to 17
of 4,689, but L-Coll rose 1.62 -> 2.65 %, H-Coll 2.26 -> 2.63 %, mean strain 6.48 -> 7.22 % and the RMS offset
from skinning 6.5 -> 10.5 cm; held-out outfits the same way (docs/RESULTS.md). The garments that pass 0.4 m from
their skinned place drift off rather than swing, and a reset to skinning is the better frame."""

SKIN_GUARDS = ("always", "symptomatic")
"""How :data:`MAX_SKIN_DISTANCE` is applied: ``always`` (a vertex beyond it is divergence) or ``symptomatic``
(beyond it only together with a symptom of a tangle, :data:`SYMPTOM_STRAIN_MEAN` or :data:`SYMPTOM_H_COLL`, or
beyond :data:`HARD_SKIN_FACTOR` times it). Session 9, without any guard on the training clips (shipped full
model, 3 seen outfits x 19 training clips, at most 150 frames; ``bench/skin_guard_probe.py``,
docs/results/skin_guard_excursions_train.json): of the 28 excursions past 0.4 m, 17 never showed a symptom
(jackets swinging open in sword play, torso rotations, arabesques, dribbles; up to 0.63 m from skinning), 11 did
(the climb and dangle, up to 0.77 m from the body; the cartwheel, 13-19 % mean strain; jump landings; one
pirouette with H-Coll rising 1.6 -> 6 %). On the test clips ``symptomatic`` cut the fallback frames 55 -> 43 of
4,689 but raised L-Coll 1.62 -> 1.81 % (the excursions it lets through carry layer penetration that neither
symptom sees), so ``always`` stays the default (docs/RESULTS.md, "Against the targets")."""

SYMPTOM_STRAIN_MEAN = 0.10
"""``skin_guard="symptomatic"``: a frame's mean edge strain above this (fraction) is a symptom of a tangle."""

SYMPTOM_H_COLL = 5.0
"""``skin_guard="symptomatic"``: a frame's H-Coll above this (% of garment vertices inside the body) is a symptom."""

HARD_SKIN_FACTOR = 2.0
"""``skin_guard="symptomatic"``: beyond this multiple of ``max_distance`` a vertex is divergence whatever else."""


def tangle_symptom(strain_mean, h_coll, strain_limit: float = SYMPTOM_STRAIN_MEAN,
                   h_coll_limit: float = SYMPTOM_H_COLL):
    """The symptom test of ``skin_guard="symptomatic"``: mean edge strain (fraction) above ``strain_limit`` or
    H-Coll (%) above ``h_coll_limit``. Scalars give a bool, numpy arrays (per frame) a bool array."""
    return (strain_mean > strain_limit) | (h_coll > h_coll_limit)


class RolloutError(RuntimeError):
    """The rollout diverged (message names the frame and the cause)."""


@dataclass
class RolloutFrame:
    """One frame of a rollout (arrays float32 numpy on the CPU; accelerations in m/frame^2)."""

    index: int
    garment_positions: np.ndarray
    body_vertices: np.ndarray
    predicted_acceleration: np.ndarray
    repulsion_acceleration: np.ndarray
    layer_penetration: np.ndarray
    body_penetration: np.ndarray
    metrics: dict[str, float]
    fallback: bool


def _sequence_arrays(body_sequence: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """(vertices (T, Vb, 3), transforms (T, B, 4|3, 4)) from a BodySequence-like object or a pair."""
    if isinstance(body_sequence, tuple | list):
        verts, transforms = body_sequence
    else:
        verts, transforms = body_sequence.vertices, body_sequence.transforms
    return torch.as_tensor(verts, dtype=torch.float32), torch.as_tensor(transforms, dtype=torch.float32)


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().to("cpu", torch.float32).numpy()


def rollout(
    model: SMLN,
    cloth: Cloth,
    body_sequence: Any,
    body_faces: torch.Tensor | np.ndarray,
    *,
    num_frames: int | None = None,
    device: str | torch.device = "cpu",
    fallback: bool = False,
    initial_velocity: str = "skinned",
    max_distance: float = MAX_SKIN_DISTANCE,
    max_body_distance: float = MAX_BODY_DISTANCE,
    max_strain: float = 1.0,
    skin_guard: str = "always",
    symptom_strain_mean: float = SYMPTOM_STRAIN_MEAN,
    symptom_h_coll: float = SYMPTOM_H_COLL,
    settle_steps: int = 1,
    project_body: bool = False,
    project_layers: bool = False,
    precision: str = "float32",
    compiled: bool = False,
) -> Iterator[RolloutFrame]:
    """Animate ``cloth`` on a body clip with ``model``.

    Args:
        model: the network (moved to ``device``, run in eval mode without gradients).
        cloth: the outfit (rest pose, skin weights into the body's bones).
        body_sequence: object with ``vertices`` (T, Vb, 3) and ``transforms`` (T, B, 4, 4) (or the pair).
        body_faces: (Fb, 3) body triangles (body normals for the metrics).
        num_frames: frames to produce (default: the whole clip).
        device: "cpu" or "cuda".
        fallback: replace a diverged frame by skinning instead of raising.
        initial_velocity: "skinned" (frames 0, 1 skinned) or "zero" (frame 0 twice).
        max_distance: divergence threshold on the distance to the skinned position, m (:data:`MAX_SKIN_DISTANCE`).
        max_body_distance: divergence threshold on the distance of any garment vertex to its nearest body vertex, m
            (:data:`MAX_BODY_DISTANCE`).
        max_strain: divergence threshold on the max edge strain *above the skinned state's own* at that frame
            (1.0 = an edge doubled beyond what skinning already gives; linear blend skinning of a T-pose garment
            already stretches some armpit edges by up to ~100 %).
        skin_guard: ``"always"`` (default): a vertex beyond ``max_distance`` is divergence. ``"symptomatic"``: only
            if the frame's mean edge strain exceeds ``symptom_strain_mean`` (fraction) or its H-Coll exceeds
            ``symptom_h_coll`` (%), or the vertex is beyond ``HARD_SKIN_FACTOR * max_distance``: a garment
            swinging far from its skinned place with healthy strain and no body penetration goes on
            (:data:`SKIN_GUARDS`).
        settle_steps: the first predicted steps relax the skinned garments (linear blend skinning of a T-pose
            garment leaves them strained: ~7 % mean edge strain, ~100 % at the armpits) rather than move them.
            That relaxation is not momentum: after each of these steps the velocity is reset to the skinning's
            (x_prev := x_next - (skinned_t - skinned_{t-1})). Without it the relaxation jolt carries into the
            next frames and overshoots (the L-BFGS reference on a walk: mean strain 5.0-10.4 % over frames 3-11
            instead of 4.2-5.5 %). Training episodes start the same way (:mod:`smln.train`). 0 = off.
        project_body: after each network step, move free vertices that are inside the body back out
            (:mod:`smln.projection`; off by default: the paper's model resolves collisions on its own).
        project_layers: after each network step, move each layer's free vertices out of the layer beneath.
            With either, the frame's metrics gain ``projected_fraction`` (% of vertices moved),
            ``projection_mean_mm`` / ``projection_max_mm`` (their displacement) and ``ms_projection``.
        precision: "float32" or "bfloat16" (the processor in bfloat16, :mod:`smln.model.precision`; ~1.4x
            faster network on CPUs with AMX / AVX512-BF16, slower elsewhere).
        compiled: run the processor through ``torch.compile`` (:mod:`smln.model.compiled`; 12-15 % faster steps
            on CPU after a one-off compilation of 10-80 s on the first step).

    Yields:
        :class:`RolloutFrame` for frames 0 .. num_frames-1.

    Raises:
        RolloutError: on divergence without ``fallback``; ValueError on bad arguments.
    """
    if initial_velocity not in ("skinned", "zero"):
        raise ValueError(f"initial_velocity must be 'skinned' or 'zero', got {initial_velocity!r}")
    if skin_guard not in SKIN_GUARDS:
        raise ValueError(f"skin_guard must be one of {SKIN_GUARDS}, got {skin_guard!r}")
    symptomatic = skin_guard == "symptomatic"
    hard_distance = HARD_SKIN_FACTOR * max_distance if symptomatic else max_distance
    body_v, transforms = _sequence_arrays(body_sequence)
    total = body_v.shape[0]
    n = total if num_frames is None else min(int(num_frames), total)
    if n < 1:
        return
    dev = torch.device(device)
    model = with_processor_dtype(model.to(dev).eval(), precision)
    if compiled:
        model = with_compiled_processor(model)
    cloth_d = cloth.to(dev)
    topology = model.make_topology(cloth_d)
    rest = ClothRest.from_cloth(cloth)
    faces_np = _np_index(body_faces)  # a GPU run passes the faces on the GPU
    projecting = project_body or project_layers
    rest_d = rest.to(dev) if projecting else rest
    faces_d = torch.as_tensor(faces_np, device=dev)
    skinned = lbs(
        cloth.rest_vertices.float(), cloth.skin_indices, cloth.skin_weights, transforms[:n]
    ).to(dev)
    body_d = body_v[:n].to(dev)
    zeros = np.zeros((cloth.num_vertices, 3), np.float32)
    trees: dict[int, PointTree] = {}
    nearest: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> nearest body vertex of its garment vertices

    def body_tree(t: int) -> PointTree:
        """One KD-tree per body frame: the metrics of frame t and the graph of the step from t share it."""
        if t not in trees:
            trees.clear()
            trees[t] = build_tree(body_v[t])
        return trees[t]

    def make_frame(t: int, x: torch.Tensor, p: np.ndarray, a: np.ndarray, fb: bool, extra: dict,
                   body_normals: torch.Tensor | None = None) -> RolloutFrame:
        """The frame's metrics; ``body_normals``: (Vb, 3) of body frame t if the step already computed them."""
        fm = frame_metrics(x, body_v[t], rest, body_faces=faces_np, body_normals=body_normals,
                           body_tree=body_tree(t))
        nearest.clear()  # the next step starts from these positions: its body edges reuse the query
        nearest[t] = (fm.body_index, fm.body_distance)
        metrics = dict(fm.values)
        metrics["body_distance_max"] = float(fm.body_distance.max()) if len(fm.body_distance) else 0.0
        metrics.update(extra)
        metrics["repulsion_mean"] = float(np.linalg.norm(a, axis=1).mean())
        metrics["repulsion_max"] = float(np.linalg.norm(a, axis=1).max()) if len(a) else 0.0
        metrics["prediction_mean"] = float(np.linalg.norm(p, axis=1).mean())
        return RolloutFrame(
            index=t,
            garment_positions=_np(x),
            body_vertices=_np(body_v[t]),
            predicted_acceleration=p,
            repulsion_acceleration=a,
            layer_penetration=fm.layer_penetration,
            body_penetration=fm.body_penetration,
            metrics=metrics,
            fallback=fb,
        )

    x_prev = skinned[0]
    yield make_frame(0, skinned[0], zeros, zeros, False, {"ms_model": 0.0})
    if initial_velocity == "skinned":
        if n < 2:
            return
        x_cur = skinned[1]
        yield make_frame(1, x_cur, zeros, zeros, False, {"ms_model": 0.0})
        first = 2
    else:
        x_cur = skinned[0]
        first = 1

    with torch.no_grad():
        for t in range(first, n):
            t0 = time.perf_counter()
            # body normals at t: the step's body edges (t+1 of the step) and the frame's metrics share them
            normals = vertex_normals(body_d[t], faces_d) if topology.body_normals else None
            p, a, ex = model.step(
                topology, x_prev, x_cur, body_d[t - 1], body_d[t], skinned[t], body_tree=body_tree(t - 1),
                body_nearest=nearest.get(t - 1), body_normals_next=normals,
                body_tree_next=body_tree(t) if getattr(model.config, "body_pairing", "edge") != "edge" else None,
            )
            x_next = ex["x_next"]
            ms = 1e3 * (time.perf_counter() - t0)
            extra = {"ms_model": ms}
            if projecting:
                t1 = time.perf_counter()
                pr = project(x_next, rest_d, body_d[t] if project_body else None, faces_d, body_tree(t),
                             layers=project_layers)
                x_next = pr.x
                extra.update(
                    projected_fraction=100.0 * float(pr.moved.float().mean()),
                    projection_mean_mm=1e3 * float(pr.displacement[pr.moved].mean()) if bool(pr.moved.any()) else 0.0,
                    projection_max_mm=1e3 * float(pr.displacement.max()),
                    ms_projection=1e3 * (time.perf_counter() - t1),
                )
            reason, skin_distance = _divergence(x_next, skinned[t], hard_distance)
            if reason is None:
                frame = make_frame(t, x_next, _np(p), _np(a), False, extra, normals)
                limit = max_strain + _max_strain(skinned[t], rest)
                m = frame.metrics
                if symptomatic and skin_distance > max_distance and tangle_symptom(
                        m["strain_mean"], m["h_coll"], symptom_strain_mean, symptom_h_coll):
                    reason = (f"a vertex is {skin_distance:.2f} m from its skinned position (> {max_distance} m) "
                              f"at mean strain {m['strain_mean']:.3f}, H-Coll {m['h_coll']:.1f} %")
                elif frame.metrics["body_distance_max"] > max_body_distance:
                    reason = (f"a vertex is {frame.metrics['body_distance_max']:.2f} m from the body "
                              f"(> {max_body_distance} m)")
                elif frame.metrics["strain_max"] > limit:
                    reason = f"max edge strain {frame.metrics['strain_max']:.2f} > {limit:.2f}"
            if reason is not None:
                if not fallback:
                    raise RolloutError(f"frame {t}: rollout diverged ({reason})")
                x_next = skinned[t]
                x_cur = skinned[t - 1]
                frame = make_frame(t, x_next, zeros, zeros, True, extra, normals)
            yield frame
            if t - first < settle_steps and not frame.fallback:
                x_prev, x_cur = x_next - (skinned[t] - skinned[t - 1]), x_next
            else:
                x_prev, x_cur = x_cur, x_next


def _max_strain(x: torch.Tensor, rest: ClothRest) -> float:
    """Max |l / l_rest - 1| over the cloth's edges at positions ``x`` (V, 3)."""
    e = rest.edges.to(x.device)
    length = (x[e[:, 0]] - x[e[:, 1]]).norm(dim=-1)
    return float((length / rest.rest_length.to(x.device) - 1).abs().max())


def _divergence(x: torch.Tensor, skinned: torch.Tensor, max_distance: float) -> tuple[str | None, float]:
    """Cheap checks before the metrics: non-finite positions or a vertex too far from its skinned place.

    Returns:
        (reason or None, the largest distance of a vertex from its skinned position in meters; inf if non-finite).
    """
    if not bool(torch.isfinite(x).all()):
        return "non-finite positions", float("inf")
    d = float((x.detach() - skinned).norm(dim=-1).max())
    if d > max_distance:
        return f"a vertex is {d:.2f} m from its skinned position (> {max_distance} m)", d
    return None, d
