"""The native marcher and feature gather (recon/nerf/march.c) against the torch paths they replace, and the
fallback to torch when the library cannot be built."""
from __future__ import annotations

import pytest
import torch

import recon.nerf.native as native
from recon.nerf.fast import FastConfig, FastModel
from recon.nerf.grid import DenseGrid
from recon.nerf.occupancy import march_front_to_back
from recon.nerf.rays import camera_rays, clip_to_box, ray_aabb, ray_aabb_torch
from tests.odd_rays import BOX, odd_rays, stacked_batcher

needs_native = pytest.mark.skipif(native.native_marcher() is None, reason=f"native marcher {native.native_status()}")


def _ball_model(levels: int, activation: str, occupancy_res: int = 24) -> FastModel:
    """A fast model holding a noisy opaque ball (radius ~0.6) on ``levels`` density grids; occupancy refreshed
    (24³ cells: rays jump over empty blocks of 8³; 20³ has no blocks)."""
    torch.manual_seed(0)
    cfg = FastConfig(aabb=((-1.0, -1.2, -0.8), (1.1, 1.0, 1.0)), density_res=40, feature_res=24, density_levels=levels,
                     occupancy_res=occupancy_res, density_activation=activation)
    model = FastModel(cfg)
    with torch.no_grad():
        grids = model.density_grid.grids if levels > 1 else [model.density_grid]
        for i, grid in enumerate(grids):
            r = grid.res
            lin = torch.linspace(-1.0, 1.0, r)
            x, y, z = torch.meshgrid(lin, lin, lin, indexing="ij")
            raw = (40.0 if i == 0 else 4.0) * (0.6 - (x**2 + y**2 + z**2).sqrt()) + 0.5 * torch.randn_like(x)
            grid.table.copy_(raw.reshape(-1, 1) / len(grids))
        model.color_grid.table.normal_()
    model.occupancy.warmup_steps = 0
    model.occupancy.update(model.density, 100)
    return model.eval()


def _rays(model: FastModel, n_side: int = 40) -> tuple[torch.Tensor, ...]:
    c2w = torch.eye(4)
    c2w[:3, 3] = torch.tensor([0.3, -0.2, 3.0])
    o, d = camera_rays(c2w, 45.0, 45.0, n_side / 2, n_side / 2, n_side, n_side)
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    tn, tf, hit = ray_aabb(o, d, model.aabb)
    return o, d, tn.clamp_min(0.5), torch.where(hit, tf, tn)


@needs_native
@pytest.mark.parametrize("levels,activation,jitter,cells", [(3, "softplus", False, 24), (1, "trunc_exp", False, 24),
                                                         (3, "softplus", True, 24), (3, "softplus", True, 20)])
def test_native_march_keeps_the_torch_marchers_samples(levels: int, activation: str, jitter: bool, cells: int) -> None:
    model = _ball_model(levels, activation, cells)
    blocks = native._empty_blocks(model.occupancy.occupied)
    assert (blocks is None) == (cells % native.BLOCK != 0)
    if blocks is not None:
        assert 0 < int(blocks.sum()) < blocks.numel()  # some blocks are empty: rays jump over them
    o, d, tn, tf = _rays(model)

    def sigma_fn(ts: torch.Tensor, te: torch.Tensor, ri: torch.Tensor) -> torch.Tensor:
        return model._sigma_unit(model._unit(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).clamp(0.0, 1.0))

    torch.manual_seed(3)
    ref = march_front_to_back(o, d, tn, tf, model.occupancy, model.step_size, 1024, sigma_fn, jitter=jitter,
                              min_transmittance=1e-3)
    torch.manual_seed(3)
    with torch.no_grad():
        got = native.march_dense_native(o, d, tn, tf, jitter, model._dense_density(), model.step_size, 1024, 1e-3)
    assert got is not None
    assert ref[2].numel() > 10 * o.shape[0] // 4  # the ball is hit: many samples, early termination matters
    assert torch.equal(got[2], ref[2])  # the same samples of the same rays, in the same order
    for a, b in zip(got[:2], ref[:2]):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(got[3], ref[3], atol=1e-3, rtol=1e-4)


