"""Tests for ptrack.cli: `ptrack run` / `ptrack replay` in-process through `main(argv)`, and once as the
installed `ptrack` command. User errors exit 2 with one `ptrack: error:` line and write nothing."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_errors import fail

import ptrack.io.viz
from ptrack.cli import main, parse_args
from ptrack.pipeline.config import load_config
from ptrack.pipeline.run import prepare

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo.yaml"
ASF = REPO / "ptrack" / "data" / "10.asf"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
FAST = ["data.stop=48", "data.stride=4", "frame.iterations=15", "frame.first_iterations=60", "progress=false"]


def _run_argv(out: Path, *extra: str, config: Path = DEMO) -> list[str]:
    return ["run", str(config), *FAST, *extra, f"out_dir={out}"]


@pytest.fixture(scope="module")
def obs_arrays(tmp_path_factory) -> dict[str, np.ndarray]:
    """The arrays of an observation file (Observations.save_npz) matching FAST's 12 frames."""
    cfg = load_config(DEMO, [*FAST, "observations.missing=0"])
    path = tmp_path_factory.mktemp("obs") / "obs.npz"
    prepare(cfg).problem.observations.save_npz(path)
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


def _save(path: Path, arrays: dict[str, np.ndarray], **changes: np.ndarray) -> Path:
    np.savez(path, **{**arrays, **changes})
    return path


# ---------------------------------------------------------------- success


def test_run_success(tmp_path, capsys):
    out = tmp_path / "ok"
    assert main([*_run_argv(out), "--quiet", "--json"]) == 0
    captured = capsys.readouterr()
    metrics = json.loads(captured.out)  # stdout: only the metrics (--json)
    assert metrics == json.loads((out / "metrics.json").read_text())
    assert metrics["frames"] == 12 and metrics["mpjpe_mm"] > 0
    assert "Traceback" not in captured.err and "error" not in captured.err
    assert sorted(p.name for p in out.iterdir()) == [
        "config.yaml",
        "metrics.json",
        "plots",
        "result.bvh",
        "result.npz",
        "run.rrd",
        "skeleton.urdf",
    ]


def test_run_from_observation_file(tmp_path, capsys, obs_arrays):
    path = _save(tmp_path / "obs.npz", obs_arrays)
    out = tmp_path / "from_file"
    assert main(_run_argv(out, f"observations.file={path}", "frame.iterations=3", "frame.first_iterations=5")) == 0
    assert capsys.readouterr().out == f"{out}\n"  # stdout: only the run folder's path


# ---------------------------------------------------------------- user errors: exit 2, one line


def test_missing_config(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", config=tmp_path / "nope.yaml"), "nope.yaml")


def test_invalid_yaml_config(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("data: {asf: [1, 2\n")
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", config=bad), "bad.yaml")


def test_invalid_yaml_override_value(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "camera.width=[1, 2"), "camera.width")


def test_missing_asf(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"data.asf={tmp_path / 'gone.asf'}"), "gone.asf")


def test_missing_amc(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"data.amc={tmp_path / 'gone.amc'}"), "gone.amc")


@pytest.mark.parametrize(
    "text",
    [
        "hello world\n:bonedata\n begin\n name x\n",  # not ASF at all
        None,  # a real ASF cut off in the middle of :bonedata
    ],
)
def test_malformed_asf(tmp_path, capsys, text):
    bad = tmp_path / "broken.asf"
    full = ASF.read_text()
    bad.write_text(text if text is not None else full[: len(full) // 3])
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"data.asf={bad}"), "broken.asf")


@pytest.mark.parametrize("edit", ["number", "empty", "unknown_bone"])
def test_malformed_amc(tmp_path, capsys, edit):
    bad = tmp_path / "broken.amc"
    text = AMC.read_text()
    if edit == "number":
        text = text.replace("lfemur -12.5863", "lfemur abc", 1)
    elif edit == "empty":
        text = ""
    else:
        text = text.replace("\nlfemur ", "\nlthigh ", 1)
    bad.write_text(text)
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"data.amc={bad}"), "broken.amc")


