"""One plan for training (recon.plans.training.plan_training) and one way to build it (build_training): the train
stage, `recon bench --profile` and the benchmarks time and run the same step, pieces included."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from recon.app.profiling import profile_training
from recon.app.progress import Reporter
from recon.camera import look_at
from recon.capture.scene import Frame, Scene
from recon.config import TrainConfig
from recon.evaluation.views import View
from recon.nerf.pieces import DepthPriorLoss
from recon.plans.training import GRID_LR, build_training, plan_training
from tests.ball_scene import masked_ball_photos

W, H, FL = 16, 12, 14.0
CPU = torch.device("cpu")


def _unbounded_without_masks(n_views: int = 24) -> tuple[TrainConfig, Scene, list[View]]:
    """An unbounded capture without masks whose sparse points every photo sees: train.depth_prior=auto turns the
    prior on (whatever the photo count), so the step renders the prior's rays too."""
    frames, views = [], []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views
        c2w = look_at(np.array([3.0 * math.cos(a), 3.0 * math.sin(a), 1.0]), np.zeros(3))
        frames.append(Frame(f"/p/{i:02d}.jpg", c2w, FL, FL, W / 2, H / 2, W, H, split="train"))
        views.append(View(f"{i:02d}", np.full((H, W, 3), 128, np.uint8), c2w, (FL, FL, W / 2, H / 2), 1.0, 5.0))
    points = np.random.default_rng(0).uniform(-0.3, 0.3, (40, 3))
    scene = Scene(frames=frames, points=points, point_visibility={f.name: np.arange(40) for f in frames},
                  point_errors=np.full(40, 0.8), aabb=np.array([[-1.0] * 3, [1.0] * 3]), capture="unbounded")
    return replace(TrainConfig(), batch_rays=128), scene, views


def test_the_profiler_times_the_step_the_stage_plans_depth_prior_included() -> None:
    cfg, scene, views = _unbounded_without_masks()
    plan = plan_training(cfg, scene, views, CPU)  # what the train stage calls
    assert [r for r in plan.reasons if r.startswith("depth prior:")][0].startswith(
        "depth prior: on (an unbounded capture without masks")
    step, profiled_plan, setup = profile_training(cfg, scene, views, Reporter(quiet=True), warmup=2, steps=1,
                                                  title="unbounded")
    assert profiled_plan.reasons == step["reasons"] == plan.reasons
    assert step["pieces"] == ["DepthPriorLoss"]
    assert any(isinstance(p, DepthPriorLoss) for p in setup.step_kwargs["pieces"])
    depth_part = next(part for part in step["parts"] if part.startswith("depth prior"))
    assert step["parts"][depth_part] > 0  # the profiled step ran the prior's rays, and its time is shown apart


def test_an_unbounded_plan_cuts_rays_to_each_photos_near_far_and_builds_the_same_model_twice() -> None:
    cfg, scene, views = _unbounded_without_masks()
    plan = plan_training(replace(cfg, adjusted="no GPU: the CPU's settings"), scene, views, CPU)
    assert plan.reasons[0] == "no GPU: the CPU's settings" and plan.aabb is None
    first, second = build_training(plan, CPU), build_training(plan, CPU)
    assert first.aabb is None and first.batcher.near_far is not None
    assert first.step_kwargs["lr"] == plan.lr and first.step_kwargs["lr_final"] == plan.lr_final
    for a, b in zip(first.model.state_dict().values(), second.model.state_dict().values(), strict=True):
        assert torch.equal(a, b)  # seeded from the plan: the profiler's model is the stage's
    prior = first.step_kwargs["pieces"][0].prior
    assert prior is not plan.depth_prior and torch.equal(prior.depth, plan.depth_prior.depth)


def test_the_grid_models_rate_grows_with_the_cube_root_of_a_batch_above_4096_rays_and_says_so() -> None:
    cfg, scene, views = _unbounded_without_masks(8)
    obj = replace(scene, capture="object")
    for model, capture in (("fast", scene), ("surface", obj)):
        rates = {}
        for rays in (128, 4096, 32768):
            plan = plan_training(replace(cfg, batch_rays=rays, model=model), capture, views, CPU)
            rates[rays] = plan.lr, [r for r in plan.reasons if r.startswith("learning rate")]
            assert plan.lr_final == pytest.approx(plan.lr * cfg.lr_decay)
        assert rates[128] == rates[4096] == (GRID_LR, [])
        assert rates[32768][0] == pytest.approx(2 * GRID_LR)
        assert f"the {model} model's" in rates[32768][1][0] and "32,768 / 4,096" in rates[32768][1][0]
        chosen = plan_training(replace(cfg, batch_rays=32768, lr=3e-3, model=model), capture, views, CPU)
        assert chosen.lr == 3e-3 and not any(r.startswith("learning rate") for r in chosen.reasons)


