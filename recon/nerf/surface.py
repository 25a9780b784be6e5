"""The surface field: a signed distance on multi-level dense grids, rendered as a NeuS volume.

Why: a density field's mesh is an iso-surface of a soft, unconstrained volume (orange peel on flat faces,
inner walls, holes where no photo looked). A signed distance f (negative inside) has one zero set that is
closed by construction; rendering it as a volume lets photos train it like a radiance field.

* f(x) = f0(x) + sum of the enabled levels of a multi-level dense grid + a small MLP on the levels' values
  (last layer zero): at step 0 the field is exactly f0, a closed surface's SDF (the geometric initialization
  of SAL/IDR/NeuS, here exact instead of approximate). f0 is the photos' visual hull when they have silhouettes
  (``init_shape="visual_hull"``, set with ``set_initial_sdf``; `recon.geometry.visual_hull`), else the convex hull
  of the SfM points when the config has its planes (``init_planes``), on a frozen grid either way, else a sphere
  |x - c| - r0. Why a hull, with a weak pull back to it (``init_prior_weight``): what no photo sees drifts with
  the coarse levels the seen parts move, so from a sphere an unseen underside comes out as a cave; the hull and
  the pull keep it where the silhouettes (or the SfM points) put it. The grid levels are
  :class:`recon.nerf.grid.DenseGrid` scalars read through ``grid_sample`` (the fastest read grid.py measured).
* Coarse to fine (Neuralangelo, Li et al. 2023): level k is added to f after ``k * level_every`` steps,
  and the finite-difference step of the regularizers shrinks with the finest enabled level.
* Opacity, NeuS form (Wang et al. 2021, eq. 13): over an interval whose ends have SDF f0 and f1,
  alpha = max((Φ(f0) - Φ(f1)) / Φ(f0), 0) with Φ(x) = sigmoid(s x) and a learned sharpness s. As
  optical thickness tau = -log(1 - alpha) = log Φ(f0) - log Φ(f1) (``logsigmoid``: finite for any s and f),
  so the packed transmittance of :mod:`recon.nerf.render` composites it unchanged. For a plane the
  weights are the logistic density of the crossing point, symmetric about the surface: unbiased
  (tests/test_nerf_surface.py). NeuS over VolSDF: VolSDF's density is a Laplace CDF of -f whose weight
  peak lies in front of the surface unless its error-bounded sampler places samples; NeuS's alpha from
  consecutive SDF values is unbiased with the plain fixed-step marching this project already has.
* Consecutive samples share an end point (uniform steps), so f is evaluated once per boundary, not twice.
* Eikonal (|∇f| - 1)² and curvature |Δf| (Neuralangelo) on a subset of the ray samples and on random
  points in the box, both from central finite differences (6 extra SDF reads per point, step one cell
  of the finest enabled level, so the gradient spans grid cells instead of being one cell's constant).
* The object closes inside its box: relu(2 cells - f) on random points of the box's faces. NeuS makes
  opacity only where a ray crosses from f > 0 to f < 0, so an inside that reaches a face is invisible to
  rays entering there and nothing holds it back: without it the SDF can run through the box floor under the
  object, and the mesh's underside is then the floor.
* Empty space: the occupancy grid of :mod:`recon.nerf.occupancy` marks a vertex occupied when
  |f| < 2 cell diagonals + ``band_width / s`` (weights are below e^-band_width of the peak beyond); rays march only
  through that shell, and a no-grad pre-pass drops samples behind the surface (early termination).
* Color as in :mod:`recon.nerf.fast`: a dense feature grid and a small MLP (optionally view dependent).
* Concavities: NeuS gives opacity wherever f falls along a ray, inside too, so a field that has closed over a
  concavity (a bowl) keeps a lid there, and colours alone do not open it. The train stage adds the SfM points'
  depths (`recon.nerf.depth_prior`) for this model, which do.

Coordinates: the normalized scene frame of an object capture (bounded; the grids span ``aabb``).

Two choices for CPU speed: the regularizers' gradients are central differences, not autograd with
``create_graph`` (slower, and constant inside a grid cell); the SDF MLP uses ReLU, not IDR/NeuS's Softplus
(several times the cost on a CPU, and the grids already make f piecewise trilinear). Current accuracy and speed:
docs/surface.md and the records in benchmarks/.
"""
from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from recon.nerf.fast import _make_grid, color_from_features, composite_packed, make_color_mlp, ray_background
from recon.nerf.grid import MultiDenseGrid, grid_sample_coords
from recon.nerf.model_config import SurfaceConfig
from recon.nerf.occupancy import OccupancyGrid, march
from recon.nerf.rays import clip_to_box
from recon.nerf.render import RadianceModel, accumulate_packed, checked_aabb

