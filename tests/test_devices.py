"""The same closed-form checks on every device (`device` fixture: the CPU, and CUDA where present) for rays,
compositing, grid reads and training steps; the GPU sizing of presets (`recon.config.device_sizing`); and the
compiled colour network against its eager reference (`recon.nerf.compiled`)."""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import pytest
import torch

from recon.config import (GPU_DISTORTION_FROM, GPU_FEATURE_LEVELS, GPU_HASH_FEATURES, GPU_HASH_KEYS, GPU_SH_DEGREE,
                          GPU_TIERS, device_sizing, load_config)
from recon.nerf.compiled import compile_color_network, compile_wanted
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.fitting import RayBatcher
from recon.nerf.grid import DenseGrid, MultiDenseGrid
from recon.nerf.rays import camera_rays, pixel_rays, ray_aabb
from recon.nerf.render import render_packed, render_weights_packed
from recon.nerf.trainer import train

GiB = 2**30
TINY = dict(density_res=24, feature_res=16, feature_dim=4, occupancy_res=8, occupancy_warmup=4,
            occupancy_every=2, mlp_width=16, mlp_layers=1)


# ----------------------------------------------------------------------------- rays
def test_camera_rays_are_unit_and_the_centre_ray_looks_down_minus_z(device: torch.device) -> None:
    c2w = torch.eye(4, device=device)
    c2w[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    o, d = camera_rays(c2w, 10.0, 10.0, 2.0, 2.0, 4, 4)
    assert o.device.type == device.type and d.shape == (4, 4, 3)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(4, 4, device=device))
    # the pixel whose centre is 0.5 px right of and below the principal point: direction (0.05, -0.05, -1), normalized
    torch.testing.assert_close(d[2, 2], torch.nn.functional.normalize(torch.tensor([0.05, -0.05, -1.0], device=device), dim=0))
    torch.testing.assert_close(o[3, 1], torch.tensor([1.0, 2.0, 3.0], device=device))


def test_pixel_rays_and_box_entry_match_the_geometry(device: torch.device) -> None:
    n = 5
    c2w = torch.eye(4, device=device).expand(n, 4, 4).clone()
    c2w[:, 2, 3] = 3.0  # cameras at z = 3 looking down -Z at the unit box
    f = torch.full((n,), 100.0, device=device)
    c = torch.zeros(n, device=device)
    px = torch.linspace(-20.0, 20.0, n, device=device)  # slopes x / f in [-0.2, 0.2]: in through the top, out the bottom
    o, d = pixel_rays(c2w, f, f, c, c, px, torch.zeros(n, device=device))
    t0, t1, hit = ray_aabb(o, d, torch.tensor([[-1.0] * 3, [1.0] * 3], device=device))
    assert bool(hit.all())
    torch.testing.assert_close(t0 * -d[:, 2], torch.full((n,), 2.0, device=device))  # enters the top face z = 1
    torch.testing.assert_close(t1 * -d[:, 2], torch.full((n,), 4.0, device=device))  # leaves the bottom face z = -1


# ----------------------------------------------------------------------------- compositing
def test_packed_compositing_of_a_constant_density_is_beer_lambert(device: torch.device) -> None:
    """Ray r has 10 samples (ray 1 none) of density r + 1, intervals of 0.1: T_i = exp(-σ 0.1 i), opacity 1 - exp(-σ)."""
    counts = torch.tensor([10, 0, 10, 10], device=device)
    ri = torch.repeat_interleave(torch.arange(4, device=device), counts)
    sigma = (ri + 1).float()
    delta = torch.full_like(sigma, 0.1)
    i = torch.cat([torch.arange(int(c), device=device) for c in counts.cpu()]).float()
    w, trans = render_weights_packed(sigma, delta, ri, 4)
    torch.testing.assert_close(trans, torch.exp(-sigma * 0.1 * i))
    out = render_packed(sigma, torch.full((ri.shape[0], 3), 0.25, device=device), 0.1 * (i + 0.5), delta, ri, 4,
                        torch.ones(3, device=device))
    opacity = 1 - torch.exp(-torch.tensor([1.0, 0.0, 3.0, 4.0], device=device))
    torch.testing.assert_close(out["opacity"], opacity)
    torch.testing.assert_close(out["rgb"], (0.25 * opacity + (1 - opacity))[:, None].expand(4, 3))


