"""A 2D neural field: an MLP with positional encoding fitting one image (the NeRF course's first exercise).

It isolates the encoding: with n_freqs = 0 the MLP can only learn a blur; with L ≈ 8–10 it reproduces
fine detail. A quick check that the encoding and the optimizer are right, with a PSNR curve.
"""
from __future__ import annotations

import time
from collections.abc import Callable

import torch
from torch import Tensor, nn

from recon.evaluation.metrics import mse_to_psnr

from .encoding import PositionalEncoding


class ImageField(nn.Module):
    """(x, y) in [-1, 1]² → RGB: positional encoding + ReLU MLP + sigmoid."""

    def __init__(self, n_freqs: int = 10, width: int = 256, depth: int = 4) -> None:
        super().__init__()
        self.encoding = PositionalEncoding(n_freqs, include_input=True, in_dim=2)
        layers: list[nn.Module] = []
        dim = self.encoding.out_dim
        for _ in range(depth):
            layers += [nn.Linear(dim, width), nn.ReLU(inplace=True)]
            dim = width
        layers += [nn.Linear(dim, 3), nn.Sigmoid()]
        self.mlp = nn.Sequential(*layers)

    def forward(self, xy: Tensor) -> Tensor:
        """xy: (N, 2) → rgb (N, 3)."""
        return self.mlp(self.encoding(xy))


def pixel_grid(h: int, w: int, device: torch.device | str = "cpu") -> Tensor:
    """(H·W, 2) pixel-centre coordinates in [-1, 1] (x right, y down), row-major."""
    ys = (torch.arange(h, device=device, dtype=torch.float32) + 0.5) / h * 2 - 1
    xs = (torch.arange(w, device=device, dtype=torch.float32) + 0.5) / w * 2 - 1
    yy, xx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([xx, yy], dim=-1).reshape(-1, 2)


def fit_image(
    image: Tensor,
    steps: int = 1000,
    n_freqs: int = 10,
    lr: float = 1e-3,
    batch: int = 8192,
    seed: int = 0,
    on_step: Callable[[int, float], None] | None = None,
    eval_every: int = 50,
) -> tuple[ImageField, list[dict[str, float]]]:
    """Fit an ImageField to image (H, W, 3) in [0, 1]; returns the model and a PSNR curve over the full image."""
    torch.manual_seed(seed)
    h, w = image.shape[:2]
    coords = pixel_grid(h, w, image.device)
    target = image.reshape(-1, 3).float()
    model = ImageField(n_freqs).to(image.device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    gen = torch.Generator(device="cpu").manual_seed(seed)
    curve: list[dict[str, float]] = []
    t0 = time.perf_counter()
    for step in range(1, steps + 1):
        idx = torch.randint(0, h * w, (min(batch, h * w),), generator=gen).to(image.device)
        loss = torch.mean((model(coords[idx]) - target[idx]) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % eval_every == 0 or step == steps:
            with torch.no_grad():
                full = torch.cat([model(c) for c in coords.split(65536)])
                p = float(mse_to_psnr(torch.mean((full - target) ** 2)))
            curve.append({"step": step, "psnr": p, "time_s": time.perf_counter() - t0})
        if on_step:
            on_step(step, float(loss))
    return model, curve


def render_field(model: ImageField, h: int, w: int) -> Tensor:
    """The fitted image (H, W, 3)."""
    device = next(model.parameters()).device
    with torch.no_grad():
        coords = pixel_grid(h, w, device)
        return torch.cat([model(c) for c in coords.split(65536)]).reshape(h, w, 3)
