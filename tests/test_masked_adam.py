"""MaskedAdam (recon/nerf/masked_adam.py): torch's Adam where every value has a gradient, untouched values left alone
in a masked group; the C update (recon.nerf.native.adam_native) against the torch reference; the train stage's
choice of optimizer and a fast model trained with it; the blocks the grids' C backward flags (TouchedBlocks), which the
C update then visits alone."""
from __future__ import annotations

import math

import pytest
import torch

from recon.nerf.masked_adam import MaskedAdam, TouchedBlocks, adam_step_torch, touched_blocks
from recon.nerf.native import ADAM_BLOCK, adam_blocks, adam_native, native_marcher

needs_native = pytest.mark.skipif(native_marcher() is None, reason="the native library did not build here (no cc)")


def _problem(n: int, seed: int, zero_share: float) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    start = torch.randn(n, generator=g)
    grad = torch.randn(n, generator=g) * torch.logspace(-6, 2, n)[torch.randperm(n, generator=g)]
    grad[torch.rand(n, generator=g) < zero_share] = 0.0
    return start, grad


def _steps(optimizer: type, masked: bool, start: torch.Tensor, grads: list[torch.Tensor], **kw: object) -> list[torch.Tensor]:
    p = torch.nn.Parameter(start.clone())
    opt = optimizer([{"params": [p], "masked": masked}], lr=0.05, **kw)
    for grad in grads:
        p.grad = grad.clone()
        opt.step()
    state = opt.state[p]
    return [p.detach(), state["exp_avg"], state["exp_avg_sq"]]


def test_where_every_value_has_a_gradient_it_is_torchs_adam() -> None:
    start, _ = _problem(1000, 0, 0.0)
    grads = [_problem(1000, s, 0.0)[1] for s in range(1, 6)]
    for masked in (False, True):
        for got, want in zip(_steps(MaskedAdam, masked, start, grads), _steps(torch.optim.Adam, False, start, grads),
                             strict=True):
            torch.testing.assert_close(got, want, rtol=2e-6, atol=1e-7)


def test_a_masked_group_leaves_values_without_a_gradient_alone() -> None:
    start, _ = _problem(500, 0, 0.0)
    grads = [_problem(500, s, 0.5)[1] for s in range(1, 4)]
    grads[-1][:100] = 0.0  # the first 100 get no gradient in the last step: Adam would still move them (momentum)
    p, m, v = _steps(MaskedAdam, True, start, grads)
    before = _steps(MaskedAdam, True, start, grads[:-1])
    for now, earlier in zip((p, m, v), before, strict=True):
        assert torch.equal(now[:100], earlier[:100])
    never = (torch.stack(grads) == 0).all(0)
    assert never.any() and torch.equal(p[never], start[never]) and not m[never].any() and not v[never].any()
    adam = _steps(torch.optim.Adam, False, start, grads)[0]
    assert not torch.equal(adam[:100], before[0][:100])  # unmasked Adam moves them: the test tells the two apart
    unmasked = _steps(MaskedAdam, False, start, grads)
    torch.testing.assert_close(unmasked[0], adam, rtol=2e-6, atol=1e-7)


@needs_native
@pytest.mark.parametrize("masked", [True, False])
@pytest.mark.parametrize("n", [1, 63, 64, 65, 5000, 300_001])
def test_the_c_update_matches_the_torch_reference(masked: bool, n: int) -> None:
    """Sizes around the C code's 64-value blocks and a large one split over threads; gradients from 1e-6 to 1e2, a
    third exactly 0 (whole blocks of them too), moments already non-zero."""
    start, grad = _problem(n, 3, 1 / 3)
    grad[: min(n, 200)] = 0.0
    g = torch.Generator().manual_seed(9)
    m0, v0 = torch.randn(n, generator=g) * 0.1, torch.rand(n, generator=g) * 0.01
    kwargs = {"beta1": 0.9, "beta2": 0.999, "step_size": 0.05 / (1 - 0.9**7), "bias2_sqrt": math.sqrt(1 - 0.999**7),
              "eps": 1e-8, "masked": masked}
    native = [start.clone(), grad, m0.clone(), v0.clone()]
    reference = [start.clone(), grad, m0.clone(), v0.clone()]
    assert adam_native(*native, **kwargs)
    adam_step_torch(*reference, **kwargs)
    for name, a, b in zip(("param", "exp_avg", "exp_avg_sq"), native[::2] + native[3:], reference[::2] + reference[3:],
                          strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7, msg=lambda msg, name=name: f"{name}: {msg}")
    if masked:
        assert torch.equal(native[0][grad == 0], start[grad == 0])


