"""Chamfer / F-score against closed forms (concentric spheres) and Umeyama similarity on random transforms."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from recon.geometry.compare import chamfer_fscore, fit_sim3, fit_sim3_robust


def ball(radius: float) -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=5, radius=radius)


def test_identical_surfaces_score_perfectly():
    mesh = ball(1.0)
    out = chamfer_fscore((mesh.vertices, mesh.faces), mesh, n_samples=20_000, seed=3)
    spacing = np.sqrt(mesh.area / 20_000)
    assert out["chamfer_l1"] < spacing  # only the sampling floor
    assert out["fscore@0.01"] > 0.99 and out["gt_diagonal"] == pytest.approx(2 * np.sqrt(3), rel=0.01)


def test_concentric_spheres_distance_is_the_radius_gap():
    """Spheres of radius 1 and 1.02: the surface distance is 0.02 everywhere; between samples it is
    sqrt(0.02² + lateral²) with lateral below the sample spacing."""
    n = 50_000
    out = chamfer_fscore(ball(1.02), ball(1.0), n_samples=n)
    spacing = np.sqrt(4 * np.pi / n)
    assert 0.02 < out["chamfer_l1"] < np.hypot(0.02, spacing)
    assert out["accuracy"] == pytest.approx(out["completeness"], abs=0.003)
    assert out["chamfer_l1_rel"] == pytest.approx(out["chamfer_l1"] / out["gt_diagonal"])
    # τ = 0.01 · diag ≈ 0.035 > 0.02: all within; τ = 0.005 · diag ≈ 0.017 < 0.02: none within.
    assert out["precision@0.01"] > 0.99 and out["recall@0.01"] > 0.99
    assert out["fscore@0.005"] < 0.05


def test_partial_prediction_keeps_precision_but_loses_recall():
    gt = ball(1.0)
    half = gt.copy()
    half.update_faces(half.triangles_center[:, 2] > 0)
    out = chamfer_fscore(half.vertices[np.unique(half.faces)], gt, thresholds=(0.02,), n_samples=20_000)
    assert out["precision@0.02"] > 0.99  # a point cloud input is used as given
    # GT points within τ of the upper half: the half plus a band of height τ (area share τ / 2).
    tau = 0.02 * out["gt_diagonal"]
    assert out["recall@0.02"] == pytest.approx(0.5 + tau / 2, abs=0.01)
    with pytest.raises(ValueError, match="point cloud"):
        chamfer_fscore(np.zeros((0, 3)), gt)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), log_scale=st.floats(-3, 3), n=st.integers(3, 50))
def test_fit_sim3_recovers_random_similarity(seed, log_scale, n):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * rng.uniform(0.1, 10)
    rot = Rotation.random(random_state=seed).as_matrix()
    s, t = float(np.exp(log_scale)), rng.normal(size=3) * 100
    dst = s * src @ rot.T + t
    s_hat, r_hat, t_hat = fit_sim3(src, dst)
    assert s_hat == pytest.approx(s, rel=1e-6)
    np.testing.assert_allclose(r_hat, rot, atol=1e-6)
    np.testing.assert_allclose(s_hat * src @ r_hat.T + t_hat, dst, atol=1e-6 * (1 + np.abs(dst).max()))


def test_fit_sim3_noise_rigid_and_reflection():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(200, 3))
    rot = Rotation.from_euler("xyz", [0.3, -1.0, 2.0]).as_matrix()
    dst = 2.5 * src @ rot.T + [1.0, 2.0, 3.0] + rng.normal(scale=0.01, size=(200, 3))
    s, r, _ = fit_sim3(src, dst)
    assert s == pytest.approx(2.5, rel=0.01) and np.abs(r - rot).max() < 0.01
    s_rigid, _, _ = fit_sim3(src, dst, with_scale=False)
    assert s_rigid == 1.0
    mirrored = src * [-1.0, 1.0, 1.0]
    _, r_m, _ = fit_sim3(src, mirrored)
    assert np.linalg.det(r_m) == pytest.approx(1.0)  # best proper rotation, never a reflection


def test_fit_sim3_rejects_degenerate_input():
    line = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="collinear"):
        fit_sim3(line, line + 1)
    with pytest.raises(ValueError, match="N >= 3"):
        fit_sim3(np.zeros((2, 3)), np.zeros((2, 3)))


def test_fit_sim3_robust_leaves_out_a_misplaced_camera():
    """40 cameras on a ring, 0.004 of jitter (SfM's typical error), one moved 0.1: the plain fit is dragged by it,
    the robust one finds the true similarity and names exactly the moved camera; exact data loses no camera."""
    rng = np.random.default_rng(4)
    ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    src = np.stack([1.7 * np.cos(ang), 1.7 * np.sin(ang), rng.uniform(-0.3, 1.0, 40)], axis=1)
    rot = Rotation.from_euler("xyz", [0.2, 0.5, -1.3]).as_matrix()
    truth = 0.47 * src @ rot.T + [0.3, -0.2, 0.1]
    observed = truth + rng.normal(scale=0.004 / np.sqrt(3), size=truth.shape)
    observed[2] += [0.0, 0.05, -0.0866]
    s, r, t, used = fit_sim3_robust(src, observed)
    assert used.sum() == 39 and not used[2]
    s_plain, r_plain, t_plain = fit_sim3(src, observed)
    err = np.abs(s * src @ r.T + t - truth).max()
    err_plain = np.abs(s_plain * src @ r_plain.T + t_plain - truth).max()
    assert err < 0.003 and err_plain > 2.5 * err
    _, _, _, used_exact = fit_sim3_robust(src, truth)
    assert used_exact.all()
    # more than half the pairs are never left out, however they scatter
    wild = truth + rng.normal(scale=1.0, size=truth.shape) * (np.arange(40) % 2)[:, None]
    assert fit_sim3_robust(src, wild)[3].sum() >= 20


def test_scores_where_the_photos_can_see_leave_out_the_unseen_base_and_a_fill_behind_the_surface() -> None:
    """A cube seen from above all round: its base is unseen. A mesh without the base but with a square inside the
    cube (a fill no photo sees into) loses recall and precision over everything, and none where the photos see."""
    from recon.camera import look_at
    from recon.geometry.compare import seen_by

    gt = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    cameras = []
    for az in np.linspace(0, 2 * np.pi, 8, endpoint=False):
        eye = 4.0 * np.array([np.cos(az) * np.cos(0.5), np.sin(az) * np.cos(0.5), np.sin(0.5)])
        cameras.append((look_at(eye, np.zeros(3)), (300.0, 300.0, 160.0, 120.0), (240, 320)))
    open_box = gt.copy()
    open_box.update_faces(open_box.face_normals[:, 2] > -0.5)  # no base
    inside = trimesh.creation.box(extents=(0.6, 0.6, 1e-3))
    pred = trimesh.util.concatenate([open_box, inside])
    out = chamfer_fscore(pred, gt, thresholds=(0.01,), n_samples=40_000, cameras=cameras)
    assert 0.8 < out["gt_seen_share"] < 0.86  # the five faces the cameras see of six
    assert out["recall@0.01"] < 0.9 and out["recall_seen@0.01"] > 0.99
    assert out["precision@0.01"] < 0.9 and out["precision_seen@0.01"] > 0.99
    assert out["pred_observable_share"] < 0.9
    assert "fscore_seen@0.01" not in chamfer_fscore(pred, gt, thresholds=(0.01,), n_samples=2000)
    top = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, -0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.9]])
    on_surface, observable = seen_by(gt, top, cameras, 0.01)
    assert on_surface.tolist() == [True, False, False, False]  # the top; not the base, the centre, the air
    assert observable.tolist() == [True, False, False, True]
