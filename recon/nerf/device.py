"""Choosing where tensors live: CUDA when present, else the CPU with one thread per physical core."""
from __future__ import annotations

import os
from pathlib import Path

import torch

__all__ = ["cpu_threads", "cuda_memory", "physical_cores", "select_device"]


def physical_cores() -> int:
    """Physical cores among the CPUs this process may run on (hyper-threads counted once).

    Reads Linux sysfs topology; falls back to the usable logical CPU count elsewhere.
    """
    try:
        cpus = sorted(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)
    cores = set()
    for cpu in cpus:
        topo = Path(f"/sys/devices/system/cpu/cpu{cpu}/topology")
        try:
            cores.add((topo.joinpath("physical_package_id").read_text().strip(), topo.joinpath("core_id").read_text().strip()))
        except OSError:
            return max(1, len(cpus))
    return max(1, len(cores))


def cpu_threads() -> int:
    """Threads for torch on the CPU: the physical cores, or fewer when OMP_NUM_THREADS asks for fewer.

    A scheduler that gives a process N CPUs says so through OMP_NUM_THREADS (Ray sets it to a task's CPUs), so
    several captures on one machine do not each spread over every core.
    """
    cores = physical_cores()
    try:
        limit = int(os.environ.get("OMP_NUM_THREADS", ""))
    except ValueError:
        return cores
    return max(1, min(cores, limit)) if limit > 0 else cores


def select_device(preference: str = "auto") -> torch.device:
    """The torch device to train and render on.

    preference: "auto" (CUDA when available, else CPU), "cpu", "cuda" or "cuda:K".
    On the CPU this also sets torch's intra-op threads to `cpu_threads()` (the physical cores): extra
    hyper-threads slow dense float math down. OpenMP's default wait policy stays: its threads spin briefly between
    torch's operations, which a training step's hundreds of small operations need (sleeping at once,
    OMP_WAIT_POLICY=PASSIVE, made a step markedly longer; on a machine shared with other work it still spares them).
    Raises ValueError for an unknown preference or when CUDA is requested but absent.
    """
    pref = preference.strip().lower()
    if pref == "auto":
        pref = "cuda" if torch.cuda.is_available() else "cpu"
    if pref.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device {preference!r} requested but CUDA is not available; use 'cpu' or 'auto'")
        dev = torch.device(pref)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {preference!r}: only {torch.cuda.device_count()} CUDA device(s) present")
        return dev
    if pref == "cpu":
        torch.set_num_threads(cpu_threads())
        return torch.device("cpu")
    raise ValueError(f"unknown device {preference!r}: use 'auto', 'cpu', 'cuda' or 'cuda:K'")


def cuda_memory(preference: str = "auto") -> tuple[int, str] | None:
    """(total memory in bytes, name) of the CUDA device `preference` names ("auto", "cuda" or "cuda:K"), or None
    when it names the CPU, CUDA is absent or K is out of range: what `recon.config.device_sizing` sizes a preset to."""
    pref = preference.strip().lower()
    if pref not in ("auto", "cuda") and not pref.startswith("cuda:"):
        return None
    if not torch.cuda.is_available():
        return None
    index = int(pref.partition(":")[2] or torch.cuda.current_device())
    if index >= torch.cuda.device_count():
        return None
    props = torch.cuda.get_device_properties(index)
    return int(props.total_memory), str(props.name)
