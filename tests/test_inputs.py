"""Tests of what ptrack takes in and says back (issue 38): numbers as people write them (overrides, config
files, config.yaml round trip), warnings on observations no pose explains or that hold few keypoints, the
package's own data found from any working directory, and progress lines off a terminal."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ptrack.errors import InputError
from ptrack.pipeline.config import dump_yaml, load_config, load_yaml

REPO = Path(__file__).resolve().parents[1]
ASF = REPO / "ptrack" / "data" / "10.asf"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
DATA = [f"data.asf={ASF}", f"data.amc={AMC}"]

# ---------------------------------------------------------------- numbers as people write them

NUMBERS = [
    ("1e9", 1e9),
    ("1E-6", 1e-6),
    ("1.0e+9", 1e9),
    (".5", 0.5),
    ("5.", 5.0),
    ("-1e-3", -1e-3),
    ("+2", 2.0),
    ("+.5e3", 500.0),
    ("2", 2.0),
]


@pytest.mark.parametrize(("text", "value"), NUMBERS)
def test_override_numbers_as_written(text, value):
    cfg = load_config(None, [*DATA, f"camera.azimuth_deg={text}", f"batch.tol={text.lstrip('-')}"])
    assert cfg.camera.azimuth_deg == value and isinstance(cfg.camera.azimuth_deg, float)
    assert cfg.batch.tol == abs(value)


@pytest.mark.parametrize(("text", "value"), NUMBERS)
def test_config_file_numbers_as_written(tmp_path, text, value):
    p = tmp_path / "c.yaml"
    p.write_text(f"camera:\n  azimuth_deg: {text}\nobservations:\n  noise_px: {text.lstrip('-')}\n", encoding="utf-8")
    cfg = load_config(p, DATA)
    assert cfg.camera.azimuth_deg == value
    assert cfg.observations.noise_px == abs(value)


def test_issue_overrides_accepted():
    cfg = load_config(None, [*DATA, "observations.noise_px=1e9", "batch.tol=1e-6"])
    assert cfg.observations.noise_px == 1e9 and cfg.batch.tol == 1e-6


@pytest.mark.parametrize("text", ["nan", ".nan", "NaN", "inf", ".inf", "-inf", "Infinity"])
def test_non_finite_refused(text):
    with pytest.raises(InputError, match=r"config key 'observations.noise_px' must be a finite number, got"):
        load_config(None, [*DATA, f"observations.noise_px={text}"])
    with pytest.raises(InputError, match=r"'batch.accel_sigma' must be a finite number"):
        load_config(None, [*DATA, f"batch.accel_sigma={text}"])  # float | None


def test_non_finite_in_a_config_file_is_one_cli_line(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text(f"data:\n  asf: {ASF}\n  amc: {AMC}\ncamera:\n  focal_px: .nan\n", encoding="utf-8")
    r = subprocess.run(
        [sys.executable, "-m", "ptrack.cli", "run", str(p), f"out_dir={tmp_path / 'out'}"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert r.returncode == 2
    assert r.stderr == "ptrack: error: config key 'camera.focal_px' must be a finite number, got nan\n"
    assert not (tmp_path / "out").exists()


def test_strings_that_look_like_numbers_round_trip(tmp_path):
    """config.yaml quotes a string the loader would read as a number, and writes numbers it reads back."""
    cfg = load_config(None, [*DATA, "name=x", "observations.noise_px=1e-7"])
    import dataclasses

    cfg = dataclasses.replace(cfg, name="1e9", model=dataclasses.replace(cfg.model, keypoints={"inf": "root"}))
    text = dump_yaml(cfg)
    assert load_yaml(text)["name"] == "1e9"
    p = tmp_path / "config.yaml"
    p.write_text(text, encoding="utf-8")
    again = load_config(p, run=False)
    assert again == cfg


def test_keyframe_file_numbers_as_written(tmp_path):
    from ptrack.body.skeleton import Skeleton
    from ptrack.pipeline.keyframes import read_keyframes

    sk = Skeleton.from_asf(ASF)
    p = tmp_path / "k.yaml"
    p.write_text("keyframes:\n  - frame: 0\n    dofs: {lfemur.rx: 1e1, rfemur.rx: -2.5E+1}\n", encoding="utf-8")
    kf, _ = read_keyframes(p, sk, 5, 2.0, 0.02)
    assert kf is not None
    i, j = sk.dof_names.index("lfemur.rx"), sk.dof_names.index("rfemur.rx")
    assert float(kf.q[0, i]) == pytest.approx(math.radians(10.0))
    assert float(kf.q[0, j]) == pytest.approx(math.radians(-25.0))


# ---------------------------------------------------------------- package data found by the package

# Python in a folder whose `ptrack/` subfolder (a clone's root: no __init__.py) shadows the name ptrack, with the
# package itself imported through a finder after the path's own, as setuptools' editable installs do: `ptrack` is
# then the subfolder's namespace package while its modules load from the package. Prints the limits, pose prior
# and smoothing tables it reads.
_SHADOWED = r"""
import importlib.abc, importlib.machinery, importlib.util, json, sys
from pathlib import Path

