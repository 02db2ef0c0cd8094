"""Load a file of ``bench/`` or ``scripts/`` as a module: they are scripts run by path, not a package."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent


def load_script(relative: str) -> ModuleType:
    """A fresh module of ``ROOT / relative`` (e.g. ``"bench/layer_sink.py"``), registered in ``sys.modules`` under
    ``script_<stem>`` (dataclasses resolve their annotations through it)."""
    path = ROOT / relative
    spec = importlib.util.spec_from_file_location(f"script_{path.stem}", path)
    assert spec is not None and spec.loader is not None, path
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
