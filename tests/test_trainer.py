"""The training loop on a tiny synthetic scene: it learns, resumes identically, and stops on NaN."""
from __future__ import annotations

import math

import pytest
import torch

from recon.nerf.evaluate import render_image
from recon.nerf.fitting import RayBatcher, lr_at, training_done
from recon.nerf.trainer import TrainingDiverged, make_optimizer, train, warm_up
from tests.ball_scene import AABB, COLOR
from tests.ball_scene import ball_views as _scene
from tests.ball_scene import tiny_model as _tiny_model


def test_ground_truth_renders_the_ball() -> None:
    images, c2w, intr = _scene()
    centre = images[:, 6, 6]
    torch.testing.assert_close(centre, COLOR.expand(4, 3), atol=1e-3, rtol=0)
    torch.testing.assert_close(images[:, 0, 0], torch.ones(4, 3))  # corners see the white background


def test_batcher_covers_every_kept_pixel_once_per_epoch_and_composites_alpha() -> None:
    images, c2w, intr = _scene(2, 6)
    alpha = torch.rand(2, 6, 6, 1, generator=torch.Generator().manual_seed(0))
    rgba = torch.cat([images, alpha], dim=-1)
    b = RayBatcher(rgba, c2w, intr, aabb=AABB, background=(0.0, 0.0, 0.0), seed=3, drop_missed=False)
    assert b.n_rays == 72 and b.n_dropped == 0
    batch = b.next_batch(72)
    targets = (images * alpha).reshape(-1, 3)
    # every pixel exactly once: the multiset of targets matches
    torch.testing.assert_close(torch.sort(batch["rgb"].sum(-1)).values, torch.sort(targets.sum(-1)).values)
    assert torch.allclose(batch["rays_d"].norm(dim=-1), torch.ones(72))
    # box intersections: near/far bracket the box for rays that hit
    hit = batch["far"] > batch["near"]
    p = batch["rays_o"][hit] + 0.5 * (batch["near"] + batch["far"])[hit, None] * batch["rays_d"][hit]
    assert torch.all(p.abs() <= 1.0 + 1e-5)
    dropped = RayBatcher(images, c2w, intr, aabb=AABB * 0.5, seed=3)
    assert dropped.n_rays + dropped.n_dropped == 72 and dropped.n_dropped > 0


def test_batcher_state_round_trip_and_seed() -> None:
    images, c2w, intr = _scene(2, 6)
    rgba = torch.cat([images, torch.rand(2, 6, 6, 1)], dim=-1)
    a = RayBatcher(rgba, c2w, intr, aabb=AABB, random_background=True, seed=5)
    a.next_batch(50)
    s = a.state_dict()
    want = [a.next_batch(37) for _ in range(3)]
    b = RayBatcher(rgba, c2w, intr, aabb=AABB, random_background=True, seed=5)
    b.load_state_dict(s)
    for w in want:
        got = b.next_batch(37)
        for k in w:
            torch.testing.assert_close(got[k], w[k], rtol=0, atol=0)
    c = RayBatcher(rgba, c2w, intr, aabb=AABB, random_background=True, seed=6)
    c.next_batch(50)
    assert not torch.equal(c.next_batch(37)["rgb"], want[0]["rgb"])


def test_lr_decay_is_exponential() -> None:
    assert lr_at(0, 100, 1e-2, 1e-4) == pytest.approx(1e-2)
    assert lr_at(50, 100, 1e-2, 1e-4) == pytest.approx(1e-3)
    assert lr_at(100, 100, 1e-2, 1e-4) == pytest.approx(1e-4)
    assert lr_at(7, 100, 1e-2, None) == 1e-2


@pytest.mark.parametrize("optimizer", ["adam", "masked_adam"])
def test_the_second_beta_reaches_the_optimizer(optimizer: str) -> None:
    """train.adam_beta2 sets the rate at which either optimizer forgets its squared gradients."""
    default = make_optimizer(_tiny_model(), 1e-2, optimizer)
    chosen = make_optimizer(_tiny_model(), 1e-2, optimizer, 0.99)
    assert {g["betas"] for g in default.param_groups} == {(0.9, 0.999)}
    assert {g["betas"] for g in chosen.param_groups} == {(0.9, 0.99)}


