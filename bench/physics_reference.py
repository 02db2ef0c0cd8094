"""Physics reference: the same outfit, body shape and clip as SMLN, simulated by a real cloth solver.

``python bench/physics_reference.py --outfit tshirt_jacket --clip 05_01_walk --frames 30 --out ref.npz``

The solver is NVIDIA Newton's :class:`newton.solvers.SolverVBD` (vertex block descent, implicit per-vertex
solves) with particle self-contact on, which handles cloth-body contact (the posed body is a triangle-mesh
collider), layer-layer contact and self-contact of each layer (vertex-triangle and edge-edge, all layers are one
particle system). Newton is an optional extra: ``pip install smln[physics]`` (``newton>=1.0``).

Set-up, matched to SMLN (``docs/ARCHITECTURE.md``):

- cloth: the outfit's :class:`~smln.cloth.Cloth` (all layers, Cloth vertex order), rest shape = the canonical
  T-pose rest vertices (membrane rest shape and rest dihedral angles), vertex mass = density * area / 3 (Eq. 3);
  initial state = skinned frame 1 (frames 0 and 1 are the skinned initial state, as in SMLN rollouts) with the
  skinned velocity (frame 2 - frame 1) * fps (the clips' frame 0 -> 1 step is a jump); pinned vertices
  (waistbands) get zero mass and follow the skinning, linearly interpolated per substep.
- material (SNUG): membrane Lame mu * thickness and lambda * thickness as Newton's per-area ``tri_ke``/``tri_ka``
  (Newton's stable Neo-Hookean membrane, which linearises to SMLN's StVK with the same Lame constants); the
  dihedral bending stiffness per edge matches HOOD's E = k_b l^2 / (4 (A1 + A2)) * theta^2 / 2 (Newton's energy
  is ke * l_rest * theta^2 / 2, so ke_e = k_b * l_e / (4 (A1 + A2)), set per edge); Coulomb friction 0.5.
- body: one mesh collider whose vertices are linearly interpolated between the 30 fps body frames at every
  substep (vertex velocities set too, so friction is relative to the moving skin); the mesh BVH is refitted per
  substep and its broad-phase box spans the whole clip.
- start (``--preroll N``, recommended 40): the garments start at rest in the T-pose (no interpenetration) and are
  simulated while the body moves from the T-pose to the clip's frame 1 over N frames
  (:func:`smln.motion.posing.preroll_sequence`: slerped bone orientations, a root path that arrives with the clip's
  velocity). Started from the skinned frame 1 instead (``--preroll 0``, the learned models' start), the
  interpenetrations of skinning (4-5 % of the outer layer behind the inner one, up to 1 cm deep) made the
  self-contact tear the cloth on fast or 3-layer scenes (mean edge strain 22-92 %); with a 40-frame lead-in the
  walk and the 3-layer walk stay whole (mean strain 4 %, a few snagged edges). On 09_06_run the body (12.6 cm per
  frame, 6 mm per substep at 20 substeps, more than the 3 mm contact radius) passes through the cloth and leaves it
  behind: its H-Coll then reads ~0 % while the cloth falls 1.7 m behind the body. The per-frame
  ``skin_offset_mean`` (mean distance to the skinned garments) exposes such runs; fast clips need more substeps.
- time: 30 fps frames, ``--substeps`` (default 20) solver steps per frame: with fewer the body (up to ~2 cm per
  frame on a walk) tunnels through the 3 mm contact radius.

Warp's CPU kernels run on one thread; the first run compiles kernels for ~40 s (cached under
``WARP_CACHE_PATH``). Use the coarse training outfits (``--edge-length 0.035``, the default here) to keep a frame
at seconds.

The result is written as a rollout NPZ (:func:`smln.export.save_rollout_npz`) with per-frame metrics from
:func:`smln.metrics.frame_metrics` and ``ms_model`` = wall time of the frame's substeps (ms), so the evaluation
code and the viewer read it like a network rollout.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from smln.body import DEFAULT_SHAPE
from smln.cloth import FPS, GRAVITY
from smln.garments import TRAINING_EDGE_LENGTH
from smln.metrics import frame_metrics
from smln.rollout import RolloutFrame

NEWTON_MISSING = (
    "bench/physics_reference.py needs NVIDIA Newton (the optional 'physics' extra): "
    "pip install 'smln[physics]'  (or: pip install 'newton>=1.0')"
)

CONTACT_RADIUS = 3e-3
"""Cloth particle contact radius against the body, m (SMLN's body-collision epsilon)."""
SELF_CONTACT_RADIUS = 2e-3
"""Self / layer-layer contact distance, m (layers rest >= 4 mm apart)."""
SELF_CONTACT_MARGIN = 4e-3
"""Self-contact detection distance, m (Newton's query radius = margin + gap)."""
CONTACT_GAP = 5e-3
"""Extra body-contact detection distance, m (covers a substep of body motion)."""
CONTACT_KE = 5e4
"""Contact stiffness, N/m (Newton's cloth-on-character example uses 5e3 in meters)."""
CONTACT_KD = 1e-2
"""Contact damping."""
MEMBRANE_DAMPING = 1e-6
"""Newton ``tri_kd``, a small Rayleigh damping on the membrane."""
BENDING_DAMPING = 1e-6
"""Newton ``edge_kd``."""


def import_newton():
    """Import ``warp`` and ``newton`` or exit with a clear message (Newton is an optional extra)."""
    os.environ.setdefault("WARP_CACHE_PATH", str(Path.home() / ".cache" / "warp"))
    try:
        import newton
        import warp as wp
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise SystemExit(f"{NEWTON_MISSING}\n({exc})") from exc
    return wp, newton


def bending_stiffness_per_edge(rest: np.ndarray, edges: np.ndarray, k_b: float) -> np.ndarray:
    """Newton's per-edge dihedral stiffness matching HOOD's bending energy.

    Args:
        rest: (V, 3) rest vertices, m.
        edges: (E, 4) Newton bending edges ``[o0, o1, v0, v1]`` (opposite vertices, then the hinge; -1 on a
            boundary edge).
        k_b: bending stiffness of the material (N m).

    Returns:
        (E,) float32 ``ke_e = k_b * l_e / (4 (A1 + A2))`` (0 on boundary edges), so that Newton's
        ``ke_e * l_e * theta^2 / 2`` equals HOOD's ``k_b * l_e^2 / (4 (A1 + A2)) * theta^2 / 2``.
    """
    o0, o1, v0, v1 = edges.T
    interior = (o0 >= 0) & (o1 >= 0)
    ke = np.zeros(len(edges), np.float32)
    a, b = rest[v0[interior]], rest[v1[interior]]
    e = b - a
    length = np.linalg.norm(e, axis=1)
    a1 = 0.5 * np.linalg.norm(np.cross(e, rest[o0[interior]] - a), axis=1)
    a2 = 0.5 * np.linalg.norm(np.cross(e, rest[o1[interior]] - a), axis=1)
    ke[interior] = k_b * length / (4.0 * np.maximum(a1 + a2, 1e-12))
    return ke


class NewtonClothSim:
    """One outfit on a moving body in Newton/VBD (see the module docstring for the set-up).

    Args:
        scene: a :class:`smln.data_sampling.Scene` (cloth, posed body (T, Vb, 3), skinned cloth (T, V, 3)).
        substeps: solver steps per 30 fps frame.
        iterations: VBD iterations per substep.
        self_contact: turn Newton's particle self-contact (layer-layer and self collisions) on.
        preroll: lead-in frames from the T-pose to frame 1 (0: start from skinned frame 1 instead).
    """

    def __init__(self, scene, *, substeps: int = 20, iterations: int = 10, self_contact: bool = True,
                 preroll: int = 0) -> None:
        wp, newton = import_newton()
        self.wp, self.newton = wp, newton
        self.scene = scene
        self.substeps = int(substeps)
        self.dt = 1.0 / FPS / self.substeps
        cloth = scene.cloth
        mat = cloth.material
        rest = cloth.rest_vertices.numpy().astype(np.float32)
        faces = cloth.faces.numpy().astype(np.int32)
        body = scene.body.vertices.numpy().astype(np.float32)
        self.body_frames = body
        self.skinned = scene.skinned.numpy().astype(np.float32)
        self.pinned = cloth.pinned.numpy().astype(bool)

        builder = newton.ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
        builder.add_cloth_mesh(
            pos=wp.vec3(0.0, 0.0, 0.0),
            rot=wp.quat_identity(),
            scale=1.0,
            vel=wp.vec3(0.0, 0.0, 0.0),
            vertices=[wp.vec3(*v) for v in rest],
            indices=faces.reshape(-1).tolist(),
            density=mat.density,
            tri_ke=mat.lame_mu * mat.thickness,
            tri_ka=mat.lame_lambda * mat.thickness,
            tri_kd=MEMBRANE_DAMPING,
            edge_ke=0.0,
            edge_kd=BENDING_DAMPING,
            particle_radius=CONTACT_RADIUS,
        )
        # the body: a static mesh collider whose vertices we move (and refit) every substep
        self.body_mesh = newton.Mesh(body[0].copy(), scene.body.faces.numpy().astype(np.int32).reshape(-1))
        cfg = newton.ModelBuilder.ShapeConfig(mu=mat.friction, ke=CONTACT_KE, kd=CONTACT_KD,
                                              has_shape_collision=False, density=0.0)
        builder.add_shape_mesh(-1, mesh=self.body_mesh, cfg=cfg)
        builder.color()
        model = builder.finalize(device="cpu")
        model.soft_contact_ke = CONTACT_KE
        model.soft_contact_kd = CONTACT_KD
        model.soft_contact_mu = mat.friction
        # per-edge bending stiffness (HOOD's form), rest angles from the T-pose rest mesh
        edges = model.edge_indices.numpy()
        props = model.edge_bending_properties.numpy()
        props[:, 0] = bending_stiffness_per_edge(rest, edges, mat.bending_stiffness)
        model.edge_bending_properties.assign(props)
        # pinned vertices: zero mass, driven by the skinning
        if self.pinned.any():
            mass = model.particle_mass.numpy()
            inv = model.particle_inv_mass.numpy()
            mass[self.pinned] = 0.0
            inv[self.pinned] = 0.0
            model.particle_mass.assign(mass)
            model.particle_inv_mass.assign(inv)
        # broad phase: the collider's box must cover the body over the whole clip
        lo = body.reshape(-1, 3).min(0) - 0.1
        hi = body.reshape(-1, 3).max(0) + 0.1
        model.shape_collision_aabb_lower.assign(np.array([lo], np.float32))
        model.shape_collision_aabb_upper.assign(np.array([hi], np.float32))
        self.model = model
        self.wp_mesh = self.body_mesh.mesh
        self.mass = model.particle_mass.numpy()

        self.solver = newton.solvers.SolverVBD(
            model,
            iterations=iterations,
            particle_enable_self_contact=self_contact,
            particle_self_contact_margin=SELF_CONTACT_RADIUS,
            particle_self_contact_gap=SELF_CONTACT_MARGIN - SELF_CONTACT_RADIUS,
            particle_topological_contact_filter_threshold=2,
        )
        self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=CONTACT_GAP)
        self.contacts = self.pipeline.contacts()
        self.control = model.control()
        self.state_0 = model.state()
        self.state_1 = model.state()
        n1, n2 = min(1, len(self.skinned) - 1), min(2, len(self.skinned) - 1)
        if preroll > 0:
            # start from the garments' rest shape in the T-pose (no interpenetration: L-Coll = H-Coll = 0) and
            # simulate the body's lead-in from the T-pose to frame 1 (see run_preroll)
            from smln.body import lbs, load_body
            from smln.motion.posing import preroll_sequence

            body_model = load_body(scene.shape)
            lead = preroll_sequence(body_model, scene.body, frame=n1, num_frames=preroll)
            lead_pins = lbs(cloth.rest_vertices, cloth.skin_indices, cloth.skin_weights, lead.transforms)
            # frame 0 of the lead-in is the rest pose itself (body and garments at rest)
            self.preroll_body = np.concatenate([body_model.rest_vertices.numpy()[None],
                                                lead.vertices.numpy()]).astype(np.float32)
            self.preroll_pins = np.concatenate([rest[None], lead_pins.numpy()]).astype(np.float32)
            self.state_0.particle_q.assign(rest)
            self.state_0.particle_qd.zero_()
            self._set_body(self.preroll_body[0], np.zeros_like(self.preroll_body[0]))
        else:
            # start from skinned frame 1, like SMLN's rollouts (frames 0-1 skinned). The initial velocity is the
            # skinned one of the next frame (2 - 1): the clips' frame 0 -> 1 jump (~26 cm mean body displacement
            # on 05_01_walk) would throw the cloth.
            self.preroll_body = None
            self.state_0.particle_q.assign(self.skinned[n1])
            self.state_0.particle_qd.assign((self.skinned[n2] - self.skinned[n1]) * FPS)
            self._set_body(body[n1], np.zeros_like(body[n1]))

    @property
    def num_particles(self) -> int:
        return int(self.model.particle_count)

    def _set_body(self, vertices: np.ndarray, velocity: np.ndarray) -> None:
        """Move the body collider: vertices (Vb, 3) m, velocities (Vb, 3) m/s; refits the BVH."""
        self.wp_mesh.points.assign(vertices)
        self.wp_mesh.velocities.assign(velocity)
        self.wp_mesh.refit()

    def _advance(self, b0: np.ndarray, b1: np.ndarray, pin0: np.ndarray, pin1: np.ndarray) -> np.ndarray:
        """One 30 fps frame: ``substeps`` solver steps with the body (and pins) moving from b0 (pin0) to b1 (pin1)."""
        body_vel = (b1 - b0) * FPS
        for k in range(1, self.substeps + 1):
            w = k / self.substeps
            self._set_body((1.0 - w) * b0 + w * b1, body_vel)
            if self.pinned.any():
                q = self.state_0.particle_q.numpy()
                q[self.pinned] = ((1.0 - w) * pin0 + w * pin1)[self.pinned]
                self.state_0.particle_q.assign(q)
            self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.dt)
            self.state_0, self.state_1 = self.state_1, self.state_0
        return self.state_0.particle_q.numpy().astype(np.float32)

    def run_preroll(self) -> np.ndarray | None:
        """Simulate the lead-in (T-pose -> frame 1) if one was asked for; returns the cloth at frame 1 (V, 3)."""
        if self.preroll_body is None:
            return None
        x = None
        for k in range(1, len(self.preroll_body)):
            x = self._advance(self.preroll_body[k - 1], self.preroll_body[k], self.preroll_pins[k - 1],
                              self.preroll_pins[k])
        return x

    def step_frame(self, t: int) -> np.ndarray:
        """Advance from frame t-1 to frame t (``substeps`` solver steps); returns (V, 3) float32 positions, m."""
        return self._advance(self.body_frames[t - 1], self.body_frames[t], self.skinned[t - 1], self.skinned[t])


