"""Per-photo camera corrections learned with the field (nerfstudio's SO3xR3 camera optimizer, as in BARF).

SfM fits each camera to the few hundred features it matched; a photo that sees little texture (the generator's
thin plate seen edge on: 28 points) gets a pose a few pixels off, while the field would need every photo to agree
to the pixel. Here training photo i gets a small rotation ``exp(r_i)`` about its own centre and a shift ``t_i``
of that centre, both starting at zero and pulled back towards it (``REG_WEIGHT``): the photos' pixels move the
cameras where the SfM points left them loose. The field's frame must stay the SfM poses' frame (novel views and
held-out photos are posed in it), so the corrections must not move the cameras together: after each update the similarity that the corrected camera centres make with the SfM ones
(a shift, turn or scale of the whole rig, which the field could follow) is taken out (:meth:`PoseRefinement.hold_frame`).
Held-out photos are scored with their own pose fitted to the frozen field on the half of the photo not scored
(`recon.nerf.evaluate.align_pose`, BARF's protocol): their SfM poses are as far off as the training photos' were.

It finds the photos SfM misplaced most, but has not raised the held-out PSNR or the mesh's fine accuracy
(docs/real_captures.md), so it is opt-in (``train.pose_refine=on``).

The corrected training poses go into the field's metadata (``refined_c2w``), from which the mesh stage bakes colours.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from recon.geometry.compare import fit_sim3
from recon.nerf.rays import ray_aabb

__all__ = ["PoseRefinement", "so3_exp", "so3_log", "REG_WEIGHT", "LR", "EVERY", "START"]

REG_WEIGHT = 1e-2
"""Penalty on the corrections' squared size (radians², scene units²), summed over the six numbers, mean over photos."""

LR = 2e-5
"""Adam's rate for the corrections (radians, scene units per step): Adam moves a parameter about this much per update
whatever its gradient's size, so over 750 updates (3,000 steps) a camera can turn ~0.9° at most. Half this moves
a misplaced camera too little; nerfstudio's 1e-3 moves well-placed cameras while the field is still forming."""

EVERY = 4
"""The corrections learn on every EVERY-th step only: then the rays carry gradients back through every sample's
position. On every step that cost 25% of a fast step (sample: 181 against 243 steps per minute), on every 4th 9%
(221)."""

START = 0.1
"""...and not before this fraction of the training: the first steps' field is too rough to say where a camera is."""