def test_amc_of_another_skeleton(tmp_path, capsys):
    other = tmp_path / "other.asf"  # the same skeleton with the bone lthumb renamed
    other.write_text(re.sub(r"\blthumb\b", "lpinky", ASF.read_text()))
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"data.asf={other}"), "10_02.amc", "lthumb")


def test_unknown_key(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "camera.fov=60"), "camera.fov")


@pytest.mark.parametrize(
    "override, key",
    [
        ("camera.focal_px=abc", "camera.focal_px"),
        ("data.stride=1.5", "data.stride"),
        ("data.stride=true", "data.stride"),
        ("seed=null", "seed"),
        ("data.stop=abc", "data.stop"),  # an int-or-null key given a string
    ],
)
def test_wrong_type(tmp_path, capsys, override, key):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", override), key)


def test_bad_value(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "data.stride=0"), "data.stride")
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "data.start=5000", "data.stop=null"), "data.start")


def test_bad_override_syntax(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "seed"), "seed")


def test_keypoints_npz_of_wrong_shape(tmp_path, capsys, obs_arrays):
    kp = obs_arrays["keypoints"]
    path = _save(tmp_path / "flat.npz", obs_arrays, keypoints=kp[..., :1])
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"observations.file={path}"), "flat.npz", "keypoints")
    path = _save(
        tmp_path / "k16.npz",
        obs_arrays,
        keypoints=kp[:, :16],
        confidence=obs_arrays["confidence"][:, :16],
        keypoint_names=obs_arrays["keypoint_names"][:16],
    )
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"observations.file={path}"), "keypoint")
    path = _save(
        tmp_path / "short.npz",
        {k: v[:5] if k in ("keypoints", "confidence", "times") else v for k, v in obs_arrays.items()},
    )
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"observations.file={path}"), "short.npz", "5 frames")


def test_nan_keypoints_with_confidence(tmp_path, capsys, obs_arrays):
    kp = obs_arrays["keypoints"].copy()
    kp[3, 5] = np.nan
    assert obs_arrays["confidence"][3, 5] > 0
    path = _save(tmp_path / "nan.npz", obs_arrays, keypoints=kp)
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", f"observations.file={path}"), "nan.npz", "NaN", "frame 3")
    # NaN where confidence is 0 is allowed
    conf = obs_arrays["confidence"].copy()
    conf[3, 5] = 0
    path = _save(tmp_path / "nan_ok.npz", obs_arrays, keypoints=kp, confidence=conf)
    out = tmp_path / "ok"
    assert main(_run_argv(out, f"observations.file={path}", "frame.iterations=3", "frame.first_iterations=5")) == 0
    assert out.is_dir()


def test_camera_that_sees_nothing(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "camera.focal_px=10000000"), "sees none")


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_unavailable(tmp_path, capsys):
    fail(capsys, tmp_path / "o", _run_argv(tmp_path / "o", "device=cuda"), "device", "CUDA")


def test_non_empty_out_dir(tmp_path, capsys):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert main(_run_argv(out)) == 2
    err = capsys.readouterr().err
    assert err.startswith("ptrack: error: out_dir") and str(out) in err
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_no_command_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2
    assert "usage: ptrack" in capsys.readouterr().err


# ---------------------------------------------------------------- replay