__all__ = ["SurfaceConfig", "SurfaceModel", "neus_tau", "sdf_fd_terms", "eikonal_loss", "boundary_loss", "box_face_points",
           "hull_planes", "planes_sdf"]


def hull_planes(points: Any, box: Any, min_points: int = 20) -> list[tuple[float, float, float, float]]:
    """The faces (nx, ny, nz, d) of the convex hull of the points (N, 3) inside box (2, 3), n·x <= d inside
    (coplanar facets merged); [] when fewer than `min_points` lie in the box or they span no volume."""
    import numpy as np
    from scipy.spatial import ConvexHull, QhullError

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    lo, hi = np.asarray(box, np.float64)
    pts = pts[((pts >= lo) & (pts <= hi)).all(axis=1)]
    if len(pts) < min_points:
        return []
    try:
        eq = ConvexHull(pts).equations  # n·x + offset <= 0 inside, unit n
    except QhullError:
        return []
    eq = np.unique(np.round(eq, 6), axis=0)
    return [(float(a), float(b), float(c), float(-o)) for a, b, c, o in eq]


def planes_sdf(x: Tensor, planes: Tensor) -> Tensor:
    """max_k (n_k·x - d_k) at points x (M, 3) for half-spaces planes (K, 4): the signed distance of their
    intersection inside it and on its faces' sides (a lower bound near edges outside); |gradient| = 1 everywhere."""
    return (x @ planes[:, :3].T - planes[:, 3]).amax(dim=-1)


def neus_tau(f0: Tensor, f1: Tensor, s: Tensor | float) -> Tensor:
    """Optical thickness -log(1 - alpha) of intervals whose ends have SDF f0, f1 (M,), NeuS opacity.

    alpha = max((Φ(f0) - Φ(f1)) / Φ(f0), 0), Φ(x) = sigmoid(s x)  ⇒  tau = max(log Φ(f0) - log Φ(f1), 0),
    from ``logsigmoid``: finite values and gradients for any sharpness (1e-6 to 1e8 in the tests).
    """
    return (F.logsigmoid(s * f0) - F.logsigmoid(s * f1)).clamp_min(0.0)


def sdf_fd_terms(sdf_fn: Any, x: Tensor, h: float) -> tuple[Tensor, Tensor]:
    """Gradient (M, 3) and Laplacian (M,) of sdf_fn at x (M, 3) by central differences of step h.

    One call of sdf_fn on 7 M points (x and x ± h e_i): f((M,3)) -> (M,).
    """
    m = x.shape[0]
    eye = torch.eye(3, dtype=x.dtype, device=x.device) * h
    offsets = torch.cat([torch.zeros_like(eye[:1]), eye, -eye])
    f = sdf_fn((x[None] + offsets[:, None]).reshape(-1, 3)).reshape(7, m)
    grad = (f[1:4] - f[4:7]).T / (2.0 * h)
    lap = (f[1:4] + f[4:7] - 2.0 * f[0]).sum(0) / (h * h)
    return grad, lap


