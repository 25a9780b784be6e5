"""`--preset classic` without a GPU takes the preset's [no_gpu] settings (said in the train reasons); with a GPU,
or with --set, the values are the preset's own or the user's."""
from __future__ import annotations

import tomllib

from recon.config import PIPELINES_DIR, load_config


def _no_gpu_table() -> dict:
    return tomllib.loads((PIPELINES_DIR / "classic.toml").read_text())["no_gpu"]


def test_classic_on_cpu_uses_the_no_gpu_settings() -> None:
    table = _no_gpu_table()
    cfg = load_config("classic", ["train.device=cpu"])
    assert cfg.train.max_side == table["train"]["max_side"] == 100
    assert (cfg.train.classic.n_coarse, cfg.train.classic.n_fine) == (32, 32)
    assert cfg.train.batch_rays == table["train"]["batch_rays"]
    assert cfg.train.budget == table["train"]["budget"]
    assert cfg.mesh.max_resolution == table["mesh"]["max_resolution"]
    assert cfg.train.classic.depth == 8 and cfg.train.classic.width == 256  # still the classic network
    assert "no GPU" in cfg.train.adjusted and "train.classic.n_coarse=32" in cfg.train.adjusted


def test_classic_on_gpu_keeps_the_preset_and_set_wins_on_cpu() -> None:
    gpu = load_config("classic", ["train.device=cuda"])
    assert (gpu.train.max_side, gpu.train.classic.n_coarse, gpu.train.classic.n_fine) == (400, 64, 128)
    assert gpu.train.adjusted == ""
    cpu = load_config("classic", ["train.device=cpu", "train.max_side=200", "train.classic.n_fine=0"])
    assert (cpu.train.max_side, cpu.train.classic.n_fine, cpu.train.classic.n_coarse) == (200, 0, 32)


def test_other_presets_are_unchanged_on_cpu() -> None:
    cpu = load_config("fast", ["train.device=cpu"])
    gpu = load_config("fast", ["train.device=cuda", "train.device_sizing=off"])  # sizing: tests/test_devices.py
    gpu.train.device, gpu.train.device_sizing = "cpu", "auto"
    assert cpu == gpu and cpu.train.adjusted == ""


def test_train_stage_states_the_cpu_settings() -> None:
    import numpy as np

    from recon.plans.training import model_spec

    cfg = load_config("classic", ["train.device=cpu"]).train

    class _Scene:
        aabb = np.array([[-1.0] * 3, [1.0] * 3])
        capture = "object"

    kind, kwargs, _, reasons = model_spec(cfg, _Scene(), [])
    assert kind == "classic" and (kwargs["n_coarse"], kwargs["n_fine"]) == (32, 32)
    assert "32+32 samples" in reasons[0]
    assert cfg.adjusted.startswith("no GPU (train.device=cpu)")  # plan_training puts it first among the reasons