def so3_exp(r: Tensor) -> Tensor:
    """Rotation matrices (N, 3, 3) from axis-angle vectors (N, 3) (Rodrigues), exact and smooth at zero."""
    theta2 = (r * r).sum(-1, keepdim=True)[..., None]  # (N, 1, 1)
    small = theta2 < 1e-8
    theta = theta2.clamp_min(1e-8).sqrt()
    # sin(θ)/θ and (1 - cos θ)/θ²: their Taylor series below 1e-4 rad, where the closed forms lose precision
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-8))
    zero = torch.zeros_like(r[:, 0])
    k = torch.stack([zero, -r[:, 2], r[:, 1], r[:, 2], zero, -r[:, 0], -r[:, 1], r[:, 0], zero], -1).view(-1, 3, 3)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def so3_log(rot: Tensor) -> Tensor:
    """Axis-angle vectors (N, 3) of rotation matrices (N, 3, 3) with angles below π (the inverse of so3_exp)."""
    cos = ((rot.diagonal(dim1=1, dim2=2).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    vee = torch.stack([rot[:, 2, 1] - rot[:, 1, 2], rot[:, 0, 2] - rot[:, 2, 0], rot[:, 1, 0] - rot[:, 0, 1]], -1)
    sin = torch.sin(theta)
    factor = torch.where(theta < 1e-4, 0.5 + theta**2 / 12.0, theta / (2.0 * sin.clamp_min(1e-12)))
    return factor[:, None] * vee


class PoseRefinement(nn.Module):
    """A rotation about its centre and a shift of it per training photo, applied to that photo's rays.

    ``centres`` (n, 3): the photos' camera centres as given; with them :meth:`hold_frame` keeps the rig in place."""

    def __init__(self, n_images: int, centres: Tensor | None = None, lr: float = LR, every: int = EVERY,
                 start: float = START) -> None:
        super().__init__()
        if n_images < 1 or every < 1:
            raise ValueError("PoseRefinement needs at least one photo and every >= 1")
        if centres is not None and tuple(centres.shape) != (n_images, 3):
            raise ValueError(f"centres must be ({n_images}, 3), got {tuple(centres.shape)}")
        self.lr, self.every, self.start = float(lr), int(every), float(start)
        self.centres = None if centres is None else centres.detach().double().cpu().numpy()
        self.rotation = nn.Parameter(torch.zeros(n_images, 3))
        self.translation = nn.Parameter(torch.zeros(n_images, 3))

    def learns_at(self, step: int, steps: int, fraction: float | None = None) -> bool:
        """Do the corrections learn on this step? Every ``every``-th one, once ``start`` of the training (of the steps
        or, when a time budget runs it, ``fraction`` of the budget) is done."""
        done = max(step / max(steps, 1), fraction or 0.0)
        return step % self.every == 0 and done >= self.start

    def forward(self, rays_o: Tensor, rays_d: Tensor, image: Tensor) -> tuple[Tensor, Tensor]:
        """The rays (B, 3) of photos ``image`` (B,) as the corrected cameras cast them (directions stay unit)."""
        rot = so3_exp(self.rotation)[image]
        d = torch.einsum("bij,bj->bi", rot, rays_d)
        return rays_o + self.translation[image], d

    def correct_batch(self, batch: dict[str, Tensor], aabb: Tensor | None) -> dict[str, Tensor]:
        """A trainer batch with its rays corrected; near/far re-cut against ``aabb`` when the scene is a box."""
        o, d = self(batch["rays_o"], batch["rays_d"], batch["image"])
        out = {**batch, "rays_o": o, "rays_d": d}
        if aabb is not None:
            near, far, hit = ray_aabb(o.detach(), d.detach(), aabb)
            # a ray the correction turned off the box keeps its old (empty) interval rather than a reversed one
            out["near"], out["far"] = torch.where(hit, near, batch["near"]), torch.where(hit, far, batch["far"])
        return out

    @torch.no_grad()
    def corrected_c2w(self, c2w: Tensor) -> Tensor:
        """The photos' camera-to-world matrices (n, 4, 4) as the corrections place them (for baking their colours)."""
        out = c2w.clone()
        out[:, :3, :3] = so3_exp(self.rotation.to(c2w)) @ c2w[:, :3, :3]
        out[:, :3, 3] = c2w[:, :3, 3] + self.translation.to(c2w)
        return out

    @torch.no_grad()
    def hold_frame(self) -> None:
        """Take out what the corrections do to the rig as a whole: the similarity (Umeyama) from the corrected camera
        centres to the given ones is applied to every corrected camera, so the rig keeps its place, orientation and
        size and the held-out photos' given poses stay those of the field's frame. Collinear or fewer than three
        centres fix the shift only."""
        if self.centres is None:
            return
        moved = self.centres + self.translation.detach().double().cpu().numpy()
        try:
            scale, turn, shift = fit_sim3(moved, self.centres)
        except ValueError:
            scale, turn, shift = 1.0, np.eye(3), (self.centres - moved).mean(0)
        held = scale * moved @ turn.T + shift
        self.translation.copy_(torch.as_tensor(held - self.centres, dtype=self.translation.dtype))
        q = torch.as_tensor(turn, dtype=self.rotation.dtype, device=self.rotation.device)
        self.rotation.copy_(so3_log(q @ so3_exp(self.rotation)))

    def regularizer(self) -> Tensor:
        return REG_WEIGHT * ((self.rotation**2).sum(-1) + (self.translation**2).sum(-1)).mean()

    @torch.no_grad()
    def summary(self, names: Sequence[str], focal_px: Sequence[float], distance: Sequence[float]) -> list[dict[str, Any]]:
        """Per photo: the rotation (degrees), the shift (scene units) and what they move the object in its image
        (pixels: the rotation's angle and the shift across the view at the object's ``distance``, times the focal)."""
        out = []
        for i, name in enumerate(names):
            angle = float(self.rotation[i].norm())
            shift = float(self.translation[i].norm())
            px = float(focal_px[i]) * (angle + shift / max(float(distance[i]), 1e-6))
            out.append({"photo": name, "rotation_deg": round(angle * 57.29578, 4), "shift": round(shift, 5),
                        "pixels": round(px, 2)})
        return out