def eikonal_loss(grad: Tensor) -> Tensor:
    """Mean (|∇f| - 1)² over gradients (M, 3): zero for an exact signed distance."""
    return ((grad.norm(dim=-1) - 1.0) ** 2).mean()


def box_face_points(box: Tensor, n: int) -> Tensor:
    """n points (n, 3) uniform on each of the six faces of box (2, 3) in turn (face k gets every 6th point)."""
    x = box[0] + torch.rand(n, 3, device=box.device, dtype=box.dtype) * (box[1] - box[0])
    face = torch.arange(n, device=box.device) % 6
    axis, side = face // 2, face % 2
    x[torch.arange(n, device=box.device), axis] = box[side, axis]
    return x


def boundary_loss(f_faces: Tensor, margin: float) -> Tensor:
    """Mean relu(margin - f) over SDF values (M,) on the box's faces: zero when the surface closes at least
    `margin` inside the box, growing linearly (gradient -1/M per point) where the inside reaches a face."""
    return (margin - f_faces).clamp_min(0.0).mean()


class SurfaceModel(RadianceModel):
    """SDF on multi-level dense grids rendered with NeuS opacity (see the module docstring)."""

    def __init__(self, config: SurfaceConfig | None = None) -> None:
        super().__init__()
        cfg = self.config = config or SurfaceConfig()
        aabb = checked_aabb(cfg.aabb, "SurfaceConfig")
        self.register_buffer("aabb", aabb)
        extent = float((aabb[1] - aabb[0]).max())
        self.register_buffer("centre", aabb.mean(0))
        self.radius0 = cfg.init_radius * 0.5 * float((aabb[1] - aabb[0]).min())
        self.sdf_grid = MultiDenseGrid(cfg.sdf_res, 1, levels=cfg.sdf_levels)
        # the initial surface on a frozen grid of the finest level's resolution: the planes' intersection (exact where
        # it is planar), rebuilt from the config rather than saved; or a visual hull, which is saved with the weights
        # (NaN until `set_initial_sdf` or a loaded state fills it, so a model never starts from an unset shape)
        if cfg.init_shape == "visual_hull":
            r = int(cfg.sdf_res)
            self.register_buffer("prior_volume", torch.full((1, 1, r, r, r), float("nan")))
        else:
            self.register_buffer("prior_volume", self._planes_volume(cfg, aabb), persistent=False)
        self.level_cells = [extent / (g.res - 1) for g in self.sdf_grid.grids]
        n_lv = len(self.sdf_grid.grids)
        if cfg.sdf_mlp_width > 0:
            self.sdf_mlp: nn.Sequential | None = nn.Sequential(
                nn.Linear(n_lv, cfg.sdf_mlp_width), nn.ReLU(), nn.Linear(cfg.sdf_mlp_width, 1)
            )
            nn.init.zeros_(self.sdf_mlp[2].weight)
            nn.init.zeros_(self.sdf_mlp[2].bias)
        else:
            self.sdf_mlp = None
        self.log_s = nn.Parameter(torch.tensor(math.log(cfg.init_sharpness)))
        self.step_size = cfg.step_ratio * self.level_cells[-1]
        self.color_grid = _make_grid("dense", cfg.feature_res, cfg.feature_dim, density=False)
        self.color_mlp = make_color_mlp(self.color_grid.out_dim, cfg.color_model, cfg.sh_degree, cfg.mlp_width, cfg.mlp_layers)
        self.bg_logit = nn.Parameter(torch.zeros(3)) if cfg.background == "learned" else None
        self.occupancy = OccupancyGrid(aabb, resolution=cfg.occupancy_res, sigma_threshold=0.5,
                                       warmup_steps=cfg.occupancy_warmup)
        self.register_buffer("march_box", aabb.clone())
        self.register_buffer("step", torch.zeros((), dtype=torch.long))

    @staticmethod
    @torch.no_grad()
    def _planes_volume(cfg: SurfaceConfig, aabb: Tensor, chunk: int = 1 << 16) -> Tensor | None:
        """``planes_sdf`` of cfg.init_planes at the vertices of an sdf_res³ grid over aabb, as grid_sample's
        (1, 1, r, r, r) volume; None without planes."""
        if not cfg.init_planes:
            return None
        planes = torch.tensor(cfg.init_planes, dtype=torch.float32).reshape(-1, 4)
        r = int(cfg.sdf_res)
        axes = [torch.linspace(float(aabb[0, i]), float(aabb[1, i]), r) for i in range(3)]
        pts = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        vol = torch.cat([planes_sdf(pts[s:s + chunk], planes) for s in range(0, pts.shape[0], chunk)])
        return vol.view(1, 1, r, r, r)

    @torch.no_grad()
    def set_initial_sdf(self, volume: Any) -> None:
        """Start from a signed distance given at the vertices of an sdf_res³ grid over the box, indexed [ix, iy, iz]
        (``init_shape="visual_hull"``: `recon.geometry.visual_hull.visual_hull_sdf`)."""
        if self.config.init_shape != "visual_hull":
            raise ValueError(f"set_initial_sdf needs init_shape='visual_hull' (this model's is '{self.config.init_shape}')")
        vol = torch.as_tensor(volume, dtype=torch.float32)
        r = int(self.config.sdf_res)
        if tuple(vol.shape) != (r, r, r) or not torch.isfinite(vol).all():
            raise ValueError(f"the initial SDF must be a finite {r}³ grid (got shape {tuple(vol.shape)})")
        self.prior_volume.copy_(vol.view(1, 1, r, r, r))

    def initial_sdf(self, x: Tensor, u: Tensor) -> Tensor:
        """The SDF the grids add to (M,) at world points x (M, 3) (u: the same in [0, 1] of the box): the visual
        hull or the planes' intersection when the config has them, else a sphere at the box centre."""
        if self.prior_volume is None:
            return (x - self.centre.to(x)).norm(dim=-1) - self.radius0
        return F.grid_sample(self.prior_volume.to(x.dtype), grid_sample_coords(u, x.dtype), mode="bilinear",
                             align_corners=True).view(-1)

    # ------------------------------------------------------------------ the field
    @property
    def active_levels(self) -> int:
        """SDF grid levels in use at the current step (coarse to fine)."""
        every, n = self.config.level_every, len(self.sdf_grid.grids)
        return n if every <= 0 else min(n, 1 + self.current_step() // every)

    @property
    def fd_step(self) -> float:
        """Finite-difference step of the regularizers: one cell of the finest enabled level."""
        return self.level_cells[self.active_levels - 1]

    @property
    def voxel_size(self) -> float:
        """Edge of the finest SDF voxel (world units)."""
        return self.level_cells[-1]

    @property
    def sharpness(self) -> Tensor:
        """NeuS s (1/world unit), > 0."""
        return self.log_s.clamp(-20.0, 20.0).exp()

    def sdf(self, x: Tensor) -> Tensor:
        """Signed distance (M,) at world points x (M, 3), negative inside (world units)."""
        box = self.aabb.to(x)
        u = ((x - box[0]) / (box[1] - box[0])).clamp(0.0, 1.0)
        k = self.active_levels
        levels = [g(u) for g in self.sdf_grid.grids[:k]]
        feats = torch.cat(levels, dim=-1)
        f = self.initial_sdf(x, u) + feats.sum(-1)
        if self.sdf_mlp is not None:
            if k < len(self.sdf_grid.grids):
                feats = F.pad(feats, (0, len(self.sdf_grid.grids) - k))
            f = f + self.sdf_mlp(feats).squeeze(-1)
        return f

    def density(self, x: Tensor) -> Tensor:
        """Logistic density s·sigmoid(-s f) (1/world unit) at x (M, 3): the NeuS field seen as a density,
        for tools that want one (training and meshing use the SDF itself)."""
        s = self.sharpness
        return s * torch.sigmoid(-s * self.sdf(x))

    def radiance(self, x: Tensor, d: Tensor) -> Tensor:
        """RGB (M, 3) in [0, 1] at world points x (M, 3) seen along unit directions d (M, 3)."""
        box = self.aabb.to(x)
        u = ((x - box[0]) / (box[1] - box[0])).clamp(0.0, 1.0)
        return color_from_features(self.color_grid(u), d, self.color_mlp, self.config.color_model, self.config.sh_degree)

    # ------------------------------------------------------------------ rendering
    def interval_sdf(self, rays_o: Tensor, rays_d: Tensor, ts: Tensor, te: Tensor, ri: Tensor) -> tuple[Tensor, Tensor]:
        """SDF at the start and end (M,) of packed intervals; an end shared with the next interval's start
        (same ray, contiguous) is evaluated once."""
        m = ts.shape[0]
        if m == 0:
            return ts.clone(), ts.clone()
        contiguous = torch.zeros(m, dtype=torch.bool, device=ts.device)
        contiguous[:-1] = (ri[1:] == ri[:-1]) & ((ts[1:] - te[:-1]).abs() <= 1e-4 * (te[:-1] - ts[:-1]))
        extra = (~contiguous).nonzero().squeeze(-1)
        t_all = torch.cat([ts, te[extra]])
        r_all = torch.cat([ri, ri[extra]])
        f_all = self.sdf(rays_o[r_all] + rays_d[r_all] * t_all[:, None])
        f0 = f_all[:m]
        f_next = torch.cat([f0[1:], f0[:1]])
        f_extra = torch.zeros_like(f0).index_put((extra,), f_all[m:])
        return f0, torch.where(contiguous, f_next, f_extra)

    def render_rays(
        self,
        rays_o: Tensor,
        rays_d: Tensor,
        near: Tensor,
        far: Tensor,
        *,
        training: bool,
        background: Tensor | None = None,
        colors: bool = True,
    ) -> dict[str, Any]:
        """Render rays (N, 3) between near/far (N,) (see RadianceModel.render_rays; ``colors`` is not used); in
        training also returns 'reg' (Eikonal + curvature, weighted) and 'sharpness'."""
        cfg = self.config
        n = rays_o.shape[0]
        box = self.march_box if self.occupancy.is_warm() else self.aabb
        t_near, t_far = clip_to_box(rays_o, rays_d, near, far, box)
        s = self.sharpness

        def sigma_fn(ts: Tensor, te: Tensor, ri: Tensor) -> Tensor:
            f0, f1 = self.interval_sdf(rays_o, rays_d, ts, te, ri)
            return neus_tau(f0, f1, s) / (te - ts).clamp_min(1e-12)

        step_size = self.step_size
        if training and self.current_step() < cfg.occupancy_warmup:
            step_size *= cfg.warmup_step_scale
        with torch.no_grad():
            ts, te, ri = march(
                rays_o, rays_d, t_near, t_far, self.occupancy, step_size, cfg.max_samples,
                jitter=training, sigma_fn=sigma_fn if cfg.early_stop_transmittance > 0 else None,
                min_transmittance=cfg.early_stop_transmittance,
            )
        delta = (te - ts).clamp_min(1e-12)
        mid = 0.5 * (ts + te)
        f0, f1 = self.interval_sdf(rays_o, rays_d, ts, te, ri)
        weights, opacity, depth_sum = composite_packed(neus_tau(f0, f1, s) / delta, delta, mid, ri, n, fused=False)
        sel = (weights.detach() > cfg.color_min_weight).nonzero().squeeze(-1)
        x_c = rays_o[ri[sel]] + rays_d[ri[sel]] * mid[sel, None]
        rgb_s = self.radiance(x_c, rays_d[ri[sel]])
        bg = ray_background(cfg.background, self.bg_logit, background, n, rays_o, training)
        remainder = (1.0 - opacity).clamp_min(0.0)
        rgb = accumulate_packed(weights[sel], rgb_s, ri[sel], n) + remainder[:, None] * bg
        depth = depth_sum + remainder * far
        out: dict[str, Any] = {"rgb": rgb, "depth": depth, "opacity": opacity, "background": bg,
                               "num_samples": int(ri.shape[0])}
        if training:
            out["reg"] = self._regularizers(rays_o[ri] + rays_d[ri] * mid[:, None])
        return out

    def _regularizers(self, samples: Tensor) -> Tensor:
        """Eikonal + curvature on a random subset of ray samples (M, 3) and uniform points in the box."""
        cfg = self.config
        pick = samples.detach()
        if pick.shape[0] > cfg.eikonal_samples:
            pick = pick[torch.randint(0, pick.shape[0], (cfg.eikonal_samples,), device=pick.device)]
        box = self.aabb
        rand = box[0] + torch.rand(cfg.eikonal_points, 3, device=box.device) * (box[1] - box[0])
        grad, lap = sdf_fd_terms(self.sdf, torch.cat([pick, rand]), self.fd_step)
        reg = cfg.eikonal_weight * eikonal_loss(grad)
        if cfg.curvature_weight > 0:
            reg = reg + cfg.curvature_weight * lap.abs().mean()
        if cfg.init_prior_weight > 0 and self.prior_volume is not None:
            u = ((rand - box[0]) / (box[1] - box[0])).clamp(0.0, 1.0)
            reg = reg + cfg.init_prior_weight * ((self.sdf(rand) - self.initial_sdf(rand, u)) ** 2).mean()
        if cfg.boundary_weight > 0 and cfg.boundary_points > 0:
            on_faces = box_face_points(box, cfg.boundary_points)
            reg = reg + cfg.boundary_weight * boundary_loss(self.sdf(on_faces), cfg.boundary_margin_cells * self.voxel_size)
        return reg

    # ------------------------------------------------------------------ training hooks
    @torch.no_grad()
    def _shell(self, x: Tensor) -> Tensor:
        """1 where |f| is within the band that can carry rendering weight, else 0 (the occupancy's 'density')."""
        cell = float((self.occupancy.box[1] - self.occupancy.box[0]).max()) / self.occupancy.res
        band = 2.0 * math.sqrt(3.0) * cell + self.config.band_width / float(self.sharpness)
        return (self.sdf(x).abs() < band).float()

    def step_update(self, step: int) -> bool:
        """Set the step (coarse-to-fine levels), refresh the occupancy shell every ``occupancy_every`` steps."""
        cfg = self.config
        self.set_step(step)
        if step % cfg.occupancy_every == 0:
            warming = step < cfg.occupancy_warmup
            self.occupancy.update(self._shell, step, share=1 if warming else 4, jitter=not warming)
            if self.occupancy.is_warm():
                box = self.occupancy.occupied_aabb()
                if box is not None:
                    self.march_box.copy_(box)
        return False

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """SDF grids at lr * sdf_lr_scale, color grid (and learned background) at lr * grid_lr_scale,
        the MLPs at lr, log s at lr * sharpness_lr_scale."""
        cfg = self.config
        color = list(self.color_grid.parameters()) + ([self.bg_logit] if self.bg_logit is not None else [])
        mlps = list(self.color_mlp.parameters()) if self.color_mlp is not None else []
        if self.sdf_mlp is not None:
            mlps += list(self.sdf_mlp.parameters())
        groups = [
            {"params": list(self.sdf_grid.parameters()), "lr": lr * cfg.sdf_lr_scale},
            {"params": color, "lr": lr * cfg.grid_lr_scale},
            {"params": [self.log_s], "lr": lr * cfg.sharpness_lr_scale},
        ]
        if mlps:
            groups.append({"params": mlps, "lr": lr})
        return groups
