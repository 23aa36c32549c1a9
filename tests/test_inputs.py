"""Tests of what ptrack takes in and says back (issue 38): numbers as people write them (overrides, config
files, config.yaml round trip), warnings on observations no pose explains or that hold few keypoints, the
package's own data found from any working directory, and progress lines off a terminal."""

from __future__ import annotations

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


def test_inf_where_the_key_allows():
    assert load_config(None, [*DATA, "kjs.ceiling_deg=inf"]).kjs.ceiling_deg == math.inf
    for text in ("nan", "-inf"):
        with pytest.raises(InputError, match=r"'kjs.ceiling_deg' must be a finite number \(or inf\)"):
            load_config(None, [*DATA, f"kjs.ceiling_deg={text}"])


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
    cfg = load_config(None, [*DATA, "name=x", "observations.noise_px=1e-7", "kjs.ceiling_deg=inf"])
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
