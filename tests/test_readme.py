"""The README's Python API runs as written, from the repository root, and `ptrack.estimate` returns what
`ptrack run` writes for the same config."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch

import ptrack
from ptrack.pipeline.run import execute

REPO = Path(__file__).resolve().parents[1]


def _python_blocks(section: str) -> list[str]:
    """The ```python blocks of the README section headed `section` (up to the next heading of any level)."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    start = text.index(f"\n{section}\n")
    end = re.search(r"\n#+ ", text[start + 1 :])
    body = text[start : start + 1 + end.start()] if end else text[start:]
    return re.findall(r"```python\n(.*?)```", body, flags=re.S)


def test_python_api_blocks_run(monkeypatch, cmu_dir):
    """Each block of "### Python API" runs in a fresh namespace from the repository root (the first reads
    ../shared/data/cmu, hence `cmu_dir`); the tracker's block gives the shapes its comments state."""
    blocks = _python_blocks("### Python API")
    assert len(blocks) >= 2
    monkeypatch.chdir(REPO)
    spaces = []
    for code in blocks:
        space: dict = {}
        exec(compile(code, "README.md", "exec"), space)  # the README's own example
        spaces.append(space)
    tracker = next(s for s in spaces if "est" in s)
    est, prep = tracker["est"], tracker["prep"]
    t, d = est.q.shape
    assert t == 15 and d == prep.problem.skeleton.num_dofs
    j = prep.problem.skeleton.num_joints
    assert tracker["joints"].shape == (t, j, 3) and tracker["truth"].shape == (t, j, 3)
    assert tracker["modes"].shape == (t, 8, j, 3)
    torch.testing.assert_close(est.hypothesis_weights.sum(-1), torch.ones(t, dtype=est.q.dtype))
    err_mm = 1000 * (tracker["joints"] - tracker["truth"]).norm(dim=-1).mean()
    assert torch.isfinite(err_mm) and err_mm < 150  # a tracked body, not a stray pose


@pytest.mark.parametrize("method", ["kjs", "frame"])
def test_estimate_is_what_run_writes(tmp_path, method):
    """`ptrack.estimate(cfg)` gives the trajectory and hypotheses `execute(cfg)` writes to result.npz (the same
    two seeds), and writes nothing itself."""
    over = ["data.stop=28", "progress=false", f"method={method}", "kjs.samples=64", "frame.iterations=5"]
    cfg = ptrack.load_config(REPO / "configs" / "kjs.yaml", [*over, f"out_dir={tmp_path / 'run'}"])
    out = execute(cfg)
    before = sorted(tmp_path.rglob("*"))
    prep, est = ptrack.estimate(cfg)
    assert sorted(tmp_path.rglob("*")) == before
    saved = np.load(out / "result.npz")
    np.testing.assert_array_equal(saved["q"], est.q.numpy())
    np.testing.assert_array_equal(saved["joints"], est.joints.numpy())
    if method == "kjs":
        np.testing.assert_array_equal(saved["hypothesis_weights"], est.hypothesis_weights.numpy())
    else:
        assert est.hypotheses is None and "hypotheses" not in saved
    assert prep.gt_joints is not None and prep.gt_joints.shape == est.joints.shape
