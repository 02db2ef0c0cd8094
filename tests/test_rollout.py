"""Rollout: an untrained model animates two tube layers on a moving capsule; divergence handling."""

import numpy as np
import pytest
import torch

from smln.graph.synthetic import capsule_body, rigid_lbs, sway_motion, tube_outfit
from smln.model import SMLN, SMLNConfig
from smln.rollout import RolloutError, RolloutFrame, rollout


@pytest.fixture(scope="module")
def scene():
    cloth = tube_outfit(radii=(0.12, 0.126), n_around=24, n_rings=10)
    bv, bf = capsule_body(radius=0.1, height=1.2, max_edge=0.03)
    tr = sway_motion(12, amplitude=0.03, period=1.5, angle=0.1)
    body = rigid_lbs(torch.as_tensor(bv), tr)
    return cloth, (body, tr), bf


def small_model(**kw) -> SMLN:
    torch.manual_seed(0)
    return SMLN(SMLNConfig(latent_size=16, schedule=((0, 1), (1, 1), (0, 1)), **kw))


def test_untrained_rollout_10_frames(scene):
    cloth, seq, bf = scene
    frames = list(rollout(small_model(), cloth, seq, bf, num_frames=10))
    assert [f.index for f in frames] == list(range(10))
    v = cloth.num_vertices
    for f in frames:
        assert isinstance(f, RolloutFrame)
        assert f.garment_positions.shape == (v, 3) and f.garment_positions.dtype == np.float32
        assert f.body_vertices.shape == seq[0].shape[1:]
        assert f.predicted_acceleration.shape == (v, 3) and f.repulsion_acceleration.shape == (v, 3)
        assert f.layer_penetration.shape == (v,) and f.layer_penetration.dtype == bool
        assert f.body_penetration.shape == (v,) and f.body_penetration.dtype == bool
        for key in ("l_coll", "h_coll", "strain_mean", "strain_max", "repulsion_mean", "ms_model"):
            assert np.isfinite(f.metrics[key]), key
        assert not f.fallback
        assert np.isfinite(f.garment_positions).all()
    # skinned start: frames 0 and 1 carry no prediction; pinned vertices follow the skinning
    assert np.count_nonzero(frames[0].predicted_acceleration) == 0
    assert np.count_nonzero(frames[5].predicted_acceleration) > 0
    skinned = rigid_lbs(cloth.rest_vertices, seq[1])
    pin = cloth.pinned.numpy()
    np.testing.assert_allclose(frames[7].garment_positions[pin], skinned[7].numpy()[pin], atol=1e-6)


def test_zero_velocity_start(scene):
    cloth, seq, bf = scene
    frames = list(rollout(small_model(use_repulsion_layer=False), cloth, seq, bf, num_frames=3,
                          initial_velocity="zero"))
    assert np.count_nonzero(frames[1].predicted_acceleration) > 0
    assert all(np.count_nonzero(f.repulsion_acceleration) == 0 for f in frames)


def exploding_model() -> SMLN:
    m = small_model()
    with torch.no_grad():  # p = 10 m/frame^2 on every free vertex, whatever the init: diverges on the first step
        m.decoder[-1].weight.zero_()
        m.decoder[-1].bias.fill_(1.0)
        m.output_scale.fill_(10.0)
    return m


def test_divergence_raises_with_frame(scene):
    cloth, seq, bf = scene
    with pytest.raises(RolloutError, match="frame 2"):
        list(rollout(exploding_model(), cloth, seq, bf, num_frames=5))


def test_divergence_fallback_to_skinning(scene):
    cloth, seq, bf = scene
    frames = list(rollout(exploding_model(), cloth, seq, bf, num_frames=5, fallback=True))
    assert [f.fallback for f in frames] == [False, False, True, True, True]
    skinned = rigid_lbs(cloth.rest_vertices, seq[1])
    np.testing.assert_allclose(frames[3].garment_positions, skinned[3].numpy(), atol=1e-6)


def drifting_model(acceleration: float) -> SMLN:
    """A model that accelerates every free vertex by ``acceleration`` m/frame^2 along (1, 1, 1)/sqrt(3)."""
    m = small_model(use_repulsion_layer=False)
    with torch.no_grad():
        m.decoder[-1].weight.zero_()
        m.decoder[-1].bias.fill_(1.0)
        m.output_scale.fill_(acceleration / 3**0.5)
    return m