def test_the_model_hears_the_share_of_training_done_before_each_step() -> None:
    """Steps decide it without a budget; a budget's spent share decides it when larger (as for the rate)."""
    assert training_done(3, 4) == 0.75 and training_done(1, 4, 0.6) == 0.6 and training_done(3, 4, 0.2) == 0.75
    assert training_done(9, 4, 1.3) == 1.0 and training_done(0, 0) == 0.0
    images, c2w, intr = _scene()
    model = _tiny_model()
    heard: list[float] = []
    set_progress = model.set_progress
    model.set_progress = lambda p: heard.append(p) or set_progress(p)  # type: ignore[method-assign]
    train(model, RayBatcher(images, c2w, intr, aabb=AABB, seed=0), steps=4, lr=1e-2, batch_rays=32)
    assert heard == [0.0, 0.25, 0.5, 0.75] and model.progress == 0.75


def test_training_learns_the_ball() -> None:
    images, c2w, intr = _scene()
    batcher = RayBatcher(images, c2w, intr, aabb=AABB, seed=0)
    model = _tiny_model()
    seen = []
    result = train(model, batcher, steps=150, lr=1e-2, lr_final=2e-3, batch_rays=128,
                   callbacks=[lambda p: seen.append(p.psnr)], history_every=50)
    first, last = sum(seen[:10]) / 10, sum(seen[-10:]) / 10
    assert last > first + 10.0, (first, last)
    assert last > 22.0
    assert len(result["history"]) == 3 and result["step"] == 150
    view = render_image(model, c2w[1], intr[1], 12, 12, chunk=50, aabb=AABB)
    assert view["rgb"].shape == (12, 12, 3) and view["depth"].shape == (12, 12)
    err = ((view["rgb"] - images[1]) ** 2).mean()
    assert -10 * math.log10(err) > 22.0


def test_resume_equals_uninterrupted_run() -> None:
    images, c2w, intr = _scene(3, 8)
    kw = dict(steps=12, lr=5e-3, lr_final=1e-3, batch_rays=64)

    full = _tiny_model(1)
    torch.manual_seed(123)
    train(full, RayBatcher(images, c2w, intr, aabb=AABB, seed=2), **kw)

    saved = {}
    part = _tiny_model(1)
    torch.manual_seed(123)

    def checkpoint(p):
        if p.step == 5:
            saved["state"] = p.state_dict()
        if p.step == 7:
            raise KeyboardInterrupt  # the run dies after its checkpoint; its later progress is lost

    with pytest.raises(KeyboardInterrupt):
        train(part, RayBatcher(images, c2w, intr, aabb=AABB, seed=2), callbacks=[checkpoint], **kw)
    resumed = _tiny_model(99)  # a fresh process: different init and RNG, all restored from the state
    torch.manual_seed(0)
    out = train(resumed, RayBatcher(images, c2w, intr, aabb=AABB, seed=2), state=saved["state"], **kw)
    assert out["step"] == 12
    for (k, a), b in zip(full.state_dict().items(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)


def test_a_warm_up_render_leaves_training_as_it_would_have_been() -> None:
    """The train stage's warm-up on CUDA (kernels compile before the budget): after it, the same run to the bit."""
    images, c2w, intr = _scene(3, 8)
    rgba = torch.cat([images, torch.rand(3, 8, 8, 1, generator=torch.Generator().manual_seed(1))], dim=-1)
    kw = dict(steps=6, lr=5e-3, lr_final=1e-3, batch_rays=64)
    runs = []
    for warm in (False, True):
        model = _tiny_model(1)
        batcher = RayBatcher(rgba, c2w, intr, aabb=AABB, random_background=True, seed=2)
        batcher.next_batch(40)  # mid-stream, as a resumed run is
        torch.manual_seed(123)
        if warm:
            before = {k: v.clone() for k, v in model.state_dict().items()}
            assert warm_up(model, batcher, 64) > 0.0
            assert all(p.grad is None for p in model.parameters())
            for k, v in model.state_dict().items():
                torch.testing.assert_close(v, before[k], rtol=0, atol=0, msg=k)
        out = train(model, batcher, **kw)
        runs.append((out["loss"], model.state_dict(), torch.rand(3)))
    assert runs[0][0] == runs[1][0]
    torch.testing.assert_close(runs[1][2], runs[0][2], rtol=0, atol=0)  # the random stream goes on as it would have
    for (k, a), b in zip(runs[0][1].items(), runs[1][1].values()):
        torch.testing.assert_close(b, a, rtol=0, atol=0, msg=k)


def test_interrupt_carries_a_resumable_state() -> None:
    images, c2w, intr = _scene(2, 6)
    model = _tiny_model()

    def stop(p):
        if p.step == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt) as info:
        train(model, RayBatcher(images, c2w, intr, aabb=AABB), steps=10, lr=1e-3, batch_rays=16, callbacks=[stop])
    assert info.value.step == 3 and info.value.state["step"] == 3