@needs_native
@pytest.mark.parametrize("levels,activation", [(3, "softplus"), (1, "trunc_exp"), (3, "trunc_exp")])
def test_a_training_step_on_the_marchs_densities_equals_one_that_reads_them_again(
        levels: int, activation: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The march's densities and points stand for the loss's (FastModel._marched_sigma): the same rendering and the
    same gradients in every level and the colour grid as reading the levels again (FastModel._sigma_unit), including
    where trunc_exp is clamped and its gradient is 0."""
    model = _ball_model(levels, activation).train()
    o, d, tn, tf = _rays(model, 32)
    if activation == "trunc_exp":  # past exp's clamp (raw 15) just inside the ball's surface
        with torch.no_grad():
            table = model._density_levels()[0].table
            table.add_(25.0 * (table > 0))
            sigma = native.march_dense_native(o, d, tn, tf, False, model._dense_density(), model.step_size, 1024, 1e-3)[3]
        assert 0 < int((model._activation_slope(sigma) == 0).sum()) < sigma.numel()
    weights = torch.rand(o.shape[0], 3, generator=torch.Generator().manual_seed(2))
    runs = []
    for reads_again in (False, True):
        if reads_again:
            monkeypatch.setattr(FastModel, "_marched_sigma", lambda self, sigma, u: None)
        model.zero_grad(set_to_none=True)
        torch.manual_seed(4)
        out = model.render_rays(o, d, tn, tf, training=True, background=torch.ones(3))
        ((out["rgb"] * weights).sum() + out["depth"].sum()).backward()
        tables = [g.table for g in model._density_levels()] + [model.color_grid.table]
        runs.append((out, [t.grad.clone() for t in tables]))
    (marched, marched_grads), (again, again_grads) = runs
    assert marched["num_samples"] == again["num_samples"] > o.shape[0] // 4
    assert marched["density_evals"] == marched["num_samples"] < again["density_evals"]
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(marched[key], again[key], atol=1e-4, rtol=1e-4)
    assert all(float(g.abs().sum()) > 0 for g in marched_grads)
    for a, b in zip(marched_grads, again_grads):
        torch.testing.assert_close(a, b, atol=1e-4 * float(b.abs().max()), rtol=1e-3)


@needs_native
def test_the_march_hands_back_its_points_in_the_grids_unit_cube() -> None:
    model = _ball_model(3, "softplus")
    o, d, tn, tf = _rays(model)
    torch.manual_seed(3)
    with torch.no_grad():
        ts, te, ri, _, u = native.march_dense_native(o, d, tn, tf, True, model._dense_density(), model.step_size, 1024,
                                                     1e-3, points=True)
    assert ri.numel() > o.shape[0]
    torch.testing.assert_close(u, model._unit(o[ri] + d[ri] * (0.5 * (ts + te))[:, None]).clamp(0.0, 1.0),
                               atol=1e-6, rtol=0.0)


@needs_native
def test_native_render_equals_the_torch_render() -> None:
    model = _ball_model(3, "softplus")
    o, d, tn, tf = _rays(model, 48)
    with torch.inference_mode():
        fast = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
    from recon.app.profiling import reference_marching

    with torch.inference_mode(), reference_marching():
        ref = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
    assert float(ref["opacity"].max()) > 0.99
    for key in ("rgb", "depth", "opacity"):
        torch.testing.assert_close(fast[key], ref[key], atol=1e-4, rtol=1e-4)
    assert fast["num_samples"] == ref["num_samples"]


@needs_native
def test_native_features_equal_the_gather_at_cells_faces_and_corners() -> None:
    torch.manual_seed(1)
    grid = DenseGrid(7, 12, init_std=1.0)
    x = torch.cat([torch.rand(5000, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.0], [1 / 6, 2 / 6, 1.0]]),
                   torch.rand(50, 3) * 1.4 - 0.2])  # beyond the cube too: clamped like the torch path
    with torch.enable_grad():
        ref = grid(x)  # with gradients: the torch gather
    with torch.no_grad():
        got = grid(x)
        direct = native.trilinear_features_native(x, grid.table, grid.res)
    assert direct is not None
    torch.testing.assert_close(got, ref.detach(), atol=1e-5, rtol=1e-5)
    assert torch.equal(got, direct)


@needs_native
@pytest.mark.parametrize("channels", [1, 12])
def test_the_c_backward_in_parts_adds_the_same_sums_as_in_one(channels: int) -> None:
    """Each part of the dense backward adds into x-planes of its own: split over any number of parts (threads) the
    gradient and the flagged blocks are the one part's bit for bit, and both the torch gather's gradient."""
    from recon.nerf.grid import trilinear_torch

    torch.manual_seed(2)
    res, n = 9, 5000
    x = torch.cat([torch.rand(n - 2, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])])
    g = torch.randn(n, channels)
    lib = native.native_marcher()
    results = []
    for parts in (1, 2, 3):
        grad, flags = torch.zeros(res**3, channels), torch.zeros(native.adam_blocks(res**3 * channels), dtype=torch.uint8)
        for part in range(parts):
            lib.recon_trilinear_backward(n, x.data_ptr(), g.data_ptr(), res, channels, grad.data_ptr(),
                                         flags.data_ptr(), part, parts)
        results.append((grad, flags))
    for grad, flags in results[1:]:
        assert torch.equal(grad, results[0][0]) and torch.equal(flags, results[0][1])
    table = torch.zeros(res**3, channels, requires_grad=True)
    (trilinear_torch(x, table, res) * g).sum().backward()
    torch.testing.assert_close(results[0][0], table.grad, atol=1e-4, rtol=1e-5)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)  # the wrapper splits n = 5000 points over two threads
        assert torch.equal(native.trilinear_backward_native(x, g, res), results[0][0])
    finally:
        torch.set_num_threads(threads)


@needs_native
@pytest.mark.parametrize("room", ["steps", "short"])
def test_the_openmp_parts_compute_what_recons_own_threads_do(room: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A library built with OpenMP runs each call's parts on OpenMP's threads in one call (the `_all` entry points);
    without, recon splits them over threads of its own. Both give the same results bit for bit, with each ray's
    steps as its room, and with room short of that (16 samples a ray), so slices are marched again."""
    from recon.nerf.grid import HashGrid
    from recon.nerf.masked_adam import adam_blocks

    if not native._parallel_in_c(native.native_marcher()):
        pytest.skip("march.c was built without OpenMP here")
    model = _ball_model(3, "softplus")
    with torch.no_grad():  # a faint field: rays march through it, far beyond 48 samples
        for level in model._density_levels():
            level.table.mul_(0.02)
    model.occupancy.update(model.density, 100)
    o, d, tn, tf = _rays(model, 48)
    field, step = model._dense_density(), model.step_size / 6
    torch.manual_seed(0)
    x, hash_grid = torch.rand(6000, 3), HashGrid(levels=4, features=2, log2_table=12, base_res=4, max_res=64)
    g_dense, g_hash = torch.randn(6000, 12), torch.randn(6000, 8)
    n = 200_000
    param, grad = torch.randn(n), torch.randn(n)

    def every_call() -> list[torch.Tensor]:
        torch.manual_seed(3)
        marched = native.march_dense_native(o, d, tn, tf, True, field, step, 1024, 1e-3, points=True)
        rendered = native.march_render_native(o, d, tn, tf, field, step, 1024, 1e-3, 0.0)
        dense_grad, hash_grad = torch.zeros_like(model.color_grid.table), torch.zeros_like(hash_grid.table)
        model.color_grid._native_add_grad(x, g_dense, dense_grad, None)
        hash_grid._native_add_grad(x, g_hash, hash_grad, None)
        adam = [param.clone(), grad.clone(), torch.zeros(n), torch.zeros(n)]
        flags = (torch.arange(adam_blocks(n)) % 3 == 0).to(torch.uint8)
        assert native.adam_native(*adam, beta1=0.9, beta2=0.999, step_size=0.01, bias2_sqrt=0.5, eps=1e-8, masked=True,
                                  clear=True, touched=flags)
        return [*marched, *rendered.values(), model.color_grid._native_read(x), hash_grid._native_read(x), dense_grad,
                hash_grad, *adam, flags]

    threads = torch.get_num_threads()
    if room == "short":
        monkeypatch.setattr(native, "MARCH_ROOM", 1)
    try:
        torch.set_num_threads(2)
        in_c = every_call()
        monkeypatch.setattr(native, "_parallel_in_c", lambda lib: False)
        ours = every_call()
    finally:
        torch.set_num_threads(threads)
    assert int(torch.bincount(in_c[2]).max()) > 48 and int(torch.bincount(in_c[7]).max()) > 24  # beyond 16 a ray
    assert len(in_c) == len(ours)
    for a, b in zip(in_c, ours):
        assert torch.equal(a, b)


@needs_native
@pytest.mark.parametrize("rays", [48, 300])
def test_a_march_gives_each_ray_its_steps_and_marches_no_slice_twice(rays: int, monkeypatch: pytest.MonkeyPatch
                                                                      ) -> None:
    """Each ray is given room for its steps (the most samples it can keep): rays through a faint field, far beyond
    the 48 samples a ray the march once guessed, and a depth prior's few hundred rays, are each marched once, on both
    threads, and keep the torch marcher's samples."""
    model = _ball_model(3, "softplus")
    with torch.no_grad():
        for level in model._density_levels():
            level.table.mul_(0.02)
    model.occupancy.update(model.density, 100)
    o, d, tn, tf = _rays(model, 48)
    pick = torch.randperm(o.shape[0], generator=torch.Generator().manual_seed(1))[:rays]
    o, d, tn, tf = o[pick], d[pick], tn[pick], tf[pick]
    field, step = model._dense_density(), model.step_size / 6
    lib, calls = native.native_marcher(), []
    for name in ("recon_march_dense", "recon_march_render", "recon_march_dense_all", "recon_march_render_all"):
        spy = (lambda f, name: lambda *a: calls.append(name) or f(*a))(getattr(lib, name), name)
        monkeypatch.setattr(lib, name, spy)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        ts, te, ri, sigma = native.march_dense_native(o, d, tn, tf, False, field, step, 1024, 1e-3)
        rendered = native.march_render_native(o, d, tn, tf, field, step, 1024, 1e-3, 0.0)
        both = native._threads_for(rays, native.MARCH_RAYS_A_THREAD) == 2
    finally:
        torch.set_num_threads(threads)
    assert both == (rays >= 256)  # a depth prior's 256 rays take both threads
    assert int(torch.bincount(ri).max()) > 48 and int(torch.bincount(rendered["ray_indices"]).max()) > 48
    if native._parallel_in_c(lib):
        assert calls == ["recon_march_dense_all", "recon_march_render_all"]
    else:  # recon's own threads: one call a slice
        slices = native._in_slices(rays, lambda lo, hi: lo, native.MARCH_RAYS_A_THREAD)
        assert calls == ["recon_march_dense"] * len(slices) + ["recon_march_render"] * len(slices)
    sigma_fn = lambda a, b, r: model._sigma_unit(model._unit(o[r] + d[r] * (0.5 * (a + b))[:, None]).clamp(0, 1))
    ref = march_front_to_back(o, d, tn, tf, model.occupancy, step, 1024, sigma_fn, jitter=False, min_transmittance=1e-3)
    assert torch.equal(ri, ref[2])
    torch.testing.assert_close(ts, ref[0])


@needs_native
def test_a_marchs_room_holds_infinite_and_nan_distances() -> None:
    """A ray's room is its steps, at most max_samples: an infinite far gets max_samples (not an integer cast of
    infinity), a NaN or an empty interval none, so the offsets never run backwards."""
    model = _ball_model(1, "softplus")
    o, d, tn, tf = _rays(model, 4)
    tf = tf.clone()
    tf[:4] = torch.tensor([float("inf"), float("nan"), 0.0, 1e30])
    steps = ((tf - tn) / 0.05).ceil().clamp(0, 64).nan_to_num(0.0).long()
    steps[:4] = torch.tensor([64, 0, 0, 64])
    offsets = native._march_room(tn, tf, 0.05, 64, False)(0, o.shape[0], 4)
    bounds = [o.shape[0] * s // 4 for s in range(5)]
    assert offsets.tolist() == [int(steps[:b].sum()) for b in bounds]
    ts, te, ri, sigma = native.march_dense_native(o, d, tn, tf, False, model._dense_density(), 0.05, 64, 1e-3)
    assert int(torch.bincount(ri, minlength=o.shape[0]).max()) <= 64 and not bool((ri == 1).any())


def test_a_failed_build_falls_back_to_torch(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # nothing built here yet
    monkeypatch.setenv("CC", "false")  # a "compiler" that fails
    native.native_marcher.cache_clear()
    try:
        assert native.native_marcher() is None
        assert native.native_status().startswith("torch: building recon/nerf/march.c failed")
        model = _ball_model(1, "softplus")
        o, d, tn, tf = _rays(model, 16)
        assert native.march_dense_native(o, d, tn, tf, False, model._dense_density(), 0.01, 64, 1e-3) is None
        with torch.no_grad():  # the model renders through the torch marcher
            out = model.render_rays(o, d, tn, tf, training=False, background=torch.ones(3))
        assert out["num_samples"] > 0
        monkeypatch.setenv("RECON_NATIVE", "0")
        native.native_marcher.cache_clear()
        assert native.native_marcher() is None and native.native_status() == "torch (RECON_NATIVE=0)"
    finally:
        native.native_marcher.cache_clear()


@needs_native
def test_a_compiler_without_host_flags_gets_the_portable_build(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    """The library is built for this CPU first (HOST_CFLAGS); a compiler that refuses that gets the portable flags,
    and a build for this CPU is cached under a key that names the CPU, so another kind of CPU builds its own."""
    import shutil

    cc = next(c for c in ("cc", "gcc", "clang") if shutil.which(c))
    picky = tmp_path / "picky-cc"
    picky.write_text(f'#!/bin/sh\nfor a in "$@"; do [ "$a" = "{native.HOST_CFLAGS[0]}" ] && exit 1; done\n'
                     f'exec {cc} "$@"\n')
    picky.chmod(0o755)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(picky))
    native.native_marcher.cache_clear()
    try:
        assert native.native_marcher() is not None
        status = native.native_status()
        assert "built portable, as the compiler refused -march=native" in status
        portable = [*native.CFLAGS, *native.OPENMP_CFLAGS] if "with OpenMP" in status else native.CFLAGS
        built = sorted(p.name for p in (tmp_path / "cache" / "recon" / "native").glob("march-*.so"))
        assert built == [native._target(native.SOURCE, portable).name]
    finally:
        native.native_marcher.cache_clear()
    host = [*native.CFLAGS, *native.HOST_CFLAGS]
    here = native._target(native.SOURCE, host)
    monkeypatch.setattr(native, "_cpu_signature", lambda: "model name: another CPU")
    assert native._target(native.SOURCE, host) != here
    assert native._target(native.SOURCE, portable).name in built  # the portable build is the same anywhere


@needs_native
@pytest.mark.parametrize("channels", [1, 5, 12])  # the C loop is built for 1 and 12, and for any
def test_native_grid_reads_train_as_the_torch_paths(channels: int) -> None:
    """Values and table gradients of the C reads equal torch's (grid_sample for one channel, the gather for more);
    points that need a gradient themselves (normals, pose refinement) keep the torch path."""
    from recon.nerf.grid import MultiDenseGrid

    torch.manual_seed(2)
    for grid in (DenseGrid(9, channels, init_std=1.0), MultiDenseGrid(17, channels, levels=3)):
        for level in grid.modules():
            if isinstance(level, DenseGrid):
                torch.nn.init.normal_(level.table)
        x = torch.cat([torch.rand(3000, 3), torch.tensor([[0.0, 1.0, 0.5], [1.0, 1.0, 1.0]])])
        upstream = torch.randn(x.shape[0], channels)
        native_out = grid(x)  # x needs no gradient: the C path
        (native_out * upstream).sum().backward()
        native_grads = [p.grad.clone() for p in grid.parameters()]
        grid.zero_grad()
        x_torch = x.clone().requires_grad_(True)  # a point gradient is wanted: the torch path
        torch_out = grid(x_torch)
        (torch_out * upstream).sum().backward()
        torch.testing.assert_close(native_out, torch_out, atol=1e-5, rtol=1e-5)
        for a, p in zip(native_grads, grid.parameters()):
            torch.testing.assert_close(a, p.grad, atol=1e-4, rtol=1e-4)
        assert x_torch.grad is not None and bool(x_torch.grad.abs().sum() > 0)
        grid.zero_grad()


@needs_native
@pytest.mark.parametrize("max_res, log2_table", [(24, 10), (64, 8)], ids=["some-levels-hashed", "most-hashed"])
def test_native_hash_reads_train_as_the_torch_read(max_res: int, log2_table: int) -> None:
    """A hash grid's C read (dense levels and hashed ones, tables small enough that vertices collide; points on the
    box's faces and corners and outside it) gives the torch read's features and table gradient (collisions sum)."""
    from recon.nerf.grid import HashGrid, hash_reference

    torch.manual_seed(5)
    grid = HashGrid(levels=6, features=2, log2_table=log2_table, base_res=4, max_res=max_res, init_scale=1.0)
    assert any(grid.hashed) and not all(grid.hashed)
    x = torch.cat([torch.rand(3000, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.0]]),
                   torch.rand(50, 3) * 1.4 - 0.2])
    upstream = torch.randn(x.shape[0], grid.out_dim)
    native_out = grid(x)  # x needs no gradient: the C path
    assert native_out.grad_fn is not None and "NativeRead" in type(native_out.grad_fn).__name__
    (native_out * upstream).sum().backward()
    native_grad = grid.table.grad.clone()
    grid.zero_grad()
    torch_out = grid.read_torch(x)
    (torch_out * upstream).sum().backward()
    torch.testing.assert_close(native_out, torch_out, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(native_grad, grid.table.grad, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(native_out[:40].detach(), hash_reference(grid, x[:40]), atol=1e-5, rtol=1e-5)
    x_torch = x.clone().requires_grad_(True)  # a point gradient is wanted: the torch path
    (grid(x_torch) * upstream).sum().backward()
    assert x_torch.grad is not None and bool(x_torch.grad.abs().sum() > 0)


@needs_native
@pytest.mark.parametrize("set_to_none", [True, False])
@pytest.mark.parametrize("kind", ["dense", "hash"])
def test_the_reused_gradient_buffer_never_doubles_a_gradient(set_to_none: bool, kind: str) -> None:
    from recon.nerf.grid import HashGrid

    torch.manual_seed(4)
    grid = DenseGrid(6, 12, init_std=1.0) if kind == "dense" else HashGrid(levels=3, log2_table=8, base_res=4,
                                                                            max_res=16, init_scale=1.0)
    x, upstream = torch.rand(500, 3), torch.randn(500, grid.out_dim)
    opt = torch.optim.SGD(grid.parameters(), lr=0.0)
    grads = []
    for _ in range(3):
        opt.zero_grad(set_to_none=set_to_none)
        (grid(x) * upstream).sum().backward()
        grads.append(grid.table.grad.clone())
    torch.testing.assert_close(grads[1], grads[0])
    torch.testing.assert_close(grads[2], grads[0])
    if set_to_none:  # the gradient of every step lands in the same memory
        assert grid.table.grad is grid._grad_buffer
    (grid(x) * upstream).sum().backward()  # no zero_grad: gradients accumulate, as autograd's do
    torch.testing.assert_close(grid.table.grad, 2 * grads[0])


def test_slices_are_each_computed_once_in_order_and_the_caller_takes_them_when_no_helper_starts(monkeypatch) -> None:
    """`_in_slices` hands each slice to one thread and returns the results in order; the calling thread takes slices
    too, so a helper the pool has not started yet is dropped, not waited for; an error in a slice goes up after the
    slices already begun have ended, and no slice starts after it."""
    import threading
    from concurrent.futures import Future

    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    seen: list[tuple[int, int]] = []
    lock = threading.Lock()

    def work(lo: int, hi: int) -> int:
        with lock:
            seen.append((lo, hi))
        return hi - lo

    assert sum(native._in_slices(100_000, work)) == 100_000 and len(seen) == 12
    assert sorted(seen) == [(100_000 * i // 12, 100_000 * (i + 1) // 12) for i in range(12)]  # each once, all of it
    assert native._in_slices(100_000, lambda lo, hi: lo) == [100_000 * i // 12 for i in range(12)]  # in order

    class NeverStarts:  # a pool whose threads are all busy elsewhere: what it is handed stays queued
        def __init__(self) -> None:
            self.handed: list[Future] = []

        def submit(self, fn, *args):
            self.handed.append(Future())
            return self.handed[-1]

    idle = NeverStarts()
    monkeypatch.setattr(native, "_thread_pool", lambda workers: idle)
    seen.clear()
    assert sum(native._in_slices(100_000, work)) == 100_000 and len(seen) == 12  # all on the caller, no wait
    assert len(idle.handed) == 2 and all(f.cancelled() for f in idle.handed)

    def fails_at_the_third(lo: int, hi: int) -> int:
        work(lo, hi)
        if len(seen) == 3:
            raise RuntimeError("slice failed")
        return 0

    seen.clear()
    with pytest.raises(RuntimeError, match="slice failed"):
        native._in_slices(100_000, fails_at_the_third)
    assert len(seen) == 3  # no slice after the error


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal values, NaN where NaN (torch.equal counts NaN unequal)."""
    return torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(0.0), b.nan_to_num(0.0))


@needs_native
def test_the_c_ray_box_is_the_torch_one_bit_for_bit() -> None:
    o, d, near, far = odd_rays()
    fast = native.ray_box_native(o, d, BOX)
    reference = ray_aabb_torch(o, d, BOX)
    assert fast is not None and int(reference[2].sum()) > 300  # enough rays meet the box to mean something
    for a, b in zip(fast, reference, strict=True):
        assert a.dtype == b.dtype and _same(a, b)
    assert all(_same(a, b) for a, b in zip(ray_aabb(o, d, BOX), reference, strict=True))  # ray_aabb takes the C pass
    t_near, t_far = clip_to_box(o, d, near, far, BOX)
    tn, tf, hit = reference
    clipped_near = torch.maximum(near, tn)
    assert _same(t_near, clipped_near)
    assert _same(t_far, torch.where(hit, torch.minimum(far, tf), clipped_near))
    # rays that need gradients (pose refinement) keep the torch operations, and their gradients
    o.requires_grad_(True)
    assert ray_aabb(o, d, BOX)[0].requires_grad


@needs_native
@pytest.mark.parametrize("box", [True, False])
def test_a_batch_of_rays_in_c_is_the_torch_batch(box: bool) -> None:
    batcher = stacked_batcher(box)
    flat = torch.arange(batcher.n_rays).flip(0)  # every pixel, each photo's first and last among them
    fast = native.pixel_rays_native(flat, batcher.offsets, batcher._widths, batcher.c2w, batcher.intrinsics,
                                    batcher.aabb, batcher.near_far)
    assert fast is not None
    o, d, near, far, hit, img = fast
    o_t, d_t, near_t, far_t, hit_t, img_t = batcher._rays_torch(flat)
    assert torch.equal(img, img_t) and torch.equal(o, o_t)
    assert img.unique().numel() == 5
    # the directions to a rounding: torch's matrix product and norm may sum in another order
    torch.testing.assert_close(d, d_t, rtol=0, atol=3e-7)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(flat.shape[0]), rtol=0, atol=3e-7)
    # where the rays meet the box, to those directions' rounding (a ray grazing an edge may flip: none here)
    assert torch.equal(hit, hit_t) and 0 < int(hit.sum()) < flat.shape[0] if box else bool(hit.any())
    torch.testing.assert_close(near, near_t, rtol=2e-6, atol=2e-6)
    torch.testing.assert_close(far, far_t, rtol=2e-6, atol=2e-6)
    assert torch.equal(batcher._rays(flat)[5], img_t)  # the batcher takes the C pass


def _packed_samples(seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Packed samples over rays of 0 to 130 samples, with opaque (1e12), zero-length and negative-density samples."""
    counts = [0, 1, 2, 5, 130, 0, 17, 64, 65, 3] * 20
    g = torch.Generator().manual_seed(seed)
    ri = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    m = ri.shape[0]
    sigma = torch.rand(m, generator=g) * 20 + 1e-3
    delta = torch.rand(m, generator=g) * 0.1 + 1e-3
    sigma[::37], delta[::41], sigma[::43] = 1e12, 0.0, -1.0
    return sigma, delta, 3.0 + torch.cumsum(delta, 0), ri, torch.tensor(len(counts))


def _with_gradients(fn, inputs: list[torch.Tensor], seed: int, keep: tuple[int, ...] = (0,)) -> list[torch.Tensor]:
    """fn's outputs numbered in ``keep`` and the gradients of a random weighting of them to each input."""
    leaves = [x.clone().requires_grad_(True) for x in inputs]
    outs = [fn(*leaves)[k] for k in keep]
    g = torch.Generator().manual_seed(seed)
    sum((o * torch.randn(o.shape, generator=g).to(o.dtype)).sum() for o in outs).backward()
    return [o.detach() for o in outs] + [x.grad for x in leaves]


@needs_native
def test_c_compositing_is_the_torch_compositing_forward_and_back() -> None:
    """To float32's rounding of the same sums (both keep the running optical depth in float64): weights, opacity,
    depth and the gradients (of all four, the transmittance's too) to sigma, delta and t; the transmittance bit for
    bit. (A float64 reference is no truth
    here: its clamps and exponentials cut elsewhere.)"""
    from recon.nerf.kernels import composite_packed_torch
    from recon.nerf.render import SIGMA_MAX, TAU_MAX

    sigma, delta, t, ri, n = _packed_samples()
    fast = _with_gradients(lambda s, d, tt: native.composite_packed_native(s, d, tt, ri, int(n)), [sigma, delta, t],
                           seed=1, keep=(0, 1, 2, 3))
    reference = _with_gradients(lambda s, d, tt: composite_packed_torch(s, d, tt, ri, int(n)), [sigma, delta, t],
                                seed=1, keep=(0, 1, 2, 3))
    names = ("weights", "transmittance", "opacity", "depth", "d/dsigma", "d/ddelta", "d/dt")
    for name, a, b in zip(names, fast, reference, strict=True):
        # a gradient is its sample's own term less the later samples' sum, which cancel in float32 (an opaque
        # sample's d/ddelta, ~5e7 here, to 1e-5): the gradients to 2e-5
        torch.testing.assert_close(a, b, rtol=2e-6 if name[0] != "d" else 2e-5, atol=1e-6 * float(b.abs().max()),
                                   msg=lambda m, name=name: f"{name}: {m}")
    transmittance = native.composite_packed_native(sigma, delta, t, ri, int(n))[1]
    assert torch.equal(transmittance, composite_packed_torch(sigma, delta, t, ri, int(n))[1])
    assert (fast[4][sigma < 0] == 0).all() and (fast[4][sigma > SIGMA_MAX] == 0).all()  # outside the clamps: none


@needs_native
def test_c_distortion_loss_is_the_reference_in_float64() -> None:
    """Its sums in float64, from each ray's first midpoint: closer to the float64 reference than the float32 one is."""
    from recon.nerf.render import distortion_packed

    _, delta, t, ri, n = _packed_samples(seed=2)
    w = torch.rand(delta.shape, generator=torch.Generator().manual_seed(5))
    fast = _with_gradients(lambda ww, mm, dd: [native.distortion_packed_native(ww, mm, dd, ri, int(n))],
                           [w, t, delta], seed=3)
    exact = _with_gradients(lambda ww, mm, dd: [distortion_packed(ww, mm, dd, ri, int(n))],
                            [x.double() for x in (w, t, delta)], seed=3)
    in_float32 = _with_gradients(lambda ww, mm, dd: [distortion_packed(ww, mm, dd, ri, int(n))], [w, t, delta], seed=3)
    for name, a, b, c in zip(("loss", "d/dw", "d/dmid", "d/ddelta"), fast, exact, in_float32, strict=True):
        scale = float(b.abs().max())
        assert float((a.double() - b).abs().max()) <= 2e-7 * scale, name
        assert float((a.double() - b).abs().max()) <= float((c.double() - b).abs().max()) + 1e-7 * scale, name


@needs_native
@pytest.mark.parametrize("held", [False, True])
@pytest.mark.parametrize("resolutions", [(24, 48, 97), (97, 24, 48)])
def test_the_density_levels_backward_a_level_a_thread_adds_what_one_at_a_time_does(
        held: bool, resolutions: tuple[int, ...], monkeypatch: pytest.MonkeyPatch) -> None:
    """The same sums and the same touched-block flags bit for bit, into fresh buffers or into gradients held, with
    the levels given coarsest first (a model's order, handed to the threads finest first) or mixed."""
    import recon.nerf.grid as grid_module
    from recon.nerf.grid import add_native_grads
    from recon.nerf.masked_adam import touched_blocks

    g = torch.Generator().manual_seed(4)
    x01, grad = torch.rand(20000, 3, generator=g), torch.randn(20000, 1, generator=g)
    runs, parallel_calls = [], []
    parallel = grid_module.trilinear_backward_levels_native
    for one_at_a_time in (False, True):
        torch.manual_seed(0)
        levels = [DenseGrid(r, 1, init_std=0.1) for r in resolutions]
        if held:
            for level in levels:
                level.table.grad = torch.randn(level.table.shape, generator=torch.Generator().manual_seed(level.res))
        with monkeypatch.context() as patch:
            if one_at_a_time:
                patch.setattr(grid_module, "trilinear_backward_levels_native", lambda *args: False)
            else:
                patch.setattr(grid_module, "trilinear_backward_levels_native",
                              lambda *args: parallel_calls.append(parallel(*args)) or parallel_calls[-1])
            add_native_grads(levels, x01, grad)
            add_native_grads(levels, x01[:5000], grad[:5000])  # a second step's add into the same gradients
        runs.append([(level.table.grad.clone(), touched_blocks(level.table).flags.clone()) for level in levels])
    for (a, flags_a), (b, flags_b) in zip(*runs, strict=True):
        assert torch.equal(a, b) and torch.equal(flags_a, flags_b)
    assert all(int(flags.sum()) > 0 for _, flags in runs[0]) or held  # fresh buffers are flagged where added into
    # with OpenMP the levels went in one parallel call; without, a level at a time both ways
    assert parallel_calls == [bool(native.native_marcher().openmp)] * 2


def test_the_levels_go_to_the_threads_finest_first() -> None:
    """The finest level, the most work, is handed out first; ties keep their order."""
    assert native._levels_order([24, 48, 97]) == [2, 1, 0]
    assert native._levels_order([97, 24, 48, 48]) == [0, 2, 3, 1]
