"""SMLN network: shapes, pinned vertices, translation invariance, repulsion layer, normaliser, backward."""

import pytest
import torch

from smln.geometry import vertex_normals
from smln.graph.synthetic import capsule_body, rigid_lbs, sway_motion, tube_outfit
from smln.model import MLP, SMLN, Normalizer, RepulsionLayer, SMLNConfig


@pytest.fixture(scope="module")
def scene():
    torch.manual_seed(0)
    cloth = tube_outfit(radii=(0.12, 0.125), n_around=24, n_rings=10)
    bv, bf = capsule_body(radius=0.1, height=1.2, max_edge=0.03)
    tr = sway_motion(4)
    body = rigid_lbs(torch.as_tensor(bv), tr)
    return cloth, body, rigid_lbs(cloth.rest_vertices, tr), vertex_normals(body, torch.as_tensor(bf))


def small_config(**kw):
    base = dict(latent_size=16, schedule=((0, 1), (1, 1), (2, 1), (1, 1), (0, 1)))
    base.update(kw)
    return SMLNConfig(**base)


def test_config_validation():
    with pytest.raises(ValueError):
        SMLNConfig(schedule=((0, 1), (2, 1), (0, 1)))
    with pytest.raises(ValueError):
        SMLNConfig(schedule=((1, 1), (0, 1)))
    with pytest.raises(ValueError):
        SMLNConfig(coarse_edges="two_hop")  # needs anchors="bfs_even"
    with pytest.raises(ValueError):
        SMLNConfig(coarse_edges="knn")
    cfg = SMLNConfig()
    assert (cfg.coarse_edges, cfg.anchors) == ("cluster", "mis")
    assert SMLNConfig.from_dict(cfg.to_dict()) == cfg
    legacy = SMLNConfig(coarse_edges="two_hop", anchors="bfs_even")
    assert SMLNConfig.from_dict(legacy.to_dict()) == legacy


def test_mlp_layernorm_and_decoder():
    m = MLP(5, 8, 16, 2)
    assert isinstance(m[-1], torch.nn.LayerNorm)
    assert sum(isinstance(x, torch.nn.Linear) for x in m) == 3
    d = MLP(5, 3, 16, 2, layer_norm=False)
    assert isinstance(d[-1], torch.nn.Linear)