@needs_native
@pytest.mark.parametrize("share", [0.5, 0.03])
@pytest.mark.parametrize("n", [1, 64, 65, 5000, 300_001])
def test_the_c_update_visits_the_flagged_blocks_alone(n: int, share: float) -> None:
    """With flags it updates the flagged blocks as the reference does (gradients 0 there too are left alone), clears
    those flags and gradients, and does not look at an unflagged block: one with a gradient stays as it was (the
    flags' promise broken on purpose, to see that they are what it reads). Sizes around the 64-value blocks, one
    split over threads; half the blocks flagged, and a few percent, as a step flags a fine grid (the C code reads the
    flags eight at a time, so runs of eight unflagged ones are skipped whole)."""
    start, grad = _problem(n, 4, 1 / 3)
    blocks = adam_blocks(n)
    flags = (torch.rand(blocks, generator=torch.Generator().manual_seed(5)) < share).to(torch.uint8)
    flags[0] = 1
    flagged = flags.repeat_interleave(ADAM_BLOCK)[:n].bool()
    kwargs = {"beta1": 0.9, "beta2": 0.999, "step_size": 0.05, "bias2_sqrt": 0.3, "eps": 1e-8, "masked": True}
    native = [start.clone(), grad.clone(), torch.zeros(n), torch.zeros(n)]
    reference = [start.clone(), torch.where(flagged, grad, 0.0), torch.zeros(n), torch.zeros(n)]
    assert adam_native(*native, clear=True, touched=flags, **kwargs)
    adam_step_torch(*reference, **kwargs)
    for a, b in zip(native[::2] + native[3:], reference[::2] + reference[3:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    assert not flags.any()
    assert not native[1][flagged].any() and torch.equal(native[1][~flagged], grad[~flagged])
    with pytest.raises(ValueError, match="touched flags"):
        adam_native(*native, clear=True, touched=torch.zeros(blocks + 1, dtype=torch.uint8), **kwargs)


@needs_native
@pytest.mark.parametrize("kind", ["density", "features", "hash"])
def test_the_grids_c_backward_flags_the_blocks_it_adds_into(kind: str) -> None:
    """After a read and its backward, the flagged blocks are the blocks holding a non-zero gradient, exactly
    (points inside cells: every corner gets a weight)."""
    from recon.nerf.grid import DenseGrid, HashGrid

    torch.manual_seed(0)
    grid = {"density": lambda: DenseGrid(20, 1), "features": lambda: DenseGrid(20, 12, init_std=0.1),
            "hash": lambda: HashGrid(levels=4, features=2, log2_table=12, base_res=4, max_res=64, init_scale=1.0)}[kind]()
    x = torch.rand(30, 3) * 0.9 + 0.05
    (grid(x) * torch.randn(30, grid.out_dim)).sum().backward()
    grad = grid.table.grad.view(-1)
    padded = torch.cat([grad, grad.new_zeros(-grad.numel() % ADAM_BLOCK)]).view(-1, ADAM_BLOCK)
    touched = grid.table.touched_blocks
    assert touched.valid_for(grid.table.grad)
    assert 0 < int(touched.flags.sum()) < touched.flags.numel()
    assert torch.equal(touched.flags.bool(), (padded != 0).any(1))


@needs_native
def test_a_gradient_another_writer_added_to_is_looked_at_whole() -> None:
    """A torch write into the flagged gradient (here an in-place add, as autograd's accumulation or a regularizer
    would make) changes its version: the flags no longer speak for it, the update looks at every block and moves
    the value the flags never saw; afterwards they are valid again."""
    from recon.nerf.grid import DenseGrid

    grid = DenseGrid(16, 4, init_std=0.1)
    opt = MaskedAdam([{"params": list(grid.parameters()), "masked": True}], lr=0.1)
    x = torch.full((1, 3), 0.1)
    grid(x).sum().backward()
    opt.step()
    opt.zero_grad()
    grid(x).sum().backward()  # flags the low corner's blocks
    far = grid.table.shape[0] - 1
    grid.table.grad[far] += 1.0
    touched = touched_blocks(grid.table)
    assert not touched.flags[far * 4 // ADAM_BLOCK] and not touched.valid_for(grid.table.grad)
    before = grid.table.detach()[far].clone()
    opt.step()
    assert not torch.equal(grid.table.detach()[far], before)
    assert touched.valid_for(grid.table.grad) and not touched.flags.any() and not grid.table.grad.any()


def test_touched_blocks_are_made_again_for_a_parameter_that_changed_size() -> None:
    p = torch.nn.Parameter(torch.zeros(130))
    first = touched_blocks(p)
    assert isinstance(first, TouchedBlocks) and first.flags.numel() == 3 and touched_blocks(p) is first
    p.data = torch.zeros(1000)
    assert touched_blocks(p).flags.numel() == 16


@needs_native
def test_zero_grad_keeps_only_the_gradients_a_step_left_all_zero() -> None:
    grid, net = torch.nn.Parameter(torch.randn(300)), torch.nn.Parameter(torch.randn(5))
    opt = MaskedAdam([{"params": [grid], "masked": True}, {"params": [net]}], lr=0.1)
    grid.grad, net.grad = _problem(300, 1, 0.8)[1], torch.ones(5)
    held = grid.grad
    opt.step()
    assert not held.any()  # the masked update used its gradients and set them to 0
    opt.zero_grad()
    assert grid.grad is held and net.grad is None
    grid.grad.add_(_problem(300, 2, 0.8)[1])  # the next backward adds into it
    net.grad = torch.ones(5)
    opt.step()
    assert grid.grad is held and not held.any()
    held.add_(1.0)  # changed since the step: not known to be 0 any more
    opt.zero_grad()
    assert grid.grad is None


@needs_native
def test_a_gradient_written_in_c_after_the_step_is_not_kept() -> None:
    """A dense grid's C backward writes into the kept gradient through a pointer; it says so (the tensor's version),
    so a zero_grad after a backward that no step followed drops what that backward wrote."""
    from recon.nerf.grid import DenseGrid

    grid = DenseGrid(8, 2, init_std=0.1)
    opt = MaskedAdam([{"params": list(grid.parameters()), "masked": True}], lr=0.1)
    x = torch.rand(50, 3)
    grid(x).sum().backward()
    opt.step()
    kept = grid.table.grad
    assert kept is not None and not kept.any()
    grid(x).sum().backward()  # into the kept gradient, in C, before any zero_grad
    assert grid.table.grad is kept and kept.any()
    opt.zero_grad()
    assert grid.table.grad is None


def test_the_c_update_declines_what_it_cannot_take() -> None:
    x = torch.zeros(8, dtype=torch.float64)
    kwargs = {"beta1": 0.9, "beta2": 0.999, "step_size": 0.1, "bias2_sqrt": 0.1, "eps": 1e-8, "masked": True}
    assert not adam_native(x, x, x, x, **kwargs)
    y = torch.zeros(4, 4)[:, 0]  # strided
    assert not adam_native(y, y, y, y, **kwargs)


def test_the_train_stage_picks_masked_adam_on_a_cpu_and_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    import recon.nerf.native as native
    from recon.config import load_config
    from recon.plans.training import choose_optimizer

    cfg = load_config("fast", []).train
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    if native_marcher() is not None:
        name, why = choose_optimizer(cfg, "fast", cpu)
        assert name == "masked_adam" and "touch few" in why
    assert choose_optimizer(cfg, "fast", cuda)[0] == "adam"
    assert choose_optimizer(cfg, "surface", cpu) == ("adam", "")
    forced = load_config("fast", ["train.optimizer=adam"]).train
    assert choose_optimizer(forced, "fast", cpu) == ("adam", "optimizer: adam (train.optimizer=adam)")
    monkeypatch.setattr(native, "native_marcher", lambda: None)
    name, why = choose_optimizer(cfg, "fast", cpu)
    assert name == "adam" and "no native library" in why


def _trained_fast_model(steps: int) -> tuple[torch.nn.Module, torch.Tensor, list[float]]:
    from recon.nerf.fast import FastConfig, FastModel
    from recon.nerf.fitting import RayBatcher
    from recon.nerf.trainer import train
    from tests.ball_scene import AABB, ball_views

    images, c2w, intr = ball_views()
    torch.manual_seed(0)
    model = FastModel(FastConfig(aabb=AABB.tolist(), density_res=24, feature_res=16, feature_dim=4, mlp_width=16,
                                 occupancy_res=16, occupancy_warmup=0, shrink_step=0))
    start = model.color_grid.table.detach().clone()
    seen: list[float] = []
    train(model, RayBatcher(images, c2w, intr, aabb=AABB, seed=0), steps=steps, lr=1e-2, batch_rays=256,
          optimizer="masked_adam", callbacks=[lambda p: seen.append(p.psnr)])
    return model, start, seen


def test_a_fast_model_learns_with_masked_adam_and_its_untouched_grid_values_stay() -> None:
    """The fast model's grids are the masked group: values outside every ray's reach keep their start."""
    model, start, seen = _trained_fast_model(120)
    assert sum(seen[-10:]) / 10 > sum(seen[:10]) / 10 + 5.0
    kept = (model.color_grid.table.detach() == start).all(1)
    assert 0 < int(kept.sum()) < kept.shape[0]  # some values were never reached, and kept their start exactly


@needs_native
@pytest.mark.parametrize("without", ["kept zero gradients", "flags"])
def test_keeping_the_zeroed_gradients_and_the_flags_changes_nothing(monkeypatch: pytest.MonkeyPatch,
                                                                    without: str) -> None:
    """MaskedAdam keeps the grids' gradients it left all 0 (the next backward adds into them unzeroed) and visits
    only the blocks the backward flagged: the same training, bit for bit, as dropping the gradients every step, or
    as looking at every block's gradient."""
    import recon.nerf.masked_adam as masked_adam

    flagged_steps = []
    native_update = masked_adam.adam_native

    def counted(*args: object, touched: torch.Tensor | None = None, **kwargs: object) -> bool:
        flagged_steps.append(touched is not None)
        return native_update(*args, touched=touched, **kwargs)

    monkeypatch.setattr(masked_adam, "adam_native", counted)
    fast, _, _ = _trained_fast_model(25)
    assert sum(flagged_steps) >= 25 * 2  # the grids' updates took the flags (after each grid's first step)
    if without == "flags":
        monkeypatch.setattr(TouchedBlocks, "valid_for", lambda self, grad: False)
    else:
        monkeypatch.setattr(MaskedAdam, "zero_grad", torch.optim.Optimizer.zero_grad)
    flagged_steps.clear()
    plain, _, _ = _trained_fast_model(25)
    assert any(flagged_steps) == (without != "flags")
    for (name, a), b in zip(fast.state_dict().items(), plain.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