def test_an_object_capture_plan_keeps_its_box() -> None:
    cfg, scene, views = _unbounded_without_masks(8)
    plan = plan_training(cfg, replace(scene, capture="object"), views, CPU)
    np.testing.assert_array_equal(plan.aabb, scene.aabb)
    setup = build_training(plan, CPU)
    torch.testing.assert_close(setup.aabb, torch.tensor(scene.aabb, dtype=torch.float32))
    assert setup.batcher.near_far is None


def test_the_plan_says_which_kernels_run_on_a_gpu_and_nothing_on_a_default_cpu() -> None:
    cfg, scene, views = _unbounded_without_masks(8)
    assert not any(r.startswith("kernels:") for r in plan_training(cfg, scene, views, CPU).reasons)
    triton_on_cpu = plan_training(replace(cfg, fast=replace(cfg.fast, kernels="triton")), scene, views, CPU)
    assert [r for r in triton_on_cpu.reasons if r.startswith("kernels:")] == [
        "kernels: torch on the cpu (train.fast.kernels=triton: the Triton kernels run on CUDA only)"]
    on_gpu = plan_training(cfg, scene, views, torch.device("cuda"))  # planning touches no CUDA memory
    assert any(r.startswith("kernels: ") for r in on_gpu.reasons)



@pytest.mark.parametrize("share", [0.0, 0.25])
def test_a_masked_fast_plan_trains_as_empty_space_the_transparent_pixels_the_photos_agree_on_and_says_so(
        share: float) -> None:
    """A ball on a ring of 12 photos, one of whose masks cut away half the ball: its cut half pays only
    train.transparent_disputed_share of the opacity loss (the other photos' masks keep the hull there; 0: the colour
    loss alone), while every photo's pixels off the ball train as empty at the full weight."""
    images, c2w, intr = masked_ball_photos(size=32, fl=40.0)
    wrong = images[3].copy()
    wrong[:, :16, 3] = 0  # the left half of the ball cut away in one photo
    images[3] = wrong
    frames, views = [], []
    for i, (image, pose, k) in enumerate(zip(images, c2w.double().numpy(), intr.tolist(), strict=True)):
        frames.append(Frame(f"/p/{i:02d}.png", pose, *k, 32, 32, split="train"))
        views.append(View(f"{i:02d}", image, pose, tuple(k), 1.0, 4.0))
    scene = Scene(frames=frames, aabb=np.array([[-1.0] * 3, [1.0] * 3]), capture="object", has_alpha=True)
    cfg = replace(TrainConfig(), batch_rays=128, transparent_disputed_share=share)
    plan = plan_training(cfg, scene, views, CPU)
    assert plan.empty is not None and plan.empty_weight == cfg.transparent_weight
    ball = [v.image[..., 3] > 0 for v in views]
    for i, (empty, view) in enumerate(zip(plan.empty, views, strict=True)):
        weight = np.asarray(empty, np.float32)
        assert not weight[view.image[..., 3] != 0].any()  # only transparent pixels are ever known empty
        assert (weight[:, :4] == 1).all() and (weight[:, -4:] == 1).all()  # far off the ball: empty in every photo
        if i != 3:
            assert (weight == 1).sum() >= 0.9 * (~ball[i]).sum()
    cut_half = ~ball[3] & ball[2]  # the ball's pixels that photo 3's mask lost (its neighbour still shows them there)
    assert cut_half.sum() > 50 and np.allclose(np.asarray(plan.empty[3], np.float32)[cut_half], share)
    said = next(r for r in plan.reasons if r.startswith("transparent pixels: "))
    assert "train as empty space (weight 0.1)" in said and "inside the hull" in said
    assert ("train by their colour only" in said) == (share == 0) and ("at 25% of that weight" in said) == (share > 0)
    pieces = build_training(plan, CPU).step_kwargs["pieces"]
    assert type(pieces[0]).__name__ == "EmptyRays" and pieces[0].weight == cfg.transparent_weight

    off = plan_training(replace(cfg, transparent_weight=0.0), scene, views, CPU)
    assert off.empty is None and "train.transparent_weight=0" in " ".join(off.reasons)
    opaque = [replace(v, image=np.ascontiguousarray(v.image[..., :3])) for v in views]
    unmasked = plan_training(cfg, replace(scene, has_alpha=False), opaque, CPU)
    assert unmasked.empty is None and not any(r.startswith("transparent pixels") for r in unmasked.reasons)
    classic = plan_training(replace(cfg, model="classic"), scene, views, CPU)
    assert classic.empty is None and "(the classic model)" in " ".join(classic.reasons)