def test_replay_missing_folder(tmp_path, capsys, monkeypatch):
    calls = []
    monkeypatch.setattr(ptrack.io.viz, "open_viewer", calls.append)
    assert main(["replay", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ptrack: error:") and "nothing" in err and "Traceback" not in err
    (tmp_path / "empty").mkdir()
    assert main(["replay", str(tmp_path / "empty")]) == 2
    assert "run.rrd" in capsys.readouterr().err
    assert calls == []


def test_replay_opens_the_recording(tmp_path, capsys, monkeypatch):
    run_dir = tmp_path / "a_run"
    run_dir.mkdir()
    (run_dir / "run.rrd").write_bytes(b"RRF2")  # replay checks rerun's header, then hands the path to the viewer
    calls = []
    monkeypatch.setattr(ptrack.io.viz, "open_viewer", calls.append)
    assert main(["replay", str(run_dir)]) == 0
    assert main(["replay", str(run_dir / "run.rrd")]) == 0
    assert [Path(c) for c in calls] == [run_dir / "run.rrd"] * 2
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------- the installed command


def test_console_script_exit_code(tmp_path):
    exe = shutil.which("ptrack")
    if exe is None:
        pytest.skip("the ptrack console script is not installed")
    out = tmp_path / "o"
    proc = subprocess.run(
        [exe, *_run_argv(out, f"data.amc={tmp_path / 'gone.amc'}")],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [f"ptrack: error: AMC file not found: {tmp_path / 'gone.amc'}"]
    assert proc.stdout == "" and not out.exists()


def test_estimator_failure_is_one_line_and_exit_1(tmp_path, capsys, monkeypatch):
    from ptrack.estimators import ESTIMATORS
    from ptrack.problem import Estimate

    def nan_estimator(problem, cfg, gen, progress):
        q = torch.full((problem.observations.num_frames, problem.skeleton.num_dofs), float("nan"))
        nan = torch.full((q.shape[0],), float("nan"))
        return Estimate(q=q, joints=problem.skeleton.forward_kinematics(q), cost=nan, terms={})

    monkeypatch.setitem(ESTIMATORS, "frame", nan_estimator)
    out = tmp_path / "nan"
    assert main(_run_argv(out)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ptrack: error: method 'frame' returned non-finite poses in 12 of 12")
    assert not out.exists()


# ---------------------------------------------------------------- argument order (through the command line)


def _cli(*argv: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ptrack.cli", *argv],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=cwd,
        env=None if env is None else {**os.environ, **env},
    )


def test_flags_and_overrides_in_any_order(tmp_path):
    # every override is read wherever it stands: the last one names a missing AMC, so the run stops
    # at loading it (exit 2, one line) instead of at argparse's "unrecognized arguments"
    out = tmp_path / "o"
    proc = _cli("run", str(DEMO), "seed=3", "--quiet", *FAST, f"out_dir={out}", "data.amc=gone.amc", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"ptrack: error: AMC file not found: {tmp_path / 'gone.amc'}"]
    proc = _cli(
        "evaluate",
        str(DEMO),
        "--clips",
        str(AMC),
        "--out",
        str(out),
        "data.stop=40",
        "--quiet",
        "camera.fov=60",
        cwd=tmp_path,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: unknown config key 'camera.fov'"), proc.stderr
    assert not out.exists()


def test_config_among_the_overrides(tmp_path):
    # the config file after overrides is found as the first argument without '=', the overrides keep
    # their order (data.amc=gone.amc comes last, so the run stops at loading it)
    out = tmp_path / "o"
    proc = _cli("run", "seed=3", f"out_dir={out}", str(DEMO), "--quiet", "data.amc=gone.amc", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"ptrack: error: AMC file not found: {tmp_path / 'gone.amc'}"]
    args = parse_args(["run", "data.stop=8", "seed=1", str(DEMO), "seed=2"])
    assert args.config == str(DEMO) and args.overrides == ["data.stop=8", "seed=1", "seed=2"]
    proc = _cli("run", "seed=3", "data.stop=8", cwd=tmp_path)
    assert proc.returncode == 2 and "no config file given: every argument is a key=value override" in proc.stderr
    assert not out.exists()


def test_unknown_flag_after_overrides_is_a_usage_error(tmp_path):
    proc = _cli("run", str(DEMO), "seed=3", "--bogus", cwd=tmp_path)
    assert proc.returncode == 2 and "unrecognized arguments: --bogus" in proc.stderr
    proc = _cli("replay", str(tmp_path), "extra", cwd=tmp_path)
    assert proc.returncode == 2 and "unrecognized arguments: extra" in proc.stderr


def test_overrides_after_a_flag_keep_their_order(tmp_path, capsys):
    # data.stride=4 (in FAST) before the flag, data.stride=0 after it: the later one is applied
    fail(capsys, tmp_path / "o", [*_run_argv(tmp_path / "o"), "--quiet", "data.stride=0"], "data.stride")


def test_unwritable_out_dir_is_one_line_before_the_run(tmp_path):
    (tmp_path / "file").write_text("x")
    out = tmp_path / "file" / "run"
    proc = _cli("run", str(DEMO), *FAST, f"out_dir={out}", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"ptrack: error: out_dir {out} cannot be made: {tmp_path / 'file'} is a file, not a folder"
    ]
    assert proc.stdout == "" and sorted(p.name for p in tmp_path.iterdir()) == ["file"]


@pytest.mark.parametrize(
    "args, line",
    [
        (
            ['model.freeze=["*"]'],
            "ptrack: error: config key 'model.freeze' ['*'] freezes every dof of "
            + str(ASF)
            + "; nothing is left to estimate",
        ),
        (
            ["seed=99999999999999999999999"],
            "ptrack: error: config key 'seed' must be between -2**63 and 2**63 - 1, got 99999999999999999999999",
        ),
    ],
)
def test_former_tracebacks_are_one_line(tmp_path, args, line):
    out = tmp_path / "o"
    proc = _cli("run", str(DEMO), *FAST, *args, f"out_dir={out}", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [line]
    assert proc.stdout == "" and not out.exists()


def test_config_that_is_a_folder(tmp_path):
    proc = _cli("run", "configs/", cwd=REPO)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: config configs is a folder; give a YAML file"), lines


def test_garbage_observation_file_is_not_an_npz(tmp_path):
    garbage = tmp_path / "obs.npz"
    garbage.write_bytes(bytes(range(256)) * 4)
    proc = _cli("run", str(DEMO), *FAST, f"observations.file={garbage}", f"out_dir={tmp_path / 'o'}", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"ptrack: error: {garbage}: not an .npz archive (numpy cannot read it)"]


@pytest.mark.parametrize("key", ["missing", "dropped_frames"])
def test_channel_rate_of_one_names_the_config_key(tmp_path, capsys, key):
    # the config accepts what the channel accepts: one interval, one message, naming the config key
    line = fail(
        capsys,
        tmp_path / "o",
        _run_argv(tmp_path / "o", f"observations.{key}=1.0"),
        f"config key 'observations.{key}' must be a number in [0, 1), got 1.0",
    )
    assert "ChannelConfig" not in line


def test_observation_file_warns_about_ignored_channel_settings(tmp_path, obs_arrays):
    path = _save(tmp_path / "obs.npz", obs_arrays)
    out = tmp_path / "o"
    proc = _cli(
        "run",
        str(DEMO),
        *FAST,
        "frame.iterations=3",
        "frame.first_iterations=5",
        "observations.missing=0",
        "observations.noise_px=5",
        f"observations.file={path}",
        f"out_dir={out}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "ptrack: WARNING: observations.file is given, so observations.noise_px (for simulated observations) is ignored"
    ]
    assert out.is_dir()


def test_amc_override_runs_with_the_skeleton_beside_it(tmp_path):
    sub = tmp_path / "subjects" / "10"
    sub.mkdir(parents=True)
    for f in (ASF, AMC):
        (sub / f.name).write_bytes(f.read_bytes())
    out = tmp_path / "o"
    proc = _cli(
        "run",
        str(DEMO),
        *FAST,
        "frame.iterations=3",
        "frame.first_iterations=5",
        f"data.amc={sub / AMC.name}",
        f"out_dir={out}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"ptrack: WARNING: data.amc is {sub / AMC.name}: using the skeleton "
        f"beside it, {sub / ASF.name} (set data.asf to choose another)"
    ]
    assert load_config(out / "config.yaml").data.asf == str(sub / ASF.name)


def test_camera_that_sees_little_warns_and_too_little_is_refused(tmp_path):
    out = tmp_path / "o"
    quick = [*FAST, "frame.iterations=3", "frame.first_iterations=5"]
    proc = _cli("run", str(DEMO), *quick, "camera.focal_px=4500", f"out_dir={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "ptrack: WARNING: the camera sees only 41% of the keypoints (visible_fraction 0.412): the estimate rests on "
        "few observations"
    ]
    assert json.loads((out / "metrics.json").read_text())["visible_fraction"] == pytest.approx(7 / 17)
    out = tmp_path / "o2"
    proc = _cli("run", str(DEMO), *quick, "camera.focal_px=6000", f"out_dir={out}", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        "ptrack: error: the camera sees too little: 0 of 12 frames have at least a third of the keypoints visible "
        "(3 are needed; visible_fraction 0.294); check camera.* or the observations"
    ]
    assert not out.exists()


# ---------------------------------------------------------------- stdout for scripts, messages on stderr


def test_stdout_is_the_run_folder_or_the_json_and_progress_only_on_a_terminal(tmp_path):
    quick = [a for a in FAST if a != "progress=false"] + ["frame.iterations=3", "frame.first_iterations=5"]
    out = tmp_path / "o"
    slow = {"PTRACK_PROGRESS_SECONDS": "3600"}  # off a terminal a long run logs progress lines; not this one
    proc = _cli("run", str(DEMO), *quick, f"out_dir={out}", cwd=tmp_path, env=slow)  # progress on, not a terminal
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == f"{out}\n" and proc.stderr == ""
    proc = _cli("run", str(DEMO), *quick, f"out_dir={tmp_path / 'j'}", "--json", cwd=tmp_path, env=slow)
    assert proc.returncode == 0 and proc.stderr == ""
    assert json.loads(proc.stdout) == json.loads((tmp_path / "j" / "metrics.json").read_text())
    proc = _cli(
        "evaluate", str(DEMO), *quick, "--clips", str(AMC), "--out", str(tmp_path / "e"), "--json", cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert list(json.loads(proc.stdout)) == ["10_02"]
    assert proc.stderr.splitlines() == ["ptrack: INFO: clip 1 of 1: 10_02"]  # one short line per clip, no bar


def test_closed_stdout_is_not_a_traceback(tmp_path):
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "ptrack.cli",
            "run",
            str(DEMO),
            *FAST,
            "frame.iterations=3",
            "frame.first_iterations=5",
            f"out_dir={tmp_path / 'o'}",
            "--json",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=tmp_path,
    )
    proc.stdout.close()  # the reader has gone before the run prints
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=300) == 141, err
    assert err == "" and (tmp_path / "o" / "metrics.json").is_file()


# ---------------------------------------------------------------- fast help


def test_help_and_version_do_not_load_torch(tmp_path):
    code = (
        "import sys\nfrom ptrack.cli import main\n"
        "for argv in (['--help'], ['--version'], ['run', '--help'], ['evaluate', '--help'],"
        " ['replay', '--help']):\n"
        "    try:\n        main(argv)\n    except SystemExit as e:\n        assert e.code == 0, (argv, e.code)\n"
        "import ptrack\nprint(sorted(m for m in ('torch', 'numpy', 'yaml', 'rerun') if m in sys.modules))"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == "[]"
    assert f"ptrack {__import__('ptrack').__version__}" in proc.stdout
    # the package's names still come on first use
    proc = subprocess.run(
        [sys.executable, "-c", "import ptrack; print(ptrack.Skeleton.__module__, ptrack.InputError)"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert proc.stdout.split()[0] == "ptrack.body.skeleton", proc.stderr


def test_every_argument_has_help():
    from ptrack.cli import _parser

    parser = _parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subparsers.choices.items():
        for action in sub._actions:
            assert action.help, f"ptrack {name}: {action.dest} has no help text"


# ---------------------------------------------------------------- replay without a display, --web


@pytest.mark.skipif(sys.platform in ("darwin", "win32"), reason="X11/Wayland systems only")
def test_replay_without_a_display_says_how_to_view_the_run(tmp_path):
    run_dir = tmp_path / "a_run"
    run_dir.mkdir()
    (run_dir / "run.rrd").write_bytes(b"RRF2")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    proc = subprocess.run(
        [sys.executable, "-m", "ptrack.cli", "replay", str(run_dir)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env=env,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: no display here"), proc.stderr
    assert f"ptrack replay {run_dir / 'run.rrd'} --web" in lines[0] and "copy it" in lines[0]


def test_replay_web_serves_on_localhost_and_prints_the_address(tmp_path, capsys, monkeypatch):
    run_dir = tmp_path / "a_run"
    run_dir.mkdir()
    (run_dir / "run.rrd").write_bytes(b"RRF2")
    calls = []

    def fake_run(cmd, env=None):
        calls.append((cmd, env))
        return 0

    monkeypatch.setattr(ptrack.io.viz, "run_child", fake_run)
    assert main(["replay", str(run_dir), "--web"]) == 0
    ((cmd, env),) = calls
    assert cmd[cmd.index("--bind") + 1] == "127.0.0.1" and "--serve-web" in cmd and str(run_dir / "run.rrd") in cmd
    assert env["RUST_LOG"] == "warn"  # no rerun banner
    out = capsys.readouterr().out
    web = cmd[cmd.index("--web-viewer-port") + 1]
    assert out.startswith(f"http://127.0.0.1:{web}?url=") and out.count("\n") == 1


def test_native_viewer_listens_on_localhost(tmp_path, monkeypatch):
    rrd = tmp_path / "run.rrd"
    rrd.write_bytes(b"RRF2")
    argvs = []

    class FakePopen:
        def __init__(self, argv, **kw):
            argvs.append(argv)

        def wait(self):
            return 0

    monkeypatch.setattr(ptrack.io.viz, "has_display", lambda: True)
    monkeypatch.setattr(ptrack.io.viz.subprocess, "Popen", FakePopen)
    assert ptrack.io.viz.open_viewer(rrd) == 0
    assert argvs[0][argvs[0].index("--bind") + 1] == "127.0.0.1"


# ---------------------------------------------------------------- one line, not a traceback (issue 38)


@pytest.mark.parametrize("device", ["gpu", "mps", "cuda:99", "cpu:x"])
def test_a_device_torch_cannot_use_here_is_one_line(tmp_path, capsys, device):
    """At config load, before any work: the key, this machine's choices and the value given."""
    out = tmp_path / "o"
    line = fail(capsys, out, _run_argv(out, f"device={device}"), "config key 'device'", "cpu", f"{device!r}")
    assert "cuda:N" in line and "mps" in line


@pytest.mark.parametrize("web", [True, False])
def test_replay_of_a_file_that_is_not_a_recording_is_one_line(tmp_path, capsys, web):
    """metrics.json (or a .rrd that is no recording) is refused before an address is printed or a viewer starts."""
    run_dir = tmp_path / "a_run"
    run_dir.mkdir()
    (run_dir / "metrics.json").write_text('{"frames": 12}\n')
    (run_dir / "run.rrd").write_text('{"frames": 12}\n')
    for path in (run_dir / "metrics.json", run_dir / "run.rrd", run_dir):
        capsys.readouterr()
        assert main(["replay", str(path), *(["--web"] if web else [])]) == 2
        captured = capsys.readouterr()
        assert captured.out == ""  # no address
        lines = captured.err.strip().splitlines()
        assert lines == [
            f"ptrack: error: {path if path.is_file() else path / 'run.rrd'} is not a rerun recording (.rrd): "
            "give a run folder (it holds run.rrd) or its run.rrd"
        ]


def test_an_out_dir_that_cannot_be_put_in_place_is_one_line(tmp_path, capsys, monkeypatch):
    """When the finished folder cannot be renamed to out_dir (a parent made read-only during the run, ...):
    one line, status 2, and neither out_dir nor the hidden folder it was assembled in is left."""
    import ptrack.pipeline.run

    replace = os.replace

    def refused(src, dst):
        if Path(dst).name == "o":
            raise PermissionError(13, "Permission denied", str(dst))
        replace(src, dst)

    monkeypatch.setattr(ptrack.pipeline.run.os, "replace", refused)
    out = tmp_path / "runs" / "o"
    line = fail(capsys, out, _run_argv(out), f"out_dir {out}", "Permission denied", "nothing was written")
    assert line.startswith("ptrack: error: cannot put the finished run at out_dir")
    assert not out.parent.exists()  # the parent it made, empty, goes too