def test_forward_shapes_and_pinned(scene):
    cloth, body, xs, normals = scene
    model = SMLN(small_config()).eval()
    topo = model.make_topology(cloth)
    with torch.no_grad():
        p, a, ex = model.step(topo, xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    v = cloth.num_vertices
    assert p.shape == (v, 3) and a.shape == (v, 3)
    assert torch.all(torch.isfinite(p)) and torch.all(torch.isfinite(a))
    pin = cloth.pinned
    assert torch.all(p[pin] == 0) and torch.all(a[pin] == 0)
    assert torch.allclose(ex["x_next"][pin], xs[2][pin])
    assert p[~pin].abs().max() > 0


def test_default_config_runs(scene):
    cloth, body, xs, normals = scene
    model = SMLN().eval()
    topo = model.make_topology(cloth)
    with torch.no_grad():
        p, a, _ = model.step(topo, xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    assert torch.all(torch.isfinite(p))


def test_translation_invariance(scene):
    cloth, body, xs, normals = scene
    torch.manual_seed(1)
    model = SMLN(small_config(repulsion_threshold=0.02)).eval()  # wide threshold: repulsion active
    topo = model.make_topology(cloth)
    shift = torch.tensor([0.3, -0.2, 0.5])
    with torch.no_grad():
        p0, a0, _ = model.step(topo, xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
        p1, a1, _ = model.step(topo, xs[0] + shift, xs[1] + shift, body[1] + shift, body[2] + shift, xs[2] + shift,
                                 body_normals_next=normals[2])
    assert a0.abs().max() > 0
    assert torch.allclose(p0, p1, atol=1e-5)
    assert torch.allclose(a0, a1, atol=1e-5)


def _two_sheets(gap: float):
    """Inner 3x3 vertex grid at z=0 (normals +Z) and one outer vertex above its centre at height ``gap``."""
    g = torch.stack(torch.meshgrid(torch.arange(3.0), torch.arange(3.0), indexing="ij"), -1).reshape(-1, 2) * 0.01
    inner = torch.cat([g, torch.zeros(9, 1)], 1)
    outer = torch.tensor([[0.01, 0.01, gap]])
    x = torch.cat([inner, outer])
    normals = torch.zeros(10, 3)
    normals[:, 2] = 1.0
    pairs = torch.tensor([[9], [4]])
    return x, normals, pairs


def test_repulsion_zero_when_separated():
    layer = RepulsionLayer(threshold=0.005)
    x, n, pairs = _two_sheets(0.0051)
    a, ex = layer(x, x, n, pairs)
    assert torch.count_nonzero(a) == 0
    assert ex["active_pairs"].shape[1] == 0


def test_repulsion_pushes_penetrating_vertex_outward():
    torch.manual_seed(0)
    layer = RepulsionLayer(threshold=0.005)
    x, n, pairs = _two_sheets(-0.002)  # outer vertex 2 mm behind the inner layer
    a, ex = layer(x, x, n, pairs)
    assert a[9, 2] > 0  # along +n_j
    assert torch.allclose(a[9, :2], torch.zeros(2))
    assert torch.count_nonzero(a[:9]) == 0  # inner vertices are not pushed
    assert ex["active_pairs"].shape[1] == 1
    # continuous at the threshold: smaller push closer to it
    x2, _, _ = _two_sheets(0.004)
    a2, _ = layer(x2, x2, n, pairs)
    assert 0 < a2[9, 2] < a[9, 2]


def test_repulsion_off_gives_zeros(scene):
    cloth, body, xs, normals = scene
    model = SMLN(small_config(use_repulsion_layer=False)).eval()
    topo = model.make_topology(cloth)
    with torch.no_grad():
        _, a, _ = model.step(topo, xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    assert torch.count_nonzero(a) == 0


def test_normalizer_accumulates_then_freezes():
    nm = Normalizer(2, max_accumulations=2).eval()
    x = torch.tensor([[1.0, 10.0], [3.0, 30.0]])
    assert torch.equal(nm(x), x)  # identity before any data
    assert nm.count.item() == 0  # no accumulation in eval mode
    nm.train()
    nm(x)
    mean, std = nm.mean_std()
    assert torch.allclose(mean, torch.tensor([2.0, 20.0]))
    nm(x + 100)
    assert nm.frozen
    before = nm.total.clone()
    nm(x)
    assert torch.equal(nm.total, before)
    assert set(dict(nm.named_buffers())) == {"count", "calls", "total", "total_sq"}
    # the cached statistics follow a state-dict load (in-place copy into the buffers)
    other = Normalizer(2, max_accumulations=2)
    other.load_state_dict(nm.state_dict())
    assert torch.equal(other.mean_std()[0], nm.mean_std()[0])
    nm.load_state_dict(Normalizer(2).state_dict())
    assert torch.equal(nm.mean_std()[0], torch.zeros(2))


def test_backward_reaches_all_weights(scene):
    cloth, body, xs, normals = scene
    model = SMLN(small_config(repulsion_threshold=0.02)).train()
    topo = model.make_topology(cloth)
    p, a, ex = model.step(topo, xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    loss = (ex["x_next"] ** 2).sum()
    loss.backward()
    unused = "coarse_encoders.2."  # level 3 is not visited by the small schedule
    missing = [n for n, w in model.named_parameters() if w.grad is None and not n.startswith(unused)]
    assert not missing, missing


def test_repulsion_cascade_lets_the_outer_layer_see_the_pushed_middle_layer():
    """Three stacked sheets: the middle one 2 mm behind the inner one, the outer one 6 mm in front of the middle
    one (beyond the 5 mm threshold). Applied all at once only the middle layer is pushed; in the cascade the
    outer layer is processed against the middle layer's pushed position and is pushed too. With two layers the
    cascade is exactly one call."""
    from types import SimpleNamespace

    from smln.model import SMLN, SMLNConfig

    torch.manual_seed(0)
    g = torch.stack(torch.meshgrid(torch.arange(3.0), torch.arange(3.0), indexing="ij"), -1).reshape(-1, 2) * 0.01
    sheet = torch.cat([g, torch.zeros(9, 1)], 1)
    quads = [(0, 1, 4), (0, 4, 3), (1, 2, 5), (1, 5, 4), (3, 4, 7), (3, 7, 6), (4, 5, 8), (4, 8, 7)]
    faces = torch.tensor([[a + 9 * k, c + 9 * k, b + 9 * k] for k in range(3) for a, b, c in quads])  # normals +z
    x = torch.cat([sheet, sheet + torch.tensor([0, 0, -0.002]), sheet + torch.tensor([0, 0, 0.004])])
    layer = torch.arange(3).repeat_interleave(9)
    pairs = torch.stack([torch.arange(9, 27), torch.cat([torch.arange(9), torch.arange(9, 18)])])
    model = SMLN(SMLNConfig(use_repulsion_layer=True))
    model.repulsion.mlp[-1].bias.data.fill_(3.0)  # a sizeable push (softplus(3) * clearance)
    free = torch.ones(27, 1)
    topo3 = SimpleNamespace(num_layers=3, layer_index=layer, faces=faces)
    graph = SimpleNamespace(x_cur=x, repulsion_pairs=pairs)
    a, rep = model._cascade_repulsion(topo3, graph, x, free)
    assert (a[9:18, 2] > 0).all()  # middle layer pushed out of the inner one
    assert (a[18:, 2] > 0).all()  # ... and the outer layer reacts in the same step
    at_once, _ = model.repulsion(x, x, torch.tensor([[0.0, 0.0, 1.0]]).expand(27, 3), pairs)
    assert torch.count_nonzero(at_once[18:]) == 0
    assert rep["active_pairs"].shape[1] == 18
    # two layers: identical to one call of the layer
    topo2 = SimpleNamespace(num_layers=2, layer_index=layer.clamp(max=1), faces=faces[:16])
    pairs2 = pairs[:, :9]
    a2, _ = model._cascade_repulsion(topo2, SimpleNamespace(x_cur=x[:18], repulsion_pairs=pairs2), x[:18], free[:18])
    from smln.geometry import vertex_normals

    ref, _ = model.repulsion(x[:18], x[:18], vertex_normals(x[:18], faces[:16]), pairs2)
    assert torch.allclose(a2, ref, atol=1e-6)


def _one_step_graph(model):
    """(topology, graph) of one step of a small two-layer tube on a capsule body, for inference comparisons."""
    cloth = tube_outfit(radii=(0.12, 0.126), n_around=16, n_rings=6)
    topo = model.make_topology(cloth)
    x = cloth.rest_vertices
    bv, bf = capsule_body(radius=0.1, height=1.2, max_edge=0.03)
    body = torch.as_tensor(bv)
    g = topo.build(x, x + 0.002, body, body + 0.001, x + 0.004,
                   body_normals_next=vertex_normals(body, torch.as_tensor(bf)))
    return topo, g


def test_bfloat16_processor_is_close_and_leaves_the_model_alone():
    """The bfloat16 processor copy predicts nearly the same accelerations and shares/keeps the float32 weights."""
    from smln.model.precision import with_processor_dtype

    model = SMLN(SMLNConfig(latent_size=32)).eval()
    assert with_processor_dtype(model, "float32") is model
    low = with_processor_dtype(model, "bfloat16")
    assert low.node_encoder is model.node_encoder and low.processor is not model.processor
    assert next(model.processor.parameters()).dtype == torch.float32  # the original is untouched
    topo, g = _one_step_graph(model)
    with torch.no_grad():
        p32, _, _ = model(g, topo)
        p16, _, _ = low(g, topo)
    assert p16.dtype == torch.float32
    err = float((p32 - p16).norm(dim=-1).mean() / p32.norm(dim=-1).mean())
    assert 0.0 < err < 0.05  # bfloat16 rounding, not a different model
    with pytest.raises(ValueError, match="precision"):
        with_processor_dtype(model, "int8")


def test_widen_body_edges_keeps_the_function(scene):
    """A model without body-normal features widened to one with them predicts the same p and a (the new encoder
    columns start at zero), its normaliser takes the new columns' statistics from the samples, and the rest of the
    statistics and weights are copied."""
    from smln.model.migrate import widen_body_edges

    cloth, body, xs, normals = scene
    torch.manual_seed(1)
    old = SMLN(small_config(body_normal_features=False))
    old.train()
    for t in (1, 2):  # accumulate some normaliser statistics and move the weights off their init
        topo_o = old.make_topology(cloth)
        old(topo_o.build(xs[t - 1], xs[t], body[t], body[t + 1], xs[t + 1]), topo_o)
    with torch.no_grad():
        for prm in old.parameters():
            prm.add_(0.01 * torch.randn_like(prm))
    old.eval()
    new = SMLN(small_config())
    topo_n = new.make_topology(cloth)
    g = topo_n.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    samples = g.body_features[:, 9:]
    widen_body_edges(old, new, samples)
    new.eval()
    topo_o = old.make_topology(cloth)
    with torch.no_grad():
        po, ao, _ = old(topo_o.build(xs[0], xs[1], body[1], body[2], xs[2]), topo_o)
        pn, an, _ = new(g, topo_n)
    assert torch.equal(po, pn) and torch.equal(ao, an) and po.abs().max() > 0
    mean, std = new.body_norm.mean_std()
    mean_o, std_o = old.body_norm.mean_std()
    assert torch.allclose(mean[:9], mean_o) and torch.allclose(std[:9], std_o)
    assert torch.allclose(mean[9:], samples.mean(0), atol=1e-6)
    assert torch.allclose(std[9:], samples.std(0, unbiased=False).clamp_min(1e-4), atol=1e-5)
    with pytest.raises(ValueError, match="same config"):
        widen_body_edges(old, SMLN(small_config(latent_size=8)), samples)
    with pytest.raises(ValueError, match="new_columns"):
        widen_body_edges(old, new, samples[:, :3])


def _trained_looking(cfg: SMLNConfig, scene) -> SMLN:
    """A model with some normaliser statistics and weights moved off their init (eval mode)."""
    cloth, body, xs, normals = scene
    model = SMLN(cfg)
    model.train()
    for t in (1, 2):
        topo = model.make_topology(cloth)
        model(topo.build(xs[t - 1], xs[t], body[t], body[t + 1], xs[t + 1], body_normals_next=normals[t + 1]), topo)
    with torch.no_grad():
        for prm in model.parameters():
            prm.add_(0.05 * torch.randn_like(prm))
    return model.eval()


@pytest.mark.parametrize("growth", [
    {"mlp_hidden_layers": 2},
    {"mlp_hidden_layers": 3},
    {"schedule": ((0, 2), (1, 3), (2, 1), (1, 2), (0, 1))},
    {"mlp_hidden_layers": 2, "schedule": ((0, 1), (1, 1), (2, 2), (1, 1), (0, 2))},
])
def test_grow_keeps_the_function_and_the_new_weights_train(scene, growth):
    """A grown model (more hidden layers, more steps per schedule visit) predicts exactly what its parent did, has
    more parameters, and a backward pass reaches the added layers (so fine-tuning can use them)."""
    from smln.model.migrate import grow

    cloth, body, xs, normals = scene
    torch.manual_seed(3)
    old = _trained_looking(small_config(), scene)
    new = SMLN(small_config(**growth))
    grow(old, new)
    new.eval()
    topo = old.make_topology(cloth)
    g = topo.build(xs[0], xs[1], body[1], body[2], xs[2], body_normals_next=normals[2])
    with torch.no_grad():
        po, ao, _ = old(g, topo)
        pn, an, _ = new(g, topo)
    assert po.abs().max() > 0
    torch.testing.assert_close(pn, po, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(an, ao, rtol=1e-6, atol=1e-9)
    n_old = sum(p.numel() for p in old.parameters())
    assert sum(p.numel() for p in new.parameters()) > n_old
    new.train()
    p, _, _ = new(g, topo)
    (p ** 2).sum().backward()
    if "mlp_hidden_layers" in growth:  # the inserted identity layer of the decoder
        assert new.decoder[2].weight.grad.abs().sum() > 0
    if "schedule" in growth:  # an added block: only its zero LayerNorm scales get gradient at first
        added = new.processor.blocks[1] if growth["schedule"][0][1] == 2 else new.processor.blocks[-1]
        assert added.node_model[-1].weight.grad.abs().sum() > 0


def test_grow_refuses_what_is_not_a_growth():
    from smln.model.migrate import grow

    old = SMLN(small_config(mlp_hidden_layers=2, schedule=((0, 2), (1, 1), (2, 1), (1, 1), (0, 1))))
    for bad, match in [({"latent_size": 8}, "differ"), ({"mlp_hidden_layers": 1}, "shrink"),
                       ({"schedule": ((0, 2), (1, 1), (0, 1))}, "same levels"),
                       ({"schedule": ((0, 1), (1, 1), (2, 1), (1, 1), (0, 1))}, "lose")]:
        cfg = {"mlp_hidden_layers": 2, "schedule": old.config.schedule, **bad}
        with pytest.raises(ValueError, match=match):
            grow(old, SMLN(small_config(**cfg)))


def _compile_case():
    model = SMLN(small_config()).eval()
    return (model, *_one_step_graph(model))


@pytest.mark.slow
def test_compiled_processor_predicts_what_the_eager_one_does():
    import shutil

    from smln.model.compiled import with_compiled_processor

    if not (shutil.which("g++") or shutil.which("c++")):
        pytest.skip("no C++ compiler: torch.compile's CPU backend cannot build (the eager fallback is tested below)")

    model, topo, g = _compile_case()
    fast = with_compiled_processor(model)
    assert fast.processor is not model.processor and fast.node_encoder is model.node_encoder
    assert "processor" in dict(model.named_children()) and not hasattr(model.processor, "inner")  # untouched
    with torch.no_grad():
        p_eager, _, _ = model(g, topo)
        p_fast, _, _ = fast(g, topo)
    assert fast.processor.failed is None
    torch.testing.assert_close(p_fast, p_eager, rtol=1e-4, atol=1e-6)
    assert set(fast.state_dict()) == {k.replace("processor.", "processor.inner.", 1) for k in model.state_dict()}


@pytest.mark.slow
def test_compiled_processor_for_training_gives_the_eager_gradients():
    """smln train --compile: the compiled processor's forward and backward match eager autograd."""
    import shutil

    from smln.model.compiled import with_compiled_processor

    if not (shutil.which("g++") or shutil.which("c++")):
        pytest.skip("no C++ compiler: torch.compile's CPU backend cannot build")

    model, topo, g = _compile_case()
    model.train()
    fast = with_compiled_processor(model, training=True)
    assert fast.training and fast.processor.for_training

    def grads(net):
        model.zero_grad(set_to_none=True)
        p, _, _ = net(g, topo)
        (p**2).sum().backward()
        return p.detach(), [q.grad.clone() for q in model.processor.parameters()]

    p_eager, g_eager = grads(model)
    p_fast, g_fast = grads(fast)
    assert fast.processor.failed is None
    torch.testing.assert_close(p_fast, p_eager, rtol=1e-4, atol=1e-6)
    assert any(bool(x.abs().max() > 0) for x in g_eager)  # the check compares real gradients, not zeros
    for a, b in zip(g_fast, g_eager, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-6)


def test_compiled_processor_falls_back_to_eager_when_compilation_fails(monkeypatch):
    from smln.model import compiled

    def broken(module, **kwargs):
        def call(*a, **k):
            raise RuntimeError("no C++ compiler found")
        return call

    monkeypatch.setattr(compiled.torch, "compile", broken)
    model, topo, g = _compile_case()
    wrapper = compiled.CompiledProcessor(model.processor)
    fast = compiled.with_compiled_processor(model)
    fast._modules["processor"] = wrapper
    with torch.no_grad():
        p_eager, _, _ = model(g, topo)
        with pytest.warns(RuntimeWarning, match="no C.. compiler"):
            p_fast, _, _ = fast(g, topo)
    assert wrapper.failed is not None and "no C++ compiler" in wrapper.failed
    assert torch.equal(p_fast, p_eager)