@pytest.mark.parametrize("support", ["none", "table", "wall"])
def test_the_field_starts_inside_the_masks_hull_unless_the_object_hangs_on_a_wall(support: str) -> None:
    """train.hull_start=auto: a masked ball starts at hull_start_alpha a step inside the masks' visual hull (its middle)
    and as empty as ever outside it (the box's corners), standing on a table or on nothing; hung on a wall (a vertical
    support plane) it starts empty; on and off force it; without silhouettes it starts empty. Started empty though
    the photos have silhouettes, its occupancy culls untouched space late (and says so); otherwise at the usual pace."""
    images, c2w, intr = masked_ball_photos(size=32, fl=40.0)
    frames, views = [], []
    for i, (image, pose, k) in enumerate(zip(images, c2w.double().numpy(), intr.tolist(), strict=True)):
        frames.append(Frame(f"/p/{i:02d}.png", pose, *k, 32, 32, split="train"))
        views.append(View(f"{i:02d}", image, pose, tuple(k), 1.0, 4.0))
    ground = {"none": None, "table": np.array([0.0, 0.0, 1.0, -0.5]), "wall": np.array([0.0, -1.0, 0.0, -0.5])}[support]
    scene = Scene(frames=frames, aabb=np.array([[-1.0] * 3, [1.0] * 3]), capture="object", has_alpha=True,
                  ground=ground)
    base = TrainConfig()
    base = replace(base, fast=replace(base.fast, hull_start_alpha=0.2, init_alpha=0.01))

    def start(cfg: TrainConfig, photos: list[View] = views) -> tuple[list[float], str, int]:
        plan = plan_training(cfg, replace(scene, has_alpha=photos is views), photos, CPU)
        model = build_training(plan, CPU).model
        x = torch.tensor([[0.0, 0.0, 0.0], [0.95, 0.95, 0.95], [-0.95, 0.95, -0.95]])
        said = [r for r in plan.reasons if r.startswith("start:")]
        ramp = model.occupancy.ramp_steps
        return (1 - torch.exp(-model.density(x).detach() * model.step_size)).tolist(), " ".join(said), ramp

    on_wall = support == "wall"
    base = replace(base, fast=replace(base.fast, slow_occupancy_ramp=500))  # told apart from the usual ramp
    slow_ramp, usual_ramp = base.fast.slow_occupancy_ramp, base.fast.occupancy_ramp
    assert slow_ramp != usual_ramp
    (middle, *corners), said, ramp = start(base)
    assert ramp == (slow_ramp if on_wall else usual_ramp) and ("rising over" in said) == on_wall
    assert middle == pytest.approx(0.01 if on_wall else 0.2, rel=1e-3)
    assert corners == pytest.approx([0.01] * 2, rel=1e-3)
    assert ("hangs on a wall" in said) == on_wall and ("inside the visual hull" in said) == (not on_wall)
    (middle, *_), said, ramp = start(replace(base, hull_start="on"))
    assert middle == pytest.approx(0.2, rel=1e-3) and ramp == usual_ramp and "inside the visual hull of the 12 training photos" in said
    (middle, *_), said, ramp = start(replace(base, hull_start="off"))
    assert middle == pytest.approx(0.01, rel=1e-3) and "an empty field (train.hull_start=off)" in said
    assert ramp == slow_ramp and f"rising over {slow_ramp:,} steps" in said
    opaque = [replace(v, image=np.ascontiguousarray(v.image[..., :3])) for v in views]
    (middle, *_), said, ramp = start(base, opaque)
    assert middle == pytest.approx(0.01, rel=1e-3) and said == "" and ramp == usual_ramp


def test_distortion_loss_has_a_weight_for_objects_and_one_for_unbounded_captures_and_says_which() -> None:
    from recon.nerf.fast import FastModel
    from recon.nerf.model_config import FastConfig
    from recon.plans.training import auto_fast_config

    base = replace(FastConfig(), distortion_weight=0.03)
    box = np.array([[-1.0] * 3, [1.0] * 3])
    obj, why_obj = auto_fast_config(base, Scene(frames=[], aabb=box, capture="object"), footprint=0.01)
    far, why_far = auto_fast_config(base, Scene(frames=[], aabb=box, capture="unbounded"), footprint=0.01)
    assert any(r.startswith("distortion loss 0.03 (mip-NeRF 360, train.fast.distortion_weight)") for r in why_obj)
    assert any(r.startswith("no distortion loss (an object's: 0.03)") for r in why_far)
    small = dict(density_res=32, feature_res=16, occupancy_res=16)
    assert FastModel(replace(obj, **small)).distortion_weight == 0.03
    assert FastModel(replace(far, **small)).distortion_weight == 0.0
    on, why_on = auto_fast_config(replace(base, unbounded_distortion_weight=0.01),
                                  Scene(frames=[], aabb=box, capture="unbounded"), footprint=0.01)
    assert FastModel(replace(on, **small)).distortion_weight == 0.01
    assert any(r.startswith("distortion loss 0.01 (mip-NeRF 360, train.fast.unbounded_distortion_weight)")
               and "contracted distance" in r for r in why_on)
    assert not any("contracted distance" in r for r in why_obj)
    plain, why_plain = auto_fast_config(FastConfig(), Scene(frames=[], aabb=box, capture="object"), footprint=0.01)
    assert not any("distortion" in r for r in why_plain)
    assert not any("distortion_from" in r for r in why_obj)
    _, why_late = auto_fast_config(replace(base, distortion_from=0.3), Scene(frames=[], aabb=box, capture="object"),
                                   footprint=0.01)
    assert any(r.startswith("distortion loss 0.03") and "from 30% of training on (train.fast.distortion_from)" in r
               for r in why_late)


