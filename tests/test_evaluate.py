"""Tests for ptrack.pipeline.evaluate: one config over several clips -> per-clip run folders, results.md (a
markdown table with a mean row) and results.json; clip lists; failures reported per clip."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ptrack.cli import main
from ptrack.clips import parse_clips
from ptrack.errors import InputError
from ptrack.pipeline.evaluate import COLUMNS, asf_for, evaluate, markdown_table, parse_seeds, seed_mean
from ptrack.pipeline.run import remove_partial

REPO = Path(__file__).resolve().parents[1]
EVAL = REPO / "configs" / "eval_frame.yaml"
ASF = REPO / "ptrack" / "data" / "10.asf"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
FAST = ["data.stop=24", "data.stride=4", "frame.iterations=15", "frame.first_iterations=60", "progress=false"]
QUICK = [*FAST, "frame.iterations=3", "frame.first_iterations=5"]
OUTPUTS = ["config.yaml", "metrics.json", "plots", "result.bvh", "result.npz", "run.rrd", "skeleton.urdf"]


def _cells(line: str) -> list[str]:
    assert line.startswith("|") and line.endswith("|"), line
    return [c.strip() for c in line[1:-1].split("|")]


def _table(md: str) -> list[list[str]]:
    return [_cells(ln) for ln in md.splitlines() if ln.startswith("|")]


def _clip_copy(folder: Path, frames: int | None = None, stem: str = "10_02") -> Path:
    """Copy the bundled clip (first `frames` frames) and its ASF into `folder`; -> the AMC path."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(ASF, folder / "10.asf")
    lines = AMC.read_text().splitlines(keepends=True)
    if frames is not None:
        lines = lines[: lines.index(f"{frames + 1}\n")]
    amc = folder / f"{stem}.amc"
    amc.write_text("".join(lines))
    return amc


# ---------------------------------------------------------------- end to end


def test_two_clips(tmp_path, cmu_file):
    golf = cmu_file("64_01.amc")
    out = tmp_path / "eval"
    table = evaluate(EVAL, f"{AMC},{golf}", FAST, out=out)
    assert table == out / "results.md"
    md = table.read_text()
    assert md.startswith("Config `eval_frame`, method `frame`.")
    rows = _table(md)
    header, rule, body = rows[0], rows[1], rows[2:]
    assert header[0] == "clip" and "MPJPE mm" in header and "reproj px" in header and "seconds" in header
    assert "best-of-K mm" not in header  # no method here gives hypotheses
    assert all(set(c) <= {"-"} for c in rule) and len(rule) == len(header)
    assert [r[0] for r in body] == ["10_02", "64_01", "**mean (2 clips)**"]
    assert all(len(r) == len(header) for r in body)
    results = json.loads((out / "results.json").read_text())
    assert list(results) == ["10_02", "64_01"]
    col = header.index("MPJPE mm")
    for r in body[:2]:
        m = results[r[0]]
        assert m["frames"] == 6 and r[header.index("frames")] == "6"
        assert r[col] == f"{m['mpjpe_mm']:.1f}"
        assert m == json.loads((out / r[0] / "metrics.json").read_text())
        assert sorted(p.name for p in (out / r[0]).iterdir()) == OUTPUTS
    mean = (results["10_02"]["mpjpe_mm"] + results["64_01"]["mpjpe_mm"]) / 2
    assert body[2][col] == f"{mean:.1f}"
    assert sorted(p.name for p in out.iterdir()) == ["10_02", "64_01", "results.json", "results.md", "results.png"]


