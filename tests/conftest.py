"""Shared fixtures: the real CMU mocap folder (../shared/data/cmu relative to the repo root).

Tests that take `cmu_dir` (or any fixture built on it) are skipped when the folder is absent.
`cmu_file("64_01.amc")` / `cmu_file("64.asf")` gives a file of the `subjects/NN/` layout.
"""

from __future__ import annotations

from pathlib import Path

import pytest

CMU_DIR = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "cmu"


@pytest.fixture(scope="session")
def cmu_dir() -> Path:
    """The CMU data folder (contains `subjects/`); skips the test if it is absent."""
    d = CMU_DIR.resolve()
    if not (d / "subjects").is_dir():
        pytest.skip(f"CMU mocap data not found at {d} (expected ../shared/data/cmu next to the repo)")
    return d


@pytest.fixture(scope="session")
def cmu_file(cmu_dir):
    """`cmu_file("64_01.amc") -> Path` of `subjects/64/64_01.amc`; skips if that file is absent."""

    def get(name: str) -> Path:
        subject = name.split("_")[0].split(".")[0]
        p = cmu_dir / "subjects" / subject / name
        if not p.is_file():
            pytest.skip(f"CMU file {name} not found at {p}")
        return p

    return get


@pytest.fixture(scope="session")
def asf_64(cmu_file) -> Path:
    """Skeleton of CMU subject 64 (golf)."""
    return cmu_file("64.asf")


@pytest.fixture(scope="session")
def amc_64_01(cmu_file) -> Path:
    """CMU 64_01, a golf swing: 448 frames at 120 fps."""
    return cmu_file("64_01.amc")
