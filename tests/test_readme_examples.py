"""The README's keyframe commands run as written (with a short clip and a light solve added):

    ptrack run configs/batch.yaml keyframes.file=my_keys.yaml     # your own keyframes instead
    ptrack run configs/batch.yaml init_from=logs/batch-<time>     # re-solve from an earlier run

with a keyframe file in the README's format (partial angle keyframes and joint positions, no
keyframe giving every dof), and the interactive loop: add a keyframe, run again from the first run."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from ptrack.cli import main

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
BATCH = REPO / "configs" / "batch.yaml"
LIGHT = [  # 6 frames, a few iterations
    "data.stop=24",
    "progress=false",
    "frame.first_iterations=30",
    "frame.iterations=5",
    "batch.iterations=4",
    "batch.uncertainty=false",
    "batch.flip_restarts=0",
]

MY_KEYS = {
    "units": "degrees",
    "keyframes": [
        {"frame": 0, "dofs": {"lfemur.rx": -20.0, "root.ty": 0.95}, "sigma_deg": 2.0, "sigma_m": 0.02},
        {"frame": 3, "joints": {"lhand": [0.12, 1.31, 0.40], "rfoot": [-0.2, 0.05, 0.3]}, "sigma_m": 0.03},
    ],
}


@pytest.fixture(autouse=True)
def _cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the README's relative paths, and nothing written into the repository


def _readme_command(pattern: str) -> list[str]:
    """The README command line (`ptrack run ...`) containing `pattern`, as arguments after `ptrack`."""
    for line in README.read_text().splitlines():
        if line.startswith("    ptrack run ") and pattern in line:
            return line.split("#")[0].split()[1:]
    raise AssertionError(f"no README command with {pattern!r}")


def test_the_readme_keyframe_file_example_runs(tmp_path, capsys):
    argv = _readme_command("keyframes.file=my_keys.yaml")
    assert argv == ["run", "configs/batch.yaml", "keyframes.file=my_keys.yaml"]
    (tmp_path / "my_keys.yaml").write_text(json.dumps(MY_KEYS))  # JSON is YAML
    argv[1] = str(BATCH)  # the command is run from the repository
    first = tmp_path / "first"
    assert main([*argv, *LIGHT, f"out_dir={first}"]) == 0, capsys.readouterr().err
    with np.load(first / "result.npz") as z:
        assert np.isfinite(z["q"]).all() and z["q"].shape[0] == 6

    # the interactive loop: one keyframe more, and the README's re-solve from the first run
    warm = _readme_command("init_from=logs/batch-<time>")
    assert re.fullmatch(r"init_from=logs/batch-<time>", warm[-1])
    keys = dict(MY_KEYS, keyframes=[*MY_KEYS["keyframes"], {"frame": 5, "dofs": {"rtibia.rx": 30.0}}])
    (tmp_path / "my_keys.yaml").write_text(json.dumps(keys))
    second = tmp_path / "second"
    again = ["run", str(BATCH), "keyframes.file=my_keys.yaml", f"init_from={first}", *LIGHT, f"out_dir={second}"]
    assert main(again) == 0, capsys.readouterr().err
    with np.load(second / "result.npz") as z:
        names, q = [str(n) for n in z["dof_names"]], z["q"]
    assert abs(np.degrees(q[5, names.index("rtibia.rx")]) - 30.0) < 10.0  # the new keyframe is met


def test_keyframes_start_needs_no_full_keyframe(tmp_path, capsys):
    """batch.init=keyframes (configs/batch.yaml's) with only partial keyframes starts from the
    per-frame fits, as batch.init=frame does: the same result."""
    (tmp_path / "my_keys.yaml").write_text(json.dumps(MY_KEYS))
    runs = {}
    for init in ("keyframes", "frame"):
        out = tmp_path / init
        assert (
            main(["run", str(BATCH), "keyframes.file=my_keys.yaml", f"batch.init={init}", *LIGHT, f"out_dir={out}"])
            == 0
        )
        with np.load(out / "result.npz") as z:
            runs[init] = z["q"]
    np.testing.assert_array_equal(runs["keyframes"], runs["frame"])