def test_body_distance_guard(scene):
    """The guard on the distance to the body fires on its own (other bounds off) and names the cause; the
    per-frame ``body_distance_max`` is the nearest-body-vertex distance computed independently."""
    from scipy.spatial import cKDTree

    cloth, seq, bf = scene
    model = drifting_model(0.02)  # free vertices 2, 6, 12 cm off after the first 3 predicted steps
    loose = dict(max_distance=1e9, max_strain=1e9)
    with pytest.raises(RolloutError, match=r"frame \d+: .* m from the body \(> 0.08 m\)"):
        list(rollout(model, cloth, seq, bf, num_frames=8, max_body_distance=0.08, **loose))
    frames = list(rollout(model, cloth, seq, bf, num_frames=8, max_body_distance=1e9, **loose))
    assert not any(f.fallback for f in frames)
    dist = [float(cKDTree(f.body_vertices).query(f.garment_positions)[0].max()) for f in frames]
    np.testing.assert_allclose([f.metrics["body_distance_max"] for f in frames], dist, rtol=1e-5)
    assert dist[-1] > 0.08 > dist[1]  # the bound of the first call was crossed, and not at the start
    fb = list(rollout(model, cloth, seq, bf, num_frames=8, max_body_distance=0.08, fallback=True, **loose))
    first = next(i for i, f in enumerate(fb) if f.fallback)
    assert dist[first] > 0.08 and all(d <= 0.08 for d in dist[:first])


def _still_model() -> SMLN:
    """A model whose decoder predicts exactly zero acceleration and has no repulsion layer: x_{t+1} = x_t + v_t."""
    m = small_model(use_repulsion_layer=False)
    with torch.no_grad():
        m.decoder[-1].weight.zero_()
        m.decoder[-1].bias.zero_()
    return m


@pytest.mark.parametrize("settle_steps", [0, 1, 2])
def test_settle_steps_reset_the_velocity_to_skinning(scene, settle_steps):
    cloth, seq, bf = scene
    frames = list(rollout(_still_model(), cloth, seq, bf, num_frames=6, settle_steps=settle_steps))
    s = rigid_lbs(cloth.rest_vertices, seq[1]).numpy().astype(np.float64)
    x = [f.garment_positions.astype(np.float64) for f in frames]
    free = ~cloth.pinned.numpy()
    # expected by hand: inertial steps, with the velocity replaced by the skinning's after each settle step
    exp = [s[0], s[1]]
    v = s[1] - s[0]
    for t in range(2, 6):
        exp.append(exp[-1] + v)
        v = s[t] - s[t - 1] if t - 2 < settle_steps else exp[-1] - exp[-2]
    for t in range(2, 6):
        np.testing.assert_allclose(x[t][free], exp[t][free], atol=2e-5, err_msg=f"frame {t}")
    # the sway motion changes velocity, so settling makes a visible difference by frame 3
    if settle_steps:
        assert np.abs((s[2] - s[1]) - (s[1] - s[0]))[free].max() > 1e-4


def test_shared_body_tree_changes_nothing(scene, monkeypatch):
    """The body KD-tree built once per frame (metrics of frame t, graph of the step from t) and the nearest body
    vertices the metrics found give the same rollout as querying in every step, and they belong to the right
    frame."""
    cloth, seq, bf = scene
    step = SMLN.step
    seen = []

    def spy(self, topology, x_prev, x_cur, body_cur, body_next, pinned_next=None, body_tree=None,
            body_nearest=None, body_normals_next=None, body_tree_next=None):
        g = topology.build(x_prev, x_cur, body_cur, body_next, pinned_next, body_normals_next=body_normals_next)
        seen.append((body_tree, body_nearest, x_cur.numpy().copy(), body_cur.numpy().copy(), len(g.body_receivers)))
        assert body_tree_next is None  # only a model whose body stage reads the body at t+1 gets that tree
        return step(self, topology, x_prev, x_cur, body_cur, body_next, pinned_next, body_tree=body_tree,
                    body_nearest=body_nearest, body_normals_next=body_normals_next)

    monkeypatch.setattr(SMLN, "step", spy)
    shared = list(rollout(small_model(), cloth, seq, bf, num_frames=6))
    assert len(seen) == 4 and all(n > 0 for *_, n in seen)  # body edges exist, so the tree matters
    for tree, near, x_cur, body_cur, _ in seen:
        assert tree is not None and near is not None
        np.testing.assert_array_equal(tree.points, body_cur.astype(np.float32))
        d = np.linalg.norm(x_cur[:, None, :] - body_cur[None], axis=-1)  # brute force
        np.testing.assert_array_equal(near[0], d.argmin(1))
        np.testing.assert_allclose(near[1], d.min(1), atol=1e-6)
    monkeypatch.setattr(SMLN, "step", lambda self, *a, body_tree=None, body_nearest=None, body_tree_next=None, **kw:
                        step(self, *a, **kw))
    own = list(rollout(small_model(), cloth, seq, bf, num_frames=6))
    for f, g in zip(shared, own, strict=True):
        np.testing.assert_array_equal(f.garment_positions, g.garment_positions)
        drop = ("ms_model",)
        assert {k: v for k, v in f.metrics.items() if k not in drop} == {
            k: v for k, v in g.metrics.items() if k not in drop
        }


