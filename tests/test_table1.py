"""scripts/table1.py (Table 1 of Sminchisescu & Triggs 2003) and scripts/jump_stages.py (the jump leaves that
survive each stage of a kjs step) on tiny settings: their core functions run and return sane counts."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def study():
    t1 = _script("table1")
    data = REPO / "ptrack" / "data"
    return t1, t1.Study(str(data / "10.asf"), str(data / "10_02.amc"), 0, 2.0, seed=0, iterations=10)


def test_table1_start_fits_the_noisy_2d(study):
    _, s = study
    assert torch.isfinite(s.q0).all()
    # the 2D is noisy: the true pose does not fit it exactly, the start (its polished minimum) fits it better
    assert s.cost_true > 1.0
    assert s.cost0 < s.cost_true


def test_table1_kjs_leaves_come_from_the_single_start_and_fit_the_2d(study):
    _, s = study
    q, keep = s.kjs("KJS1")
    assert q.shape == (64, s.q0.numel())  # 4^3 leaves of three 2-link chains
    # leaf 0: the start's own reading, its chain joints moved onto the rays of the noisy 2D (a few degrees)
    assert float((q[0] - s.q0).abs().max()) < 0.3
    assert 1 < int(keep.sum()) <= 64
    # flipped leaves reproject the 2D as the start does: their cost is the start's, not a random sample's
    dcost = s.cost(q[keep]) - s.cost0
    assert float(dcost.median()) < 1.0
    # and they are other poses: some lie far from the start
    assert float((q[keep] - s.q0).norm(dim=-1).max()) > 0.5
    _, keep_projected = s.kjs("KJS1 project")
    assert int(keep_projected.sum()) >= int(keep.sum())


def test_table1_scale_widens_the_css_samples(study):
    _, s = study
    gen = torch.Generator().manual_seed(0)
    spread = {}
    for scale in (1, 16):
        q = s.proposal("CSS", scale, "gaussian", 200, gen)
        spread[scale] = float((q - s.q0).norm(dim=-1).median())
    # std x sqrt(16) = 4 before the limits clamp the samples: a cap after scaling left it flat (x 1.07)
    assert spread[16] > 2.0 * spread[1]


def test_table1_stats_count_minima(study):
    t1, s = study
    gen = torch.Generator().manual_seed(1)
    q_raw = s.proposal("CSS", 4, "gaussian", 30, gen)
    c_raw = s.cost(q_raw)
    q_opt, info = s.polish(q_raw, 10)
    st = t1.Study.stats(s, q_raw, q_opt, c_raw, info.cost, 1.5)
    assert 0 <= st["minima3d"] <= 30 and 0 <= st["minima"] <= 30
    assert st["cost_raw"] > st["cost_opt"]  # optimisation lowers the cost


def test_jump_stages_counts_are_sane_and_match_the_tracker(cmu_file):
    js = _script("jump_stages")
    amc = cmu_file("35_01.amc")
    for mode in ("prune", "project"):
        # check=True: every step's modes equal track_step's, and the counted jumps equal _jump's
        c = js.run_clip(amc, mode, 3, 0, check=True, overrides=("kjs.samples=64",))
        j = c.jump
        assert c.steps == 2
        assert j["grown"] == 3 * j["jumped"] > 0  # 2-link chains: 3 flipped leaves per jumped sample
        assert j["grown"] == j["repeat"] + j["infeasible"] + j["tree"]  # every flipped leaf in one class
        assert j["repeat"] >= j["unobserved"] + j["missed"]
        assert j["tree"] >= j["ik"] >= j["limits"]
        assert j["kept"] == (j["limits"] if mode == "prune" else j["ik"])
        assert j["projected"] == (0 if mode == "prune" else j["ik"] - j["limits"])
        assert c.stage["budget"]["jump"] <= j["kept"]
        for origin in js.ORIGINS:
            assert c.stage["modes"][origin] <= c.stage["presel"][origin] <= c.stage["budget"][origin]
        assert 0 < sum(c.stage["modes"].values()) <= 8 * c.steps
        assert sum(c.stage["heaviest"].values()) == c.steps == sum(c.best.values())