# ----------------------------------------------------------------------------- grids
def test_dense_grids_reproduce_a_linear_field_and_its_gradient(device: torch.device) -> None:
    """Trilinear interpolation is exact on a linear function of the vertices, and d(read)/d(table) sums to 1."""
    res = 9
    lin = torch.linspace(0, 1, res, device=device)
    gx, gy, gz = torch.meshgrid(lin, lin, lin, indexing="ij")
    field = (1.0 + 2.0 * gx - 3.0 * gy + 0.5 * gz).reshape(-1, 1)
    grid = DenseGrid(res, 2).to(device)
    with torch.no_grad():
        grid.table.copy_(torch.cat([field, 2 * field], dim=1))
    x = torch.rand(200, 3, generator=torch.Generator().manual_seed(0)).to(device)
    expect = 1.0 + 2.0 * x[:, 0] - 3.0 * x[:, 1] + 0.5 * x[:, 2]
    out = grid(x)
    torch.testing.assert_close(out, torch.stack([expect, 2 * expect], dim=1), rtol=1e-5, atol=1e-5)
    out[:, 0].sum().backward()
    assert float(grid.table.grad[:, 0].sum()) == pytest.approx(200.0, rel=1e-5)
    levels = MultiDenseGrid(17, 1, levels=2).to(device)  # one channel: the grid_sample path, summed over levels
    with torch.no_grad():
        for g in levels.grids:
            lg = torch.linspace(0, 1, g.res, device=device)
            g.table.copy_(lg[:, None, None].expand(g.res, g.res, g.res).reshape(-1, 1))
    torch.testing.assert_close(levels(x)[:, 0], 2 * x[:, 0], rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------- a training step
def _ball_batcher(device: torch.device, size: int = 16, views: int = 6) -> RayBatcher:
    """Views of a red ball of radius 0.5 at the origin on white (its silhouette drawn in closed form)."""
    angles = torch.arange(views) * 2 * math.pi / views
    c2w = []
    for a in angles:
        eye = torch.tensor([3 * math.cos(a), 3 * math.sin(a), 0.6])
        back = eye / eye.norm()
        right = torch.nn.functional.normalize(torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back), dim=0)
        m = torch.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, torch.linalg.cross(back, right), back, eye
        c2w.append(m)
    c2w = torch.stack(c2w)
    f = 1.2 * size
    intr = torch.tensor([[f, f, size / 2, size / 2]]).expand(views, 4).contiguous()
    images = []
    for m in c2w:
        o, d = camera_rays(m, f, f, size / 2, size / 2, size, size)
        closest = (o - (o * d).sum(-1, keepdim=True) * d).norm(dim=-1)
        images.append(torch.where((closest < 0.5)[..., None], torch.tensor([1.0, 0.1, 0.1]), torch.ones(3)))
    return RayBatcher(torch.stack(images), c2w, intr, aabb=torch.tensor([[-1.0] * 3, [1.0] * 3]), device=device)


def test_training_steps_fit_a_ball_on_every_device(device: torch.device) -> None:
    torch.manual_seed(0)
    model = FastModel(FastConfig(aabb=((-1.0,) * 3, (1.0,) * 3), **TINY)).to(device)
    result = train(model, _ball_batcher(device), steps=20, lr=1e-2, batch_rays=256, history_every=5)
    first, last = result["history"][0][2], result["history"][-1][2]
    assert math.isfinite(result["loss"]) and last > first + 3.0, result["history"]
    assert model.density_grid.grids[0].table.device.type == device.type