def test_symptomatic_skin_guard_lets_a_healthy_excursion_go_on(scene):
    """``skin_guard="symptomatic"``: past ``max_distance`` from skinning a frame diverges only with a symptom
    (mean strain or H-Coll above the thresholds) or past twice that distance; "always" is the plain bound."""
    cloth, seq, bf = scene
    model = drifting_model(0.02)
    loose = dict(max_body_distance=1e9, max_strain=1e9, num_frames=10)
    free = list(rollout(model, cloth, seq, bf, max_distance=1e9, **loose))
    skinned = rigid_lbs(cloth.rest_vertices, seq[1]).numpy()
    dist = np.array([np.linalg.norm(f.garment_positions - skinned[f.index], axis=1).max() for f in free])
    bound = 0.1
    assert dist[-1] > 2 * bound and dist[2] < bound  # the drift crosses both bounds within the clip
    first_over = int(np.argmax(dist > bound))
    first_hard = int(np.argmax(dist > 2 * bound))
    assert first_hard > first_over

    def first_fallback(**kw) -> int:
        frames = list(rollout(model, cloth, seq, bf, max_distance=bound, fallback=True, **loose, **kw))
        return next(i for i, f in enumerate(frames) if f.fallback)

    assert first_fallback() == first_over
    # no symptom can fire (thresholds out of reach): only the hard bound at twice the distance
    assert first_fallback(skin_guard="symptomatic", symptom_strain_mean=1e9, symptom_h_coll=1e9) == first_hard
    # every frame symptomatic: the plain bound again
    assert first_fallback(skin_guard="symptomatic", symptom_strain_mean=-1.0) == first_over
    assert first_fallback(skin_guard="symptomatic", symptom_strain_mean=1e9, symptom_h_coll=-1.0) == first_over
    with pytest.raises(RolloutError, match=r"from its skinned position \(> 0.1 m\) at mean strain"):
        list(rollout(model, cloth, seq, bf, max_distance=bound, skin_guard="symptomatic", symptom_strain_mean=-1.0,
                     **loose))
    with pytest.raises(ValueError, match="skin_guard"):
        list(rollout(model, cloth, seq, bf, skin_guard="sometimes", **loose))


def test_nearest_body_pairing_reuses_the_frame_tree(scene, monkeypatch):
    """A model whose body stage reads the body at t+1 (body_pairing "nearest") gets the KD-tree the metrics of frame
    t+1 use, over the body at t+1, and rolls out exactly as when it builds its own."""
    cloth, seq, bf = scene
    model = small_model(body_repulsion=True, body_pairing="nearest").eval()
    step = SMLN.step
    trees = []

    def spy(self, *a, body_tree_next=None, **kw):
        trees.append((body_tree_next, a[4].numpy().copy()))  # a[4]: body_next
        return step(self, *a, body_tree_next=body_tree_next, **kw)

    monkeypatch.setattr(SMLN, "step", spy)
    shared = list(rollout(model, cloth, seq, bf, num_frames=6))
    assert len(trees) == 4
    for tree, body_next in trees:
        np.testing.assert_array_equal(tree.points, body_next.astype(np.float32))
    monkeypatch.setattr(SMLN, "step", lambda self, *a, body_tree_next=None, **kw: step(self, *a, **kw))
    own = list(rollout(model, cloth, seq, bf, num_frames=6))
    for f, g in zip(shared, own, strict=True):
        np.testing.assert_array_equal(f.garment_positions, g.garment_positions)
