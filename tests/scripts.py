"""Load a script from benchmarks/ or fixtures/ (folders that are not packages) by path, once, for its tests."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]


def load_script(path: str, name: str) -> ModuleType:
    """The module at REPO/path (e.g. "benchmarks/auto_mask_seeds.py"), imported as `name` the first time."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]