def test_nan_guard_names_the_step_and_advice() -> None:
    images, c2w, intr = _scene(2, 6)
    model = _tiny_model()
    with pytest.raises(TrainingDiverged) as info:
        train(model, RayBatcher(images, c2w, intr, aabb=AABB), steps=10, lr=math.inf, batch_rays=32)
    err = info.value
    assert err.step == 1
    assert "NaN" in err.cause
    assert "Lower the learning rate" in str(err) and "step 1" in str(err)


def test_bf16_autocast_trains_with_float32_rendering() -> None:
    images, c2w, intr = _scene(2, 6)
    model = _tiny_model()
    out = train(model, RayBatcher(images, c2w, intr, aabb=AABB), steps=5, lr=1e-3, batch_rays=32, autocast=torch.bfloat16)
    assert math.isfinite(out["loss"])
    view = render_image(model, c2w[0], intr[0], 6, 6, aabb=AABB, autocast=torch.bfloat16)
    assert view["rgb"].dtype == torch.float32 and torch.isfinite(view["rgb"]).all()


def test_select_device() -> None:
    from recon.nerf.device import cpu_threads, select_device

    assert select_device("cpu") == torch.device("cpu")
    assert torch.get_num_threads() == cpu_threads() >= 1
    assert select_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="unknown device"):
        select_device("tpu")


def test_a_state_resumed_under_another_budget_follows_that_budgets_schedule() -> None:
    """Ctrl-C halfway through a budget, then a budget four times as long: the rate is that budget's at the time
    spent (an eighth of it), as if it had been given from the start, not the stopped budget's half."""
    images, c2w, intr = _scene(2, 6)
    kw = dict(steps=10_000, lr=1e-2, lr_final=1e-4, batch_rays=32)
    states = {}

    def stop_at(step):
        def stop(p):
            states.setdefault("rates", []).append(p.lr)
            if p.step == step:
                states["state"] = p.state_dict()
                raise KeyboardInterrupt
        return stop

    with pytest.raises(KeyboardInterrupt):
        train(_tiny_model(), RayBatcher(images, c2w, intr, aabb=AABB), budget_s=1e6, callbacks=[stop_at(3)], **kw)
    states["rates"] = []
    with pytest.raises(KeyboardInterrupt):  # resumed with 500 s spent of a 4,000-s budget
        train(_tiny_model(), RayBatcher(images, c2w, intr, aabb=AABB), budget_s=4000.0, spent_s=500.0,
              state=states["state"], callbacks=[stop_at(6)], **kw)
    assert states["rates"] == pytest.approx([lr_at(0, 1, 1e-2, 1e-4, 0.125)] * 3, rel=1e-3)


def test_a_finished_training_state_with_its_weights_put_back_trains_the_field_on() -> None:
    """train's returned state holds no weights and no optimizer moments (the field file holds the weights): with
    them put back it restores the field as it was and trains on from its step, the batch stream going on."""
    images, c2w, intr = _scene(3, 8)
    kw = dict(lr=5e-3, lr_final=1e-3, batch_rays=64)
    first = _tiny_model(1)
    state = train(first, RayBatcher(images, c2w, intr, aabb=AABB, seed=2), steps=5, **kw)["state"]
    assert state["step"] == 5 and "model" not in state and "optimizer" not in state
    stream = RayBatcher(images, c2w, intr, aabb=AABB, seed=2)
    for _ in range(5):
        stream.next_batch(64)
    assert state["batcher"]["cursor"] == stream.state_dict()["cursor"]
    kept = {"model": {k: v.clone() for k, v in first.state_dict().items()}, **state}
    same = _tiny_model(99)
    assert train(same, RayBatcher(images, c2w, intr, aabb=AABB, seed=2), steps=5, state=kept, **kw)["step"] == 5
    for (k, a), b in zip(first.state_dict().items(), same.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)
    steps: list[int] = []
    on = _tiny_model(99)
    train(on, RayBatcher(images, c2w, intr, aabb=AABB, seed=2), steps=12, state=kept, **kw,
          callbacks=[lambda p: steps.append(p.step)])
    assert steps == list(range(6, 13))
