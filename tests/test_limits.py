"""Tests for ptrack.body.limits: data-derived joint limits, their file, periodic angles, and the real-data
claims they rest on (the CMU ASF limits are broken by the ground truth; the shipped ones are not)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.limits import arc_bounds, data_limits_path, read_limits_file, wrap_to_limits
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.errors import InputError
from ptrack.pipeline import metrics as M
from ptrack.pipeline.config import ModelConfig, load_config

REPO = Path(__file__).resolve().parents[1]
ASF = REPO / "ptrack" / "data" / "10.asf"
DEG = math.pi / 180.0
DEV_CLIPS = [
    ln.split("#")[0].strip().split("/")[-1]
    for ln in (REPO / "configs" / "clips" / "dev.txt").read_text().splitlines()
    if ln.split("#")[0].strip()
]
GOLF_CLIPS = [f"64_0{i}.amc" for i in (1, 2, 4, 5, 6, 8, 9)]


# ---------------------------------------------------------------- arcs


def test_arc_bounds_plain_range_with_margin():
    lo, hi = arc_bounds(np.radians([-30.0, 10.0, 45.0]), margin=5 * DEG)
    assert lo == pytest.approx(-35 * DEG) and hi == pytest.approx(50 * DEG)


def test_arc_bounds_across_the_seam():
    """359 and -1 degrees are one angle: the arc across +-180 is short, not nearly the whole circle."""
    lo, hi = arc_bounds(np.radians([170.0, 179.0, -179.0, -170.0, 359.0 - 360.0 + 180.0]), margin=0.0)
    assert hi - lo == pytest.approx(20 * DEG)
    assert lo == pytest.approx(170 * DEG) and hi == pytest.approx(190 * DEG)


def test_arc_bounds_prefers_the_representative_nearest_zero():
    lo, hi = arc_bounds(np.radians([350.0, 355.0, 365.0]), margin=0.0)
    assert lo == pytest.approx(-10 * DEG) and hi == pytest.approx(5 * DEG)


def test_arc_bounds_whole_circle_is_unlimited():
    assert arc_bounds(np.radians(np.arange(0, 360, 15.0)), margin=8 * DEG) == (-math.inf, math.inf)
    lo, hi = arc_bounds(np.radians(np.arange(0, 360, 15.0)), margin=0.0)  # one 15-degree gap left
    assert hi - lo == pytest.approx(345 * DEG)
    assert arc_bounds(np.radians([0.0, 170.0]), margin=100 * DEG) == (-math.inf, math.inf)
    lo, hi = arc_bounds(np.zeros(5), margin=10 * DEG)  # a dof the data never moves
    assert lo == pytest.approx(-10 * DEG) and hi == pytest.approx(10 * DEG)
    with pytest.raises(InputError):
        arc_bounds(np.zeros(0), 0.0)


def test_wrap_to_limits_keeps_the_pose():
    sk = Skeleton.from_asf(ASF).with_limits("data")
    gen = torch.Generator().manual_seed(0)
    lower, upper = sk.limits(dtype=torch.float64)
    angular = torch.as_tensor(sk.angular_dofs())
    q = torch.rand(20, sk.num_dofs, generator=gen, dtype=torch.float64)
    q = torch.where(torch.isfinite(lower), lower + q * (upper.clamp(max=1e3) - lower), q)  # inside the limits
    shifted = q + 2 * math.pi * torch.randint(-2, 3, q.shape, generator=gen).double() * angular
    wrapped = wrap_to_limits(shifted, lower, upper, angular)
    limited = angular & torch.isfinite(lower)
    torch.testing.assert_close(wrapped[:, limited], q[:, limited])
    torch.testing.assert_close(sk.forward_kinematics(wrapped), sk.forward_kinematics(shifted))
    assert torch.equal(wrapped[:, ~angular], shifted[:, ~angular])  # translations untouched


# ---------------------------------------------------------------- sources and the file


def test_sources():
    asf = Skeleton.from_asf(ASF)
    assert asf.with_limits("asf") is asf
    none = asf.with_limits("none")
    assert np.isinf(none.lower).all() and np.isinf(none.upper).all()
    data = asf.with_limits("data")
    table = read_limits_file()
    i = data.dof_names.index("lhumerus.rx")
    assert (data.lower[i], data.upper[i]) == table["lhumerus.rx"]
    root = [k for k, n in enumerate(data.dof_names) if n.startswith("root.")]
    assert np.isinf(data.lower[root]).all()  # the file does not limit the root
    with pytest.raises(InputError, match="one of data, asf, none"):
        asf.with_limits("tight")


def test_reduced_model_keeps_the_chosen_limits():
    sk = Skeleton.from_asf(ASF).with_limits("data").freeze(list(ModelConfig().freeze))
    table = read_limits_file()
    for n, lo, hi in zip(sk.dof_names, sk.lower, sk.upper):
        if n in table:
            assert (lo, hi) == table[n]


def test_dofs_missing_from_the_file_keep_their_own_limits(tmp_path, caplog):
    p = tmp_path / "limits.json"
    p.write_text(json.dumps({"limits_deg": {"ltibia.rx": [0, 90], "nosuch.rx": [0, 1]}}))
    sk = Skeleton.from_asf(ASF)
    lim = sk.with_limits("data", p)
    i = sk.dof_names.index("ltibia.rx")
    assert lim.upper[i] == pytest.approx(90 * DEG)
    j = sk.dof_names.index("lfemur.rx")
    assert (lim.lower[j], lim.upper[j]) == (sk.lower[j], sk.upper[j])
    p.write_text(json.dumps({"limits_deg": {"nosuch.rx": [0, 1]}}))
    with caplog.at_level(logging.WARNING):
        sk.with_limits("data", p)
    assert "keeps its own limits" in caplog.text


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("not json", "must be JSON"),
        ('{"other": 1}', "limits_deg"),
        ('{"limits_deg": {"a.rx": [3, 1]}}', "'a.rx'"),
        ('{"limits_deg": {"a.rx": "wide"}}', "'a.rx'"),
    ],
)
def test_malformed_limits_file(tmp_path, text, fragment):
    p = tmp_path / "bad.json"
    p.write_text(text)
    with pytest.raises(InputError, match=fragment):
        read_limits_file(p)
    with pytest.raises(FileNotFoundError, match="not found"):
        read_limits_file(tmp_path / "none.json")


def test_shipped_file_states_its_provenance():
    doc = json.loads(data_limits_path().read_text())
    assert doc["made_by"] == "scripts/make_limits.py"
    assert doc["margin_deg"] > 0 and doc["frames"] > 10000
    assert set(doc["clips"]) >= {c[:-4] for c in DEV_CLIPS + GOLF_CLIPS}
    assert len(doc["limits_deg"]) == 56 and not any(k.startswith("root") for k in doc["limits_deg"])


def test_config_key():
    assert load_config(REPO / "configs" / "demo.yaml").model.limits == "data"
    with pytest.raises(InputError, match=r"model\.limits"):
        load_config(REPO / "configs" / "demo.yaml", ["model.limits=loose"])


# ---------------------------------------------------------------- real data


def _gt_violation(cmu_file, clip: str, source: str) -> float:
    subject = clip.split("_")[0]
    full = Skeleton.from_asf(cmu_file(f"{subject}.asf")).with_limits(source)
    model = full.freeze(list(ModelConfig().freeze))
    q = model.reduce(load_amc(cmu_file(clip), full).q, full)
    lower, upper = model.limits(dtype=torch.float64)
    return float(M.joint_limit_violations(q, lower, upper, angular=model.angular_dofs()).fraction)


@pytest.mark.parametrize("clip", DEV_CLIPS + GOLF_CLIPS)
def test_ground_truth_obeys_the_default_limits(cmu_file, clip):
    """The issue's target: the truth breaks the default limits in under 0.5% of dof-frames."""
    assert _gt_violation(cmu_file, clip, "data") < 0.005


def test_ground_truth_breaks_the_asf_limits(cmu_file):
    """Why the data limits exist: CMU's own ASF limits are broken by the motions captured with them."""
    rates = [_gt_violation(cmu_file, c, "asf") for c in ("64_01.amc", "02_01.amc", "124_01.amc")]
    assert min(rates) > 0.02


def test_shipped_file_is_what_the_script_makes(cmu_dir):
    """Regenerating the bounds from ../shared gives the shipped numbers (the file is not hand-edited)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_limits", REPO / "scripts" / "make_limits.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    doc = json.loads(data_limits_path().read_text())
    sk, clips = mod.load_clips(cmu_dir)
    lower, upper = mod.bounds_from([q for _, q in clips.values()], sk, math.radians(doc["margin_deg"]))
    for i, name in enumerate(sk.dof_names):
        if name.startswith("root."):
            continue
        shipped = doc["limits_deg"][name]
        if shipped is None:
            assert math.isinf(lower[i])
        else:
            assert shipped == pytest.approx([math.degrees(lower[i]), math.degrees(upper[i])], abs=1e-3)
