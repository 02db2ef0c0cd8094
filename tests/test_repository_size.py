"""The repository's files must fit what the GPU machine receives (the device tool sends the working tree, at most
64 MiB, and scripts/device_check.sh carries about 3 MB more of wheels and garment cache)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIMIT_MIB = 56.0


def test_tracked_files_fit_the_gpu_machines_budget():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout.split(b"\0")
    sizes = {n.decode(): (ROOT / n.decode()).stat().st_size for n in names if n and (ROOT / n.decode()).is_file()}
    total = sum(sizes.values()) / 2**20
    largest = sorted(sizes, key=sizes.get, reverse=True)[:5]
    assert total <= LIMIT_MIB, (f"tracked files take {total:.1f} MiB, over {LIMIT_MIB} MiB (the GPU machine takes 64 "
                                f"MiB with the carried wheels and cache); largest: {largest}")