def test_close_ups_train_at_the_other_photos_pixel_footprint() -> None:
    """photo_sides: on a ring of photos with every second one stepped in to 0.4 of the distance, the close-ups (and
    only they) train at 0.4 of max_side, so their pixels on the object are as large as the others'; a ring at one
    distance, or train.photo_footprint=off, keeps every photo at max_side."""
    from recon.plans.training import photo_sides

    def ring(closer: float) -> Scene:
        frames = []
        for i in range(16):
            az = 2 * math.pi * i / 16
            eye = 4.0 * (closer if i % 2 else 1.0) * np.array([math.cos(az), math.sin(az), 0.5])
            frames.append(Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), 1600.0, 1600.0, 800.0, 600.0, 1600, 1200))
        return Scene(frames=frames, points=np.zeros((0, 3)), point_colors=np.zeros((0, 3), np.uint8),
                     aabb=np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))

    cfg = TrainConfig(max_side=400)
    scene = ring(0.4)
    sides, why = photo_sides(cfg, scene, scene.frames)
    assert set(sides) == {f.name for f in scene.frames[1::2]}
    assert all(v == round(0.4 * 400) for v in sides.values()) and "8 of 16" in why and "2.5x finer" in why
    even = ring(1.0)
    assert photo_sides(cfg, even, even.frames) == ({}, "")
    assert photo_sides(replace(cfg, photo_footprint="off"), scene, scene.frames)[0] == {}


def test_a_small_object_in_wide_photos_trains_at_a_larger_side() -> None:
    """training_side: a box of radius sqrt(3) seen by 1600-px photos (focal 1600) from 13.4 units spans 103 px at
    max_side 400, under half of it: the photos train at the side where it spans 400, capped by the photos' own size
    and the pixels all of them hold; from 4.5 units (310 px), an unbounded scene or train.small_object=off keeps
    max_side, and so does a smaller max_side (the box spans as large a share of it)."""
    from recon.plans.training import MAX_OBJECT_PIXELS, MAX_OBJECT_SIDE, training_side

    def ring(distance: float, size: int = 1600, capture: str = "object") -> Scene:
        eyes = [distance * np.array([math.cos(a), math.sin(a), 0.5]) / math.hypot(1, 0.5)
                for a in np.linspace(0, 2 * math.pi, 12, endpoint=False)]
        frames = [Frame(f"/p/{i:02d}.jpg", look_at(eye, np.zeros(3)), size, size, size / 2, size * 3 / 8, size,
                        size * 3 // 4) for i, eye in enumerate(eyes)]
        return Scene(frames=frames, points=np.zeros((0, 3)), point_colors=np.zeros((0, 3), np.uint8),
                     aabb=np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), capture=capture)

    cfg = TrainConfig(max_side=400)
    far = ring(13.4)
    side, why = training_side(cfg, far, far.frames)
    span = 2 * 400 * math.sqrt(3) / 13.4
    assert side == round(400 * 400 / span) < MAX_OBJECT_SIDE
    assert f"spans {span:.0f} px of the 400-px photos" in why and f"train at {side} px" in why
    near = ring(4.5)
    assert training_side(cfg, near, near.frames) == (400, "")
    assert training_side(replace(cfg, max_side=100), near, near.frames) == (100, "")  # a share of max_side counts
    assert training_side(replace(cfg, small_object="off"), far, far.frames) == (400, "")
    unbounded = ring(13.4, capture="unbounded")
    assert training_side(cfg, unbounded, unbounded.frames) == (400, "")
    farther = ring(40.0)
    assert training_side(cfg, farther, farther.frames)[0] == MAX_OBJECT_SIDE
    small_photos = ring(13.4, size=800)  # never larger than the photos themselves
    assert training_side(cfg, small_photos, small_photos.frames)[0] == 800
    many = ring(13.4)
    many.frames = many.frames * 4  # 48 photos: at 1547 px, 86 million pixels
    side = training_side(cfg, many, many.frames)[0]
    assert 400 < side < 1547 and len(many.frames) * side * side * 3 // 4 <= MAX_OBJECT_PIXELS
