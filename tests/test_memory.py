"""ptrack.pipeline.memory: the estimate of a run's peak memory, and the refusal of runs that would not fit."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from cli_errors import fail

import ptrack.pipeline.memory as memory
from ptrack.pipeline.config import load_config
from ptrack.pipeline.memory import available_bytes, estimate_bytes

ROOT = Path(__file__).resolve().parents[1]
KJS, BATCH, GOLF = (str(ROOT / "configs" / n) for n in ("kjs.yaml", "batch.yaml", "golf.yaml"))
SHAPES = {"frames": 148, "joints": 31, "dofs": 50, "keypoints": 17}  # the bundled clip at stride 4


def test_available_bytes_is_positive_or_unknown():
    have = available_bytes()
    assert have is None or (isinstance(have, int) and have > 0)


def test_cgroup_limit_caps_available(tmp_path, monkeypatch):
    """memory.max less memory.current wins where it is below MemAvailable."""
    real = memory.Path

    def fake(path):
        if str(path) == "/sys/fs/cgroup":
            (tmp_path / "memory.max").write_text(f"{600 << 20}\n")
            (tmp_path / "memory.current").write_text(f"{100 << 20}\n")
            return tmp_path
        return real(path)

    monkeypatch.setattr(memory, "Path", fake)
    have = available_bytes()
    assert have is not None and have <= 500 << 20


def test_estimate_grows_with_the_settings():
    def need(path, *overrides, **shapes):
        return estimate_bytes(load_config(path, list(overrides)), **{**SHAPES, **shapes})

    base = need(KJS)
    assert need(KJS, "kjs.samples=1024") > base
    assert need(KJS, "kjs.modes=64") > base
    assert need(KJS, frames=1000) > base
    assert need(KJS, "kjs.init=tree", "kjs.init_fits=64") > need(KJS, "kjs.init=tree") > base
    assert need(KJS, "dtype=float64") > base
    assert need(BATCH, frames=1000) > need(BATCH) > need(BATCH, "batch.uncertainty=laplace", "batch.flip_restarts=0")
    golf = {"silhouette_samples": 96}
    assert need(GOLF, "pca.init_yaws=64", **golf) > need(GOLF, **golf) > need(GOLF)
    assert need(GOLF, "pca.window=10", **golf) > need(GOLF, **golf)
    # the default settings of every method fit comfortably on a laptop
    for path, method in [(KJS, "frame"), (KJS, "kjs"), (KJS, "css"), (KJS, "ss"), (BATCH, "batch"), (GOLF, "pca")]:
        assert need(path, f"method={method}", **golf) < 4 << 30, method


def test_absurd_kjs_is_refused_at_once(tmp_path):
    """The issue's command: one error line, exit 2, nothing written (it used to grow past 10 GB)."""
    out = tmp_path / "run"
    args = [KJS, "kjs.modes=100000000", "kjs.samples=100000000", f"out_dir={out}", "data.stop=60"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    p = subprocess.run(
        [sys.executable, "-m", "ptrack.cli", "run", *args], capture_output=True, text=True, env=env, timeout=300
    )
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: method kjs"), p.stderr
    assert "kjs.samples=100000000" in lines[0] and "GiB available" in lines[0]
    assert not out.exists() and not list(tmp_path.iterdir())


def test_absurd_pca_is_refused(capsys, tmp_path, cmu_file):
    cmu_file("64_01.amc")  # golf.yaml's swing
    out = tmp_path / "run"
    argv = ["run", GOLF, "pca.init_yaws=100000000", "data.stop=60", f"out_dir={out}"]
    fail(capsys, out, argv, "method pca", "pca.init_yaws=100000000", "GiB available", "lower pca.init_yaws")


def test_refusal_forced_by_little_memory(capsys, tmp_path, monkeypatch):
    """Settings that fit a laptop are refused on a machine with 300 MiB available; the default kjs and batch
    runs pass the check with 4 GiB."""
    out = tmp_path / "run"
    monkeypatch.setattr(memory, "available_bytes", lambda: 300 << 20)
    fail(capsys, out, ["run", KJS, "data.stop=60", f"out_dir={out}"], "method kjs", "kjs.samples=256")
    fail(capsys, out, ["run", BATCH, "data.stop=60", f"out_dir={out}"], "method batch", "data.stop")

    from ptrack.pipeline.run import prepare

    monkeypatch.setattr(memory, "available_bytes", lambda: 4 << 30)
    for path in (KJS, BATCH):
        cfg = load_config(path, ["data.stop=60"])
        memory.check_memory(cfg, prepare(cfg).problem)  # raises on refusal


def test_no_check_where_memory_is_unknown(monkeypatch):
    from ptrack.pipeline.run import prepare

    monkeypatch.setattr(memory, "available_bytes", lambda: None)
    cfg = load_config(KJS, ["data.stop=20", "kjs.samples=100000000", "kjs.modes=100000000"])
    memory.check_memory(cfg, prepare(cfg).problem)