def test_clip_list_file_with_relative_paths(tmp_path, capsys):
    _clip_copy(tmp_path / "mocap" / "10")
    _clip_copy(tmp_path / "mocap" / "10", stem="10_77")
    lists = tmp_path / "lists"
    lists.mkdir()
    clips = lists / "mine.txt"
    clips.write_text("# my clips, relative to this file\n\n../mocap/10/10_02.amc   # kick\n   ../mocap/10/10_77.amc\n")
    out = tmp_path / "eval"
    assert main(["evaluate", str(EVAL), *QUICK, "--clips", str(clips), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out == f"{out / 'results.md'}\n"  # stdout: only the table's path
    assert (out / "results.md").read_text().startswith("Config `eval_frame`")
    assert list(json.loads((out / "results.json").read_text())) == ["10_02", "10_77"]
    for stem in ("10_02", "10_77"):
        assert sorted(p.name for p in (out / stem).iterdir()) == OUTPUTS
        assert (out / stem / "config.yaml").read_text().count(str(tmp_path / "mocap" / "10" / "10.asf")) == 1


def test_clip_too_short_is_reported_and_others_run(tmp_path):
    short = _clip_copy(tmp_path / "short", frames=20, stem="10_99")
    out = tmp_path / "eval"
    table = evaluate(EVAL, f"{short},{AMC}", [*QUICK, "data.start=100", "data.stop=124"], out=out)
    rows = _table(table.read_text())
    header, body = rows[0], rows[2:]
    assert [r[0] for r in body] == ["10_99", "10_02", "**mean (1 clips)**"]
    failed = body[0]
    assert failed[1].startswith("failed:") and "data.start" in failed[1] and "20 frames" in failed[1]
    assert len(failed) == len(header)
    results = json.loads((out / "results.json").read_text())
    assert isinstance(results["10_99"], str) and "data.start" in results["10_99"]
    assert results["10_02"]["frames"] == 6
    # no folder, no .partial
    assert sorted(p.name for p in out.iterdir()) == ["10_02", "results.json", "results.md", "results.png"]


def test_progress_false_in_config_is_respected(tmp_path, capsys):
    # `ptrack run` lets the config's `progress` decide unless --quiet is given; `ptrack evaluate` should too
    # (it passes progress=not --quiet to execute(), which overrides progress=false from the config).
    out = tmp_path / "eval"
    assert main(["evaluate", str(EVAL), *QUICK, "--clips", str(AMC), "--out", str(out)]) == 0
    assert capsys.readouterr().err == ""


def test_missing_clip(tmp_path, capsys):
    out = tmp_path / "eval"
    with pytest.raises(FileNotFoundError, match=r"nope\.amc"):
        evaluate(EVAL, f"{AMC},{tmp_path / 'nope.amc'}", QUICK, out=out)
    assert not out.exists()
    rc = main(["evaluate", str(EVAL), *QUICK, "--clips", str(tmp_path / "nope.amc"), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("ptrack: error:") and "nope.amc" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_bad_config_fails_before_any_run(tmp_path, capsys):
    out = tmp_path / "eval"
    assert main(["evaluate", str(EVAL), "camera.fov=3", "--clips", str(AMC), "--out", str(out)]) == 2
    assert "camera.fov" in capsys.readouterr().err
    assert not out.exists()


def test_non_empty_out_is_refused(tmp_path):
    out = tmp_path / "eval"
    out.mkdir()
    (out / "old.md").write_text("x")
    with pytest.raises(InputError, match="not empty"):
        evaluate(EVAL, str(AMC), QUICK, out=out)
    assert [p.name for p in out.iterdir()] == ["old.md"]


# ---------------------------------------------------------------- parts


def test_parse_clips(tmp_path):
    a = _clip_copy(tmp_path / "m")
    b = _clip_copy(tmp_path / "m", stem="10_03")
    assert parse_clips("m/10_02.amc, m/10_03.amc", cwd=tmp_path) == [a, b]
    assert parse_clips(str(a)) == [a]
    listing = tmp_path / "m" / "list.txt"
    listing.write_text("10_03.amc\n# 10_02.amc\n")
    assert parse_clips("m/list.txt", cwd=tmp_path) == [b]
    listing.write_text("# nothing\n")
    with pytest.raises(InputError, match="no clip"):
        parse_clips(str(listing))
    with pytest.raises(InputError, match=r"not an \.amc"):
        parse_clips("m/10_02.amc,m/10.asf", cwd=tmp_path)
    with pytest.raises(FileNotFoundError, match=r"gone\.amc"):
        parse_clips("gone.amc", cwd=tmp_path)
    assert parse_clips("m/*.amc", cwd=tmp_path) == [a, b]  # a glob: its matches, sorted
    assert parse_clips(str(tmp_path / "**" / "10_0[3].amc")) == [b]
    with pytest.raises(InputError, match="matches no file"):
        parse_clips("m/*_99.amc", cwd=tmp_path)


def test_shipped_clip_lists(cmu_dir):
    for name, n in (("dev.txt", 8), ("golf.txt", 7)):
        paths = parse_clips(str(REPO / "configs" / "clips" / name))
        assert len(paths) == n and all(p.suffix == ".amc" and p.is_file() for p in paths)
        assert all(asf_for(p).is_file() for p in paths)


def test_asf_for(tmp_path):
    amc = _clip_copy(tmp_path / "a")
    assert asf_for(amc) == tmp_path / "a" / "10.asf"
    other = tmp_path / "b"
    other.mkdir()
    shutil.copy(AMC, other / "10_02.amc")
    shutil.copy(ASF, other / "skeleton.asf")
    assert asf_for(other / "10_02.amc") == other / "skeleton.asf"  # the only .asf there
    shutil.copy(ASF, other / "another.asf")
    with pytest.raises(InputError, match=r"10\.asf"):
        asf_for(other / "10_02.amc")


def test_markdown_table():
    rows = [
        ("a", {"frames": 10, "mpjpe_mm": 20.0, "reprojection_error_px": 1.0, "seconds": 2.0}),
        ("b", "too short"),
        ("c", {"frames": 20, "mpjpe_mm": 40.0, "reprojection_error_px": None, "seconds": 4.0}),
    ]
    md = markdown_table("cfg", "frame", rows)
    assert md.startswith("Config `cfg`, method `frame`.\n\n")
    table = _table(md)
    assert table[0] == ["clip", "frames", "MPJPE mm", "reproj px", "seconds"]  # only columns with values
    assert table[2] == ["a", "10", "20.0", "1.00", "2.0"]
    assert table[3][:2] == ["b", "failed: too short"] and len(table[3]) == 5
    assert table[4] == ["c", "20", "40.0", "–", "4.0"]
    assert table[5] == ["**mean (2 clips)**", "15.0", "30.0", "1.00", "3.0"]
    assert [c[0] for c in COLUMNS][:2] == ["frames", "mpjpe_mm"]


def test_markdown_table_all_failed():
    table = _table(markdown_table("cfg", "frame", [("a", "bad"), ("b", "worse")]))
    assert [r[0] for r in table[2:]] == ["a", "b"]  # no mean row when nothing ran


def test_estimator_failure_is_reported_per_clip(tmp_path, monkeypatch):
    """A clip on which the estimator returns non-finite poses is a failed row; the others still run."""

    from ptrack.estimators import ESTIMATORS, estimate_frames
    from ptrack.problem import Estimate

    def nan_on_second_clip(problem, cfg, gen, progress):
        est = estimate_frames(problem, cfg, gen, progress)
        if "10_77" in cfg.data.amc:
            q = est.q.clone()
            q[2] = float("nan")
            return Estimate(q=q, joints=problem.skeleton.forward_kinematics(q), cost=est.cost, terms=est.terms)
        return est

    monkeypatch.setitem(ESTIMATORS, "frame", nan_on_second_clip)
    other = _clip_copy(tmp_path / "mocap" / "10", stem="10_77")
    out = tmp_path / "eval"
    rows = _table(evaluate(EVAL, f"{AMC},{other}", QUICK, out=out).read_text())[2:]
    assert [r[0] for r in rows] == ["10_02", "10_77", "**mean (1 clips)**"]
    assert rows[1][1].startswith("failed:") and "nonfinite_frames=1" in rows[1][1]
    assert sorted(p.name for p in out.iterdir()) == ["10_02", "results.json", "results.md", "results.png"]


def test_markdown_table_shows_the_visible_fraction():
    rows = [
        ("a", {"frames": 10, "reprojection_error_px": 0.5, "visible_fraction": 0.25}),
        ("b", {"frames": 10, "reprojection_error_px": 1.5, "visible_fraction": 1.0}),
    ]
    table = _table(markdown_table("cfg", "frame", rows))
    assert table[0] == ["clip", "frames", "reproj px", "visible"]
    assert table[2] == ["a", "10", "0.50", "0.25"] and table[4] == ["**mean (2 clips)**", "10.0", "1.00", "0.62"]


# ---------------------------------------------------------------- several seeds


def test_seeds_run_every_clip_once_per_seed(tmp_path, capsys):
    out = tmp_path / "eval"
    assert (
        main(["evaluate", str(EVAL), *QUICK, "--clips", str(AMC), "--seeds", "0-1", "--out", str(out), "--quiet"]) == 0
    )
    assert capsys.readouterr().out == f"{out / 'results.md'}\n"
    assert sorted(p.name for p in out.iterdir()) == ["10_02", "results.json", "results.md", "results.png"]
    assert sorted(p.name for p in (out / "10_02").iterdir()) == ["seed-0", "seed-1"]
    runs = [json.loads((out / "10_02" / f"seed-{s}" / "metrics.json").read_text()) for s in (0, 1)]
    for s in (0, 1):
        assert sorted(p.name for p in (out / "10_02" / f"seed-{s}").iterdir()) == OUTPUTS
        assert f"seed: {s}\n" in (out / "10_02" / f"seed-{s}" / "config.yaml").read_text()
    assert runs[0]["mpjpe_mm"] != runs[1]["mpjpe_mm"]  # the seed draws the observation noise
    md = (out / "results.md").read_text()
    assert md.startswith("Config `eval_frame`, method `frame`, seeds 0, 1: each clip's row is its mean over them.")
    clips_table, seeds_table = md.split("\n\nEach seed's mean over the clips.\n\n")
    rows = _table(clips_table)
    header, body = rows[0], rows[2:]
    col = header.index("MPJPE mm")
    assert header[0] == "clip" and header[-1] == "seeds"
    assert [r[0] for r in body] == ["10_02", "**mean (1 clips)**"]
    assert body[0][col] == f"{(runs[0]['mpjpe_mm'] + runs[1]['mpjpe_mm']) / 2:.1f}"
    assert body[0][header.index("seeds")] == "2" and body[0][header.index("frames")] == "6"
    rows = _table(seeds_table)
    header, body = rows[0], rows[2:]
    assert header[0] == "seed" and "seeds" not in header
    assert [r[0] for r in body] == ["0", "1", "**mean (2 seeds)**"]
    assert [r[header.index("MPJPE mm")] for r in body[:2]] == [f"{m['mpjpe_mm']:.1f}" for m in runs]
    results = json.loads((out / "results.json").read_text())
    assert results["runs"] == {"10_02": {"0": runs[0], "1": runs[1]}}
    assert results["clips"]["10_02"]["seeds"] == 2
    assert results["clips"]["10_02"]["mpjpe_mm"] == pytest.approx((runs[0]["mpjpe_mm"] + runs[1]["mpjpe_mm"]) / 2)


def test_parse_seeds():
    assert parse_seeds("3") == [3]
    assert parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert parse_seeds(" 7, 0-1 ") == [7, 0, 1]
    for bad, match in [
        ("x", "'x' is not a seed"),
        ("3-1", "'3-1'"),
        ("-1", "'-1'"),
        ("", "''"),
        ("1,0-2", "seed 1 is given twice"),
    ]:
        with pytest.raises(InputError, match=match):
            parse_seeds(bad)


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--seeds", "2-0"], "--seeds '2-0'"), (["seed=3", "--seeds", "0-1"], "either as --seeds or as the override")],
)
def test_bad_seeds_fail_before_any_run(tmp_path, capsys, args, message):
    out = tmp_path / "eval"
    assert main(["evaluate", str(EVAL), *QUICK, "--clips", str(AMC), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ptrack: error:") and message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_seed_mean():
    runs: list[dict | str] = [
        {"frames": 6, "mpjpe_mm": 1.0, "per_limb": {"a": 1}},
        "diverged",
        {"frames": 6, "mpjpe_mm": 3.0},
    ]
    assert seed_mean(runs) == {"seeds": 2, "frames": 6, "mpjpe_mm": 2.0}
    assert seed_mean([{"frames": 6, "flip": float("nan")}, {"frames": 8, "flip": 0.5}], count=False) == {
        "frames": 7.0,
        "flip": 0.5,
    }
    assert seed_mean(["first failure", "second"]) == "first failure"


def test_a_clip_listed_twice_is_refused(tmp_path, capsys):
    other = _clip_copy(tmp_path / "elsewhere")  # the same file name in another folder
    out = tmp_path / "eval"
    assert main(["evaluate", str(EVAL), *QUICK, "--clips", f"{AMC},{other}", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--clips names 10_02 more than once" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def _without_timing(runs: dict) -> dict:
    """results.json's runs without each run's seconds and fps (a failed run's message stays as it is)."""

    def untimed(m: dict | str) -> dict | str:
        return m if isinstance(m, str) else {k: v for k, v in m.items() if k not in ("seconds", "fps")}

    return {clip: {seed: untimed(m) for seed, m in by_seed.items()} for clip, by_seed in runs.items()}


def test_jobs_give_the_results_of_runs_one_after_another(tmp_path, caplog):
    """--jobs 2 runs the (clip, seed) runs in two worker processes: the same metrics (timings apart), in the
    same order, the same folders; a run that fails is reported in its row, as without --jobs."""
    short = _clip_copy(tmp_path / "short", frames=20, stem="10_99")
    kjs = [*QUICK, "method=kjs", "kjs.samples=32", "data.start=100", "data.stop=124"]
    clips = f"{AMC},{short}"
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["evaluate", str(EVAL), *kjs, "--clips", clips, "--seeds", "0-2", "--out", str(one)]) == 0
    assert (
        main(["evaluate", str(EVAL), "--jobs", "2", *kjs, "--clips", clips, "--seeds", "0-2", "--out", str(two)]) == 0
    )
    failed = [r.getMessage() for r in caplog.records if "failed" in r.getMessage()]
    assert len(failed) == 6 and all(m.startswith("10_99 seed") for m in failed)  # 3 in each evaluation
    a, b = (json.loads((d / "results.json").read_text()) for d in (one, two))
    assert list(b["runs"]["10_02"]) == ["0", "1", "2"]
    assert isinstance(b["runs"]["10_99"]["1"], str) and "data.start" in b["runs"]["10_99"]["1"]
    assert _without_timing(a["runs"]) == _without_timing(b["runs"])
    assert b["runs"]["10_02"]["0"]["mpjpe_mm"] != b["runs"]["10_02"]["1"]["mpjpe_mm"]  # three different runs
    assert sorted(p.relative_to(two).as_posix() for p in two.glob("*/*")) == [f"10_02/seed-{s}" for s in range(3)]


@pytest.mark.parametrize("jobs", ["0", "-1"])
def test_bad_jobs_fail_before_any_run(tmp_path, capsys, jobs):
    out = tmp_path / "eval"
    assert main(["evaluate", str(EVAL), *QUICK, "--clips", str(AMC), "--out", str(out), "--jobs", jobs]) == 2
    err = capsys.readouterr().err
    assert err == f"ptrack: error: --jobs must be a whole number >= 1, got {jobs}\n"
    assert not out.exists()


@pytest.mark.skipif(sys.platform == "win32", reason="process groups and SIGINT are POSIX")
def test_ctrl_c_with_jobs_stops_every_worker(tmp_path):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) during `--jobs 2`: the command ends
    at once with `ptrack: interrupted` and status 130, no traceback; runs that finished keep complete
    folders, and nothing half-written is left."""
    out = tmp_path / "eval"
    cmd = [sys.executable, "-m", "ptrack.cli", "evaluate", str(EVAL), *QUICK, "progress=true", "--clips", str(AMC)]
    cmd += ["--seeds", "0-9", "--jobs", "2", "--out", str(out)]

    def own_group() -> None:  # a shell's background job would ignore SIGINT; a terminal's foreground one does not
        os.setpgrp()
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen(cmd, cwd=REPO, stderr=subprocess.PIPE, text=True, preexec_fn=own_group)
    assert proc.stderr is not None
    lines = []
    for line in proc.stderr:  # wait until one run has finished, then interrupt the others
        lines.append(line)
        if " done: " in line:
            break
    os.killpg(proc.pid, signal.SIGINT)
    _, rest = proc.communicate(timeout=60)
    err = "".join(lines) + rest
    assert proc.returncode == 130, err
    assert err.rstrip().endswith("ptrack: interrupted") and "Traceback" not in err
    runs = sorted((out / "10_02").iterdir())
    assert 1 <= len(runs) < 10  # the finished ones
    for run in runs:
        assert sorted(p.name for p in run.iterdir()) == OUTPUTS
    assert [p.name for p in (out / "10_02").iterdir() if p.name.startswith(".")] == []
    assert not (out / "results.md").exists()


def test_remove_partial(tmp_path):
    """What a run killed while writing leaves (its folder's hidden sibling) goes; finished folders stay."""
    done = tmp_path / "10_02" / "seed-0"
    done.mkdir(parents=True)
    (done / "metrics.json").write_text("{}")
    left = tmp_path / "10_02" / ".seed-1.k3j9.partial"
    left.mkdir()
    (left / "config.yaml").write_text("x")
    (tmp_path / "10_02" / ".seed-2.x8q1.probe").mkdir()  # killed between making and removing its write probe
    remove_partial(tmp_path)
    assert sorted(p.name for p in (tmp_path / "10_02").iterdir()) == ["seed-0"]
    assert (done / "metrics.json").is_file()