def physics_frames(scene, num_frames: int | None = None, *, substeps: int = 20, iterations: int = 10,
                   self_contact: bool = True, progress: bool = False, preroll: int = 0) -> Iterator[RolloutFrame]:
    """Frames 0 .. n-1 of the physics reference in :class:`smln.rollout.RolloutFrame` form.

    Frames 0 and 1 are the skinned initial state (as in :func:`smln.rollout.rollout`); later frames are
    simulated. With ``preroll`` > 0 frame 1 is instead the result of simulating the garments from their rest
    shape through a ``preroll``-frame lead-in from the T-pose to frame 1's pose (frame 0 stays skinned).
    ``metrics["ms_model"]`` is the wall time of the frame's simulation in ms (0 for frames 0-1);
    ``metrics["ms_setup"]`` on frame 0 is the set-up time (model build, kernel load/compile) and
    ``metrics["ms_preroll"]`` the time of the lead-in.
    """
    from smln.losses import ClothRest

    n = scene.num_frames if num_frames is None else min(int(num_frames), scene.num_frames)
    rest = ClothRest.from_cloth(scene.cloth)
    body_faces = scene.body.faces.numpy()
    zeros = np.zeros((scene.cloth.num_vertices, 3), np.float32)
    t0 = time.perf_counter()
    sim = (NewtonClothSim(scene, substeps=substeps, iterations=iterations, self_contact=self_contact,
                          preroll=preroll) if n > 2 else None)
    setup_ms = 1e3 * (time.perf_counter() - t0)
    t0 = time.perf_counter()
    x_preroll = sim.run_preroll() if sim is not None else None
    preroll_ms = 1e3 * (time.perf_counter() - t0)
    for t in range(n):
        t0 = time.perf_counter()
        if t == 1 and x_preroll is not None:
            x = x_preroll
        else:
            x = scene.skinned[t].numpy() if t < 2 else sim.step_frame(t)
        ms = 1e3 * (time.perf_counter() - t0) if t >= 2 else 0.0
        b = scene.body.vertices[t].numpy()
        fm = frame_metrics(x, b, rest, body_faces=body_faces)
        m = dict(fm.values)
        m["ms_model"] = ms
        # a body that moves faster than the contact radius per substep can pass through the cloth and leave it
        # behind (its H-Coll then reads 0): the mean distance to the skinned garments exposes that
        m["skin_offset_mean"] = float(np.linalg.norm(np.asarray(x) - scene.skinned[t].numpy(), axis=1).mean())
        if t == 0:
            m["ms_setup"] = setup_ms
            m["ms_preroll"] = preroll_ms
        if progress:
            print(f"  frame {t:4d}  {ms / 1e3:6.1f} s  H-Coll {m['h_coll']:.2f}%  L-Coll {m['l_coll']:.2f}%  "
                  f"strain mean {100 * m['strain_mean']:.2f}% max {100 * m['strain_max']:.1f}%  "
                  f"from skinning {100 * m['skin_offset_mean']:.1f} cm", flush=True)
        yield RolloutFrame(t, np.asarray(x, np.float32), b.astype(np.float32), zeros, zeros,
                           fm.layer_penetration, fm.body_penetration, m, False)