PKG = Path(sys.argv[1])


class Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if not name.startswith("ptrack."):
            return None
        p = PKG.joinpath(*name.split(".")[1:])
        if (p / "__init__.py").is_file():
            return importlib.util.spec_from_file_location(name, p / "__init__.py", submodule_search_locations=[str(p)])
        if p.with_suffix(".py").is_file():
            return importlib.util.spec_from_file_location(name, p.with_suffix(".py"))
        return None


at = sys.meta_path.index(importlib.machinery.PathFinder)
sys.meta_path.insert(at + 1, Finder())
import ptrack

assert getattr(ptrack, "__file__", None) is None, ptrack.__file__  # the namespace package of ./ptrack
from ptrack.body.pose_prior import read_pose_prior, smoothing_prior
from ptrack.body.skeleton import Skeleton

sk = Skeleton.from_asf(PKG / "data" / "10.asf").with_limits("data")
print(json.dumps({"lower": sk.lower.tolist(), "prior": read_pose_prior(), "smooth": smoothing_prior("cmu-train")}))
"""


def test_package_data_found_from_a_shadowing_folder(tmp_path):
    from ptrack.body.pose_prior import read_pose_prior, smoothing_prior
    from ptrack.body.skeleton import Skeleton

    (tmp_path / "ptrack" / "data").mkdir(parents=True)
    (tmp_path / "ptrack" / "data" / "cmu_limits.json").write_text('{"limits_deg": {}}', encoding="utf-8")
    (tmp_path / "data").mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run(
        [sys.executable, "-c", _SHADOWED, str(REPO / "ptrack")], cwd=tmp_path, capture_output=True, text=True, env=env
    )
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)
    assert got["lower"] == Skeleton.from_asf(ASF).with_limits("data").lower.tolist()
    assert got["prior"] == {k: list(v) for k, v in read_pose_prior().items()}
    assert got["smooth"] == smoothing_prior("cmu-train")


# ---------------------------------------------------------------- progress lines off a terminal


def test_progress_lines_throttled_by_the_clock(caplog):
    from ptrack.pipeline.run import progress_lines

    ticks = iter([0.0, 1.0, 9.0, 10.5, 12.0, 20.0, 30.0, 31.0, 50.0, 51.0, 52.0])  # start, then one per item
    items = list(range(10))
    with caplog.at_level("INFO", logger="ptrack.pipeline.run.progress"):
        got = list(progress_lines(items, "kjs", every=15.0, first=10.0, clock=lambda: next(ticks)))
    assert got == items
    # item 2 is taken at 10.5 s (2 done: 2 / 10.5 s), then none before 10.5 + 15 = 25.5 s: item 5 at 30 s
    # (5 / 30 s), then item 7 at 50 s (>= 45 s)
    assert [r.getMessage() for r in caplog.records] == [
        "kjs: frame 2/10 (20%), 0.19 frames/s, about 42 s left",
        "kjs: frame 5/10 (50%), 0.167 frames/s, about 30 s left",
        "kjs: frame 7/10 (70%), 0.14 frames/s, about 21 s left",
    ]
    assert {r.levelname for r in caplog.records} == {"INFO"}


def test_progress_lines_without_a_total(caplog):
    from ptrack.pipeline.run import progress_lines

    ticks = iter([0.0, 0.0, 20.0, 21.0])
    with caplog.at_level("INFO", logger="ptrack.pipeline.run.progress"):
        assert list(progress_lines(iter("abc"), "pca", every=15.0, first=10.0, clock=lambda: next(ticks))) == [
            "a",
            "b",
            "c",
        ]
    assert [r.getMessage() for r in caplog.records] == ["pca: frame 1, 0.05 frames/s"]


def test_progress_lines_leave_the_result_unchanged(monkeypatch, caplog):
    from ptrack.pipeline.run import estimate

    cfg = load_config(REPO / "configs" / "demo.yaml", ["data.stop=24"])
    _, quiet = estimate(cfg, progress=False)
    monkeypatch.setenv("PTRACK_PROGRESS_SECONDS", "0")
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    with caplog.at_level("INFO", logger="ptrack.pipeline.run.progress"):
        _, shown = estimate(cfg, progress=True)
    assert [r.getMessage().split(",")[0] for r in caplog.records] == [
        f"frame: frame {i}/6 ({i / 6:.0%})" for i in range(1, 6)
    ]
    assert (shown.q == quiet.q).all()  # the same computation on the same thread: bit for bit


def test_cli_run_logs_progress_lines_off_a_terminal(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO), "PTRACK_PROGRESS_SECONDS": "0"}
    cmd = [sys.executable, "-m", "ptrack.cli", "run", str(REPO / "configs" / "demo.yaml"), "data.stop=24"]
    r = subprocess.run([*cmd, f"out_dir={tmp_path / 'run'}"], capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert len(lines) == 5 and lines[0].startswith("ptrack: INFO: frame: frame 1/6 (17%), "), r.stderr
    assert lines[-1].startswith("ptrack: INFO: frame: frame 5/6 (83%), ") and lines[-1].endswith(" s left")


# ---------------------------------------------------------------- garbage in, a warning out


def _warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]


def test_observations_no_pose_explains_warn(tmp_path, caplog):
    from ptrack.pipeline.run import execute

    cfg = load_config(
        REPO / "configs" / "demo.yaml", ["data.stop=24", "observations.noise_px=1.0e+9", f"out_dir={tmp_path / 'r'}"]
    )
    with caplog.at_level("WARNING"):
        out = execute(cfg, progress=False)
    (message,) = _warnings(caplog)
    assert "no pose explains these observations" in message and "over 40 px" in message
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["reprojection_error_px"] > 1e8
    assert metrics["observed_fraction"] == pytest.approx(0.95, abs=0.05)  # observations.missing 0.05
    assert metrics["visible_fraction"] == 1.0


def test_few_observed_keypoints_warn_before_estimating(caplog):
    from ptrack.pipeline.run import prepare

    cfg = load_config(REPO / "configs" / "demo.yaml", ["data.stop=24", "observations.missing=0.99"])
    with caplog.at_level("WARNING"):
        prep = prepare(cfg)
    (message,) = _warnings(caplog)
    observed = float((prep.problem.observations.confidence > 0).float().mean())
    assert observed < 0.05
    assert message.startswith(f"only {100 * observed:.0f}% of the keypoints are observed (observed_fraction ")
    assert "the camera sees 100%" in message


def test_observed_fraction_is_what_the_estimator_got(caplog):
    from ptrack.pipeline.run import check_observed, check_reprojection, compute_metrics, estimate, reprojected_keypoints

    cfg = load_config(REPO / "configs" / "demo.yaml", ["data.stop=24", "observations.missing=0.3"])
    with caplog.at_level("WARNING"):
        prep, est = estimate(cfg)
        reproj = reprojected_keypoints(prep, est)
        summary, _ = compute_metrics(prep, est, reproj)
        median = check_reprojection(prep, reproj, cfg.costs.sigma_px)
    assert _warnings(caplog) == []  # a normal run says nothing
    conf = prep.problem.observations.confidence
    assert summary["observed_fraction"] == pytest.approx(float((conf > 0).float().mean()))
    assert 0.6 < summary["observed_fraction"] < 0.8 and summary["visible_fraction"] == 1.0
    assert median < 5.0  # 2 px noise
    import torch

    few = torch.rand(10, 17) < 0.2
    check_observed(few, few)  # a keypoint file: what is observed is what the camera sees, check_visibility warns
    assert _warnings(caplog) == []
