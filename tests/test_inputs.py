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

from ptrack.config import dump_yaml, load_config, load_yaml
from ptrack.errors import InputError

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
    from ptrack.keyframes import read_keyframes
    from ptrack.skeleton import Skeleton

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
from ptrack.pose_prior import read_pose_prior, smoothing_prior
from ptrack.skeleton import Skeleton

sk = Skeleton.from_asf(PKG / "data" / "10.asf").with_limits("data")
print(json.dumps({"lower": sk.lower.tolist(), "prior": read_pose_prior(), "smooth": smoothing_prior("cmu-train")}))
"""


def test_package_data_found_from_a_shadowing_folder(tmp_path):
    from ptrack.pose_prior import read_pose_prior, smoothing_prior
    from ptrack.skeleton import Skeleton

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