def run(outfit: str, clip: str, frames: int, out: str | Path, *, shape: str = DEFAULT_SHAPE,
        edge_length: float = TRAINING_EDGE_LENGTH, substeps: int = 20, iterations: int = 10,
        self_contact: bool = True, progress: bool = True, preroll: int = 0) -> list[RolloutFrame]:
    """Simulate ``frames`` frames of ``outfit`` on ``shape`` along ``clip`` and write the rollout NPZ ``out``."""
    from smln.data_sampling import make_scene
    from smln.export import save_rollout_npz

    import_newton()
    scene = make_scene(outfit, shape, clip, edge_length=edge_length, max_frames=frames)
    if progress:
        print(f"{outfit} on {shape} / {clip}: {scene.cloth.num_vertices} cloth vertices "
              f"({scene.cloth.num_layers} layers, edge {edge_length} m), body {scene.body.vertices.shape[1]} "
              f"vertices, {scene.num_frames} frames, {substeps} substeps x {iterations} VBD iterations", flush=True)
    result = list(physics_frames(scene, frames, substeps=substeps, iterations=iterations,
                                 self_contact=self_contact, progress=progress, preroll=preroll))
    import newton

    meta = {"outfit": outfit, "clip": clip, "shape": shape, "variant": "physics (newton VBD)",
            "solver": "newton.solvers.SolverVBD", "newton_version": newton.__version__,
            "edge_length": edge_length, "substeps": substeps, "iterations": iterations,
            "self_contact": self_contact, "preroll": preroll, "contact_radius": CONTACT_RADIUS,
            "self_contact_radius": SELF_CONTACT_RADIUS, "contact_ke": CONTACT_KE,
            "setup_ms": result[0].metrics.get("ms_setup", 0.0)}
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    save_rollout_npz(out, result, scene.cloth, scene.body.faces, meta=meta)
    if progress:
        ms = [f.metrics["ms_model"] for f in result[2:]]
        print(f"wrote {out}: {len(result)} frames, median {np.median(ms) / 1e3 if ms else 0:.2f} s/frame "
              f"(set-up {meta['setup_ms'] / 1e3:.1f} s)", flush=True)
    return result


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--outfit", default="tshirt_jacket")
    p.add_argument("--clip", default="05_01_walk")
    p.add_argument("--shape", default=DEFAULT_SHAPE)
    p.add_argument("--frames", type=int, default=30, help="frames to produce, incl. the 2 skinned initial ones")
    p.add_argument("--edge-length", type=float, default=TRAINING_EDGE_LENGTH,
                   help=f"outfit edge length, m (default: the training outfits, {TRAINING_EDGE_LENGTH})")
    p.add_argument("--substeps", type=int, default=20)
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--no-self-contact", action="store_true", help="turn layer-layer / self contact off")
    p.add_argument("--preroll", type=int, default=0,
                   help="simulate a lead-in of this many frames from the T-pose rest garments to frame 1 "
                        "(0: start from the skinned frame 1)")
    p.add_argument("--out", default=None, help="rollout NPZ (default: runs/physics/<outfit>__<clip>.npz)")
    p.add_argument("--json", help="also write the per-frame metrics as JSON")
    a = p.parse_args(argv)
    try:
        import_newton()
    except SystemExit as exc:
        print(exc, file=sys.stderr)
        raise SystemExit(2) from None
    out = a.out or f"runs/physics/{a.outfit}__{a.clip}.npz"
    frames = run(a.outfit, a.clip, a.frames, out, shape=a.shape, edge_length=a.edge_length, substeps=a.substeps,
                 iterations=a.iterations, self_contact=not a.no_self_contact, preroll=a.preroll)
    if a.json:
        Path(a.json).write_text(json.dumps([f.metrics for f in frames], indent=1))


if __name__ == "__main__":
    main()