def test_the_batcher_serves_every_ray_once_an_epoch_and_resumes_on_its_device(device: torch.device) -> None:
    """The epoch's shuffle is drawn on the batcher's device (a GPU draws its own order): each kept ray once per epoch,
    each epoch in a new order, and a batcher loaded with a state taken mid-epoch serves what the original serves next."""
    batcher = _ball_batcher(device, size=8, views=3)
    n = batcher.n_rays
    epochs = [batcher._perm]
    batcher.next_batch(n)  # exactly the first epoch
    batcher.next_batch(10)  # into the second
    epochs.append(batcher._perm)
    for perm in epochs:
        assert perm.device.type == device.type
        assert torch.equal(torch.sort(perm).values, torch.arange(n, device=device))  # every ray once
    assert not torch.equal(epochs[0], epochs[1])
    state = batcher.state_dict()
    want = [batcher.next_batch(37) for _ in range(3)]
    other = _ball_batcher(device, size=8, views=3)
    other.load_state_dict(state)
    for w in want:
        got = other.next_batch(37)
        for key in w:
            torch.testing.assert_close(got[key], w[key], rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA: compares a CUDA training step with the CPU's")
def test_a_cuda_training_step_agrees_with_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    """One step from the same weights on the same rays: the same loss and the same grid update, to float tolerance.
    The CPU's and CUDA's generators draw different numbers from one seed, so the marcher's jitter and the batcher's
    shuffle are drawn on the CPU for both (else the two steps sample other rays, at other depths)."""
    rand, randperm = torch.rand, torch.randperm

    def drawn_on_the_cpu(*size: int, device: torch.device | str | None = None, **kwargs: object) -> torch.Tensor:
        if kwargs.get("generator") is not None:
            return rand(*size, device=device, **kwargs)
        return rand(*size, **kwargs).to(device)

    def shuffled_on_the_cpu(n: int, generator: torch.Generator | None = None, device: object = None) -> torch.Tensor:
        return randperm(n, generator=torch.Generator().manual_seed(0)).to(device)

    monkeypatch.setattr(torch, "rand", drawn_on_the_cpu)
    monkeypatch.setattr(torch, "randperm", shuffled_on_the_cpu)
    results = {}
    for name in ("cpu", "cuda"):
        dev = torch.device(name)
        torch.manual_seed(0)
        model = FastModel(FastConfig(aabb=((-1.0,) * 3, (1.0,) * 3), **TINY)).to(dev)
        out = train(model, _ball_batcher(dev), steps=1, lr=1e-2, batch_rays=256)
        results[name] = (out["loss"], model.color_grid.table.detach().cpu())
    assert results["cuda"][0] == pytest.approx(results["cpu"][0], rel=1e-3)
    torch.testing.assert_close(results["cuda"][1], results["cpu"][1], rtol=1e-3, atol=1e-5)


# ----------------------------------------------------------------------------- compiled colour network
def test_compile_is_on_for_cuda_only_unless_asked() -> None:
    assert not compile_wanted("auto", torch.device("cpu"))[0]
    assert compile_wanted("auto", torch.device("cuda"))[0]
    assert compile_wanted("on", torch.device("cpu"))[0] and not compile_wanted("off", torch.device("cuda"))[0]
    model = FastModel(FastConfig(**TINY))
    assert "off on cpu" in compile_color_network(model, torch.device("cpu"), "auto")
    assert "forward" not in vars(model.color_mlp)


def test_compiled_color_network_matches_its_eager_reference_and_keeps_the_weights() -> None:
    """aot_eager traces the graph inductor would build kernels from, without building them (fast on a CPU)."""
    torch.manual_seed(0)
    model = FastModel(FastConfig(**TINY))
    keys = list(model.state_dict())
    f = torch.rand(33, model.color_mlp[0].in_features)
    eager = model.color_mlp(f)
    graphs = []

    def counting(graph: torch.fx.GraphModule, example_inputs: list) -> Callable[..., list]:
        graphs.append(graph)
        return torch._dynamo.backends.debugging.aot_eager(graph, example_inputs)

    why = compile_color_network(model, torch.device("cpu"), "on", backend=counting)
    # both graphs are built before training: without gradients (renders) and with them (a training step), so a
    # time-budgeted training spends none of its budget compiling
    assert "eager network is its reference" in why and len(graphs) == 2
    features = f.clone().requires_grad_()  # a training step's features come from grids that need gradients
    torch.testing.assert_close(model.color_mlp(features), eager)
    torch.testing.assert_close(model.color_mlp(features[:5]), eager[:5])
    with torch.no_grad():
        torch.testing.assert_close(model.color_mlp(f[:9]), eager[:9])
    assert len(graphs) == 2  # whatever the sample count, nothing is compiled again
    assert list(model.state_dict()) == keys


def test_a_compiled_network_that_disagrees_with_its_reference_is_dropped() -> None:
    def miscompiled(graph: torch.fx.GraphModule, example_inputs: list) -> Callable[..., list]:
        return lambda *args: [out + 0.1 for out in graph(*args)]

    model = FastModel(FastConfig(**TINY))
    why = compile_color_network(model, torch.device("cpu"), "on", backend=miscompiled)
    assert why.startswith("torch.compile: failed (AssertionError") and "stays eager" in why
    assert "forward" not in vars(model.color_mlp)


def test_render_chunks_grow_with_a_cuda_cards_memory_only(device: torch.device) -> None:
    from recon.nerf.classic import ClassicModel
    from recon.nerf.evaluate import CUDA_CHUNK_GIB, default_render_chunk

    fast = FastModel(FastConfig(**TINY))
    chunk = default_render_chunk(fast, device)
    if device.type == "cpu":
        assert chunk == FastModel.render_chunk
    else:
        gib = torch.cuda.get_device_properties(device).total_memory / 2**30
        assert chunk == FastModel.render_chunk * max(1, min(16, int(gib // CUDA_CHUNK_GIB)))
    assert default_render_chunk(ClassicModel(), device) == 8192  # models without packed samples keep the default


def test_the_color_network_runs_in_slices_on_a_cpu_and_in_one_call_on_a_gpu() -> None:
    from recon.nerf.fast import MLP_SLICE, in_slices

    calls = []

    def row_wise(f: torch.Tensor, d: torch.Tensor) -> torch.Tensor:
        calls.append(f.shape[0])
        return f * 2 + d

    f, d = torch.randn(2 * MLP_SLICE + 5, 3), torch.randn(2 * MLP_SLICE + 5, 3)
    torch.testing.assert_close(in_slices(row_wise, f, d), f * 2 + d)
    assert calls == [MLP_SLICE, MLP_SLICE, 5]  # a CPU's cache takes a slice at a time
    calls.clear()
    meta = torch.empty(2 * MLP_SLICE + 5, 3, device="meta")  # a device that is not the CPU, without one
    assert in_slices(row_wise, meta, meta).shape == meta.shape and calls == [2 * MLP_SLICE + 5]


def test_the_color_networks_slices_join_their_gradients_in_one_node() -> None:
    """Recording, the slices are one split of the features: its backward joins the slices' gradients once, where a
    view a slice would fill a zeroed gradient of all the features for each and add them up; the same gradient as one
    call's."""
    from recon.nerf.fast import MLP_SLICE, color_from_features, in_slices, make_color_mlp

    torch.manual_seed(0)
    mlp = make_color_mlp(12, "mlp_view", 2, 16, 1)
    f = torch.randn(3 * MLP_SLICE + 7, 12, requires_grad=True)
    d = torch.nn.functional.normalize(torch.randn(f.shape[0], 3), dim=-1)
    net = lambda a, b: color_from_features(a, b, mlp, "mlp_view", 2)  # noqa: E731
    out = in_slices(net, f, d)
    nodes, todo = set(), [out.grad_fn]
    while todo:
        node = todo.pop()
        if node is not None and node not in nodes:
            nodes.add(node)
            todo += [n for n, _ in node.next_functions]
    names = [type(n).__name__ for n in nodes]
    assert names.count("SplitBackward0") == 1 and "SliceBackward0" not in names
    (g_sliced,) = torch.autograd.grad(out.square().sum(), f)
    (g_whole,) = torch.autograd.grad(net(f, d).square().sum(), f)
    torch.testing.assert_close(g_sliced, g_whole)


# ----------------------------------------------------------------------------- Triton kernels: the switch
# (the kernels against their torch references: tests/test_triton_kernels.py)
def test_kernels_auto_stays_on_torch_until_measured_and_a_cpu_never_uses_triton() -> None:
    from recon.nerf import kernels

    use, why = kernels.kernels_choice("auto", "cuda")
    assert use is (kernels.MEASURED_FASTER and kernels.triton_status()[0])
    if not kernels.MEASURED_FASTER:
        assert why.startswith("kernels: torch") and "until a GPU check measures the Triton kernels faster" in why
    assert kernels.kernels_choice("torch", "cuda") == (False, "kernels: torch (train.fast.kernels=torch)")
    assert not kernels.kernels_choice("triton", "cpu")[0] and "CUDA only" in kernels.kernels_choice("triton", "cpu")[1]
    cpu = torch.zeros(3)
    assert not any(kernels.use_triton(s, cpu) for s in ("auto", "torch", "triton"))
    model = FastModel(FastConfig(**TINY, kernels="triton"))
    assert {g.kernels for g in model.modules() if isinstance(g, (DenseGrid, MultiDenseGrid))} == {"triton"}


# ----------------------------------------------------------------------------- GPU sizing of presets
@pytest.mark.parametrize("preset", ["fast", "balanced", "quality", "surface"])
def test_a_large_gpu_gets_more_rays_finer_grids_and_a_higher_step_cap(preset: str) -> None:
    base = load_config(preset, ["train.device=cpu"])
    sized, why = device_sizing(base, 80 * GiB, "Test GPU")
    _, rays_x, grid_x, steps_x = GPU_TIERS[0]
    assert sized.train.batch_rays == rays_x * base.train.batch_rays
    assert sized.train.steps == steps_x * base.train.steps and sized.train.budget == base.train.budget
    res = ("fast", "density_res") if preset != "surface" else ("surface", "sdf_res")
    before, after = getattr(getattr(base.train, res[0]), res[1]), getattr(getattr(sized.train, res[0]), res[1])
    assert after % 16 == 0 and abs(after - grid_x * before) <= 8
    assert why.startswith("GPU sizing (Test GPU, 80 GiB") and f"train.batch_rays={base.train.batch_rays}→" in why
    assert base == load_config(preset, ["train.device=cpu"])  # the preset itself is untouched


def test_sizing_grows_with_memory_and_leaves_small_gpus_classic_and_set_values_alone() -> None:
    base = load_config("fast", ["train.device=cpu"])
    rays = [device_sizing(base, gib * GiB, "g")[0].train.batch_rays for gib in (4, 8, 24, 80)]
    assert rays == [4096, 8192, 16384, 32768]
    assert device_sizing(base, 4 * GiB, "small") == (base, "")
    classic = load_config("classic", ["train.device=cuda"])
    assert device_sizing(classic, 80 * GiB, "g") == (classic, "")
    kept, why = device_sizing(base, 80 * GiB, "g", keep=frozenset({"train.batch_rays", "train.fast.density_res"}))
    assert kept.train.batch_rays == 4096 and kept.train.fast.density_res == 160 and kept.train.fast.feature_res > 128
    assert "train.batch_rays" not in why
    budgetless = load_config("fast", ["train.device=cpu", "train.budget="])
    assert device_sizing(budgetless, 80 * GiB, "g")[0].train.steps == budgetless.train.steps  # a cap only with a budget


def test_grids_stay_the_presets_when_the_card_could_not_hold_them() -> None:
    huge = load_config("fast", ["train.device=cpu", "train.fast.density_res=512"])  # 2.5 GiB to train; 640³: 4.9
    sized, why = device_sizing(huge, 16 * GiB, "g")
    assert dataclasses.replace(sized.train.fast, sh_degree=huge.train.fast.sh_degree) == huge.train.fast
    assert sized.train.batch_rays == 4 * 4096 and "density_res" not in why and "hash" not in why


def test_a_card_takes_the_view_dependent_colour_a_degree_further_and_says_why() -> None:
    base = load_config("fast", ["train.device=cpu"])
    assert base.train.fast.color_model == "mlp_view" and base.train.fast.sh_degree < GPU_SH_DEGREE  # the CPU's
    for memory in (80 * GiB, 8 * GiB):  # finer grids or the preset's: the colour network's input costs a card little
        sized, why = device_sizing(base, memory, "g")
        assert sized.train.fast.sh_degree == GPU_SH_DEGREE and base.train.fast.sh_degree == 2  # the caller's is kept
        assert f"train.fast.sh_degree=2→{GPU_SH_DEGREE}" in why and "glossy" in why
    assert device_sizing(base, 4 * GiB, "g")[0].train.fast.sh_degree == 2  # below every tier: not sized
    kept = device_sizing(base, 80 * GiB, "g", keep=frozenset({"train.fast.sh_degree"}))[0]
    assert kept.train.fast.sh_degree == 2
    plain = load_config("fast", ["train.device=cpu", "train.fast.color_model=mlp"])  # no view dependence to widen
    assert "sh_degree" not in device_sizing(plain, 80 * GiB, "g")[1]
    surface = load_config("surface", ["train.device=cpu"])
    assert "sh_degree" not in device_sizing(surface, 80 * GiB, "g")[1]


def test_finer_grids_take_the_colour_features_into_a_hash_grid_and_say_why() -> None:
    base = load_config("fast", ["train.device=cpu"])
    assert base.train.fast.grid == "dense" and base.train.fast.feature_levels == 1  # the CPU's
    sized, why = device_sizing(base, 80 * GiB, "g")
    fast = sized.train.fast
    assert {key: getattr(fast, key) for key in GPU_HASH_FEATURES} == GPU_HASH_FEATURES and fast.feature_levels == 1
    assert base.train.fast.grid == "dense"  # the caller's config is kept
    assert "train.fast.grid=dense→hash" in why and "hash grid" in why and why.count("train.fast.feature_res=") == 1
    assert fast.density_res > base.train.fast.density_res  # the density stays a dense grid, finer
    same_grids, why = device_sizing(base, 8 * GiB, "g")  # more rays, the preset's grids: dense, as on a CPU
    assert same_grids.train.fast.grid == "dense" and "hash" not in why
    surface = load_config("surface", ["train.device=cpu"])
    assert "hash" not in device_sizing(surface, 80 * GiB, "g")[1]


def test_a_dense_feature_grid_kept_on_a_card_gets_a_coarser_level_under_it() -> None:
    base = load_config("fast", ["train.device=cpu"])
    assert base.train.fast.feature_levels == 1 < GPU_FEATURE_LEVELS  # the CPU's: one level
    for key in sorted(GPU_HASH_KEYS - {"train.fast.feature_levels"}):  # any of them set: the preset's dense grid
        sized, why = device_sizing(base, 80 * GiB, "g", keep=frozenset({key}))
        assert sized.train.fast.grid == "dense" and sized.train.fast.feature_levels == GPU_FEATURE_LEVELS, key
        assert f"train.fast.feature_levels=1→{GPU_FEATURE_LEVELS}" in why and "coarser" in why
    kept = device_sizing(base, 80 * GiB, "g", keep=frozenset({"train.fast.feature_levels"}))[0]
    assert kept.train.fast.grid == "dense" and kept.train.fast.feature_levels == 1
    assert kept.train.fast.feature_res > base.train.fast.feature_res
    vm = load_config("fast", ["train.device=cpu", "train.fast.grid=vm"])  # levels and hashing are a dense grid's
    assert device_sizing(vm, 80 * GiB, "g")[0].train.fast.feature_levels == 1
    huge = load_config("fast", ["train.device=cpu", "train.fast.density_res=512"])  # the grids stay: so do the features
    sized, why = device_sizing(huge, 16 * GiB, "g", keep=frozenset({"train.fast.grid"}))
    assert sized.train.fast.grid == "dense" and sized.train.fast.feature_levels == 1 and "feature_levels" not in why


def test_finer_grids_start_the_distortion_loss_later_and_say_why() -> None:
    base = load_config("fast", ["train.device=cpu"])
    assert base.train.fast.distortion_weight > 0 and base.train.fast.distortion_from == 0  # the CPU's: first step
    sized, why = device_sizing(base, 80 * GiB, "g")
    assert sized.train.fast.distortion_from == GPU_DISTORTION_FROM
    assert f"train.fast.distortion_from=0→{GPU_DISTORTION_FROM:g}" in why and "distortion loss" in why
    same_grids = device_sizing(base, 8 * GiB, "g")[0]  # more rays, the preset's grids: the loss as on a CPU
    assert same_grids.train.batch_rays > base.train.batch_rays and same_grids.train.fast.distortion_from == 0
    kept = device_sizing(base, 80 * GiB, "g", keep=frozenset({"train.fast.distortion_from"}))[0]
    assert kept.train.fast.distortion_from == 0
    no_loss = load_config("fast", ["train.device=cpu", "train.fast.distortion_weight=0"])
    assert device_sizing(no_loss, 80 * GiB, "g")[0].train.fast.distortion_from == 0
    huge = load_config("fast", ["train.device=cpu", "train.fast.density_res=512"])  # the grids stay: so does the loss
    assert device_sizing(huge, 16 * GiB, "g")[0].train.fast.distortion_from == 0
    early_stop = load_config("fast", ["train.device=cpu", "train.fast.distortion_until=0.05"])  # a later start: none
    assert device_sizing(early_stop, 80 * GiB, "g")[0].train.fast.distortion_from == 0


def test_load_config_sizes_presets_on_cuda_and_set_wins(monkeypatch: pytest.MonkeyPatch) -> None:
    import recon.nerf.device as device_module

    monkeypatch.setattr(device_module, "cuda_memory", lambda pref: (80 * GiB, "Fake H100"))
    sized = load_config("fast", ["train.device=cuda"])
    assert sized.train.batch_rays == 32768 and sized.train.adjusted.startswith("GPU sizing (Fake H100")
    user = load_config("fast", ["train.device=cuda", "train.batch_rays=8192"])
    assert user.train.batch_rays == 8192 and user.train.steps == sized.train.steps
    assert load_config("fast", ["train.device=cuda", "train.device_sizing=off"]).train.batch_rays == 4096
    cpu = load_config("fast", ["train.device=cpu"])
    assert cpu.train.batch_rays == 4096 and cpu.train.adjusted == ""


def test_cuda_memory_is_none_for_the_cpu() -> None:
    from recon.nerf.device import cuda_memory

    assert cuda_memory("cpu") is None
    if not torch.cuda.is_available():
        assert cuda_memory("auto") is None and cuda_memory("cuda:0") is None
    else:
        memory, name = cuda_memory("cuda")
        assert memory > 0 and name
