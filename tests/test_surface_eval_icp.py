"""ICP refinement of the evaluation's alignment (SfM scale error): recovers a known similarity."""
from __future__ import annotations

import math

import numpy as np
import trimesh

from recon.evaluation.mesh_eval import format_comparison
from recon.geometry.compare import icp_sim3, sample_surface


def _rot_z(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_icp_undoes_a_known_small_similarity_between_different_samples() -> None:
    shape = trimesh.creation.icosphere(subdivisions=4)
    shape.apply_scale([1.0, 0.6, 0.35])
    shape.apply_translation([0.2, -0.1, 0.05])
    truth = sample_surface(shape, 20_000, seed=0)
    ours = sample_surface(shape, 20_000, seed=1)  # other points on the same surface
    s0, r0, t0 = 1.02, _rot_z(1.5), np.array([0.01, -0.02, 0.005])  # SfM-like: 2 % too large, turned, shifted
    moved = s0 * ours @ r0.T + t0
    s, rot, t = icp_sim3(moved, truth)
    back = s * moved @ rot.T + t
    assert abs(s * s0 - 1.0) < 2e-3  # the scale error is undone
    assert np.abs(back - ours).max() < 0.01  # every point returns to where it was (sample spacing ~0.01)
    assert np.abs(s * moved @ rot.T + t - moved).max() > 0.02  # and it did move them


def test_icp_leaves_an_exact_match_alone() -> None:
    pts = sample_surface(trimesh.creation.box(extents=(1.0, 0.5, 0.3)), 5_000, seed=0)
    s, rot, t = icp_sim3(pts, pts)
    assert abs(s - 1.0) < 1e-9 and np.allclose(rot, np.eye(3), atol=1e-9) and np.linalg.norm(t) < 1e-9


def test_report_prints_the_refined_numbers_beside_the_camera_aligned_ones() -> None:
    result = {"mesh": "m.ply", "gt_mesh": "gt.ply", "alignment": {"method": "Sim(3) fit"}, "thresholds": [0.01],
              "chamfer_l1": 0.01, "chamfer_l1_rel": 0.004, "gt_diagonal": 2.5, "accuracy": 0.01, "completeness": 0.01,
              "precision@0.01": 0.9, "recall@0.01": 0.9, "fscore@0.01": 0.9,
              "icp_refined": {"scale": 0.9871, "rotation_deg": 0.066, "translation_rel": 0.0033, "chamfer_l1_rel": 0.0027,
                              "normal_consistency": 0.99, "fscore@0.01": 0.971}}
    text = format_comparison(result)
    assert "scale 0.9871" in text and "Chamfer-L1 0.270%" in text and "F@1.0% 0.971" in text
