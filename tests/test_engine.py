"""Tests for the batch engine (ptrack.pipeline.engine) and `ptrack batch` (ptrack.pipeline.batch_run): many inputs
-> one run folder each, status.csv, results.md/json; the same numbers serial, in local workers and on Ray;
resumption; failures (a corrupt input, a killed worker) as failed rows; bad input refused before anything runs."""

from __future__ import annotations

import csv
import json
import logging
import os
import shutil
import signal
import sys
from pathlib import Path

import pytest

from ptrack.cli import main
from ptrack.errors import InputError
from ptrack.pipeline.batch_run import batch, item_names, parse_sets
from ptrack.pipeline.engine import Item, Local, Progress, run_item

REPO = Path(__file__).resolve().parents[1]
EVAL = REPO / "configs" / "eval_frame.yaml"
ASF = REPO / "ptrack" / "data" / "10.asf"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
QUICK = ["data.stop=24", "data.stride=4", "frame.iterations=3", "frame.first_iterations=5", "progress=false"]


def _clips(folder: Path, stems: tuple[str, ...] = ("10_02", "10_03")) -> Path:
    """Copies of the bundled clip under other names, with its ASF, in `folder`; -> the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copy(ASF, folder / "10.asf")
    for stem in stems:
        shutil.copy(AMC, folder / f"{stem}.amc")
    return folder


def _status(out: Path) -> list[dict]:
    with (out / "status.csv").open(encoding="utf-8") as f:
        return list(csv.DictReader(f))


def _untimed(md: str) -> list[str]:
    """results.md without the seconds column (timings differ between runs)."""
    lines = md.splitlines()
    head = next(ln for ln in lines if ln.startswith("| input"))
    col = [c.strip() for c in head.strip("|").split("|")].index("seconds")
    return [
        "|".join(c for k, c in enumerate(ln.strip("|").split("|")) if k != col) if ln.startswith("|") else ln
        for ln in lines
    ]


def _metrics(out: Path) -> dict:
    """results.json's metrics without timings."""
    res = json.loads((out / "results.json").read_text())["settings"]
    return {
        s: {n: {k: v for k, v in m.items() if k not in ("seconds", "fps")} for n, m in rows.items()}
        for s, rows in res.items()
    }


def _close(a: dict, b: dict) -> None:
    """The same runs: equal keys, numbers equal to float32 rounding (the serial run's torch threads may sum in
    another order than a one-thread worker's)."""
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], dict):
            _close(a[k], b[k])
        elif isinstance(a[k], float):
            assert b[k] == pytest.approx(a[k], rel=1e-4, abs=1e-6), k
        else:
            assert a[k] == b[k], k


# ---------------------------------------------------------------- end to end


def test_workers_give_the_tables_of_a_serial_run(tmp_path, capsys):
    """A manifest (per-row data.start) under a two-value sweep, serial and in two workers: the same tables and
    metrics, one folder per item under its setting's folder, every item done in status.csv."""
    clips = _clips(tmp_path / "clips")
    manifest = tmp_path / "inputs.csv"
    manifest.write_text("input,data.start,data.stop\nclips/10_02.amc,,\nclips/10_03.amc,100,124\n")
    outs = {}
    for workers in ("1", "2"):
        out = outs[workers] = tmp_path / f"w{workers}"
        argv = ["batch", str(EVAL), *QUICK, "--inputs", str(manifest), "--out", str(out), "--workers", workers]
        assert main([*argv, "--set", "costs.sigma_px=1,3", "--quiet"]) == 0
        assert capsys.readouterr().out == f"{out / 'results.md'}\n"
    one, two = outs["1"], outs["2"]
    assert _untimed((one / "results.md").read_text()) == _untimed((two / "results.md").read_text())
    _close(_metrics(one), _metrics(two))
    metrics = _metrics(one)
    assert list(metrics) == ["costs.sigma_px=1", "costs.sigma_px=3"]
    rows = metrics["costs.sigma_px=1"]
    assert list(rows) == ["10_02", "10_03"]
    assert rows["10_02"]["mpjpe_mm"] != rows["10_03"]["mpjpe_mm"]  # the same clip from frame 100 on
    assert rows["10_02"]["mpjpe_mm"] != metrics["costs.sigma_px=3"]["10_02"]["mpjpe_mm"]  # the setting applied
    assert sorted(p.name for p in two.iterdir()) == [
        "costs.sigma_px=1",
        "costs.sigma_px=3",
        "results.json",
        "results.md",
        "status.csv",
    ]
    cfg = (two / "costs.sigma_px=3" / "10_03" / "config.yaml").read_text()
    assert "sigma_px: 3.0" in cfg and "start: 100" in cfg and str(clips / "10_03.amc") in cfg
    status = _status(two)
    assert [(r["name"], r["setting"], r["state"]) for r in status] == [
        (n, f"costs.sigma_px={s}", "done") for s in (1, 3) for n in ("10_02", "10_03")
    ]
    assert all(r["error"] == "" and float(r["seconds"]) > 0 for r in status)
    assert (two / "results.md").read_text().endswith("4 items: 4 done, 0 skipped (complete before), 0 failed.\n")


def test_corrupt_input_is_a_failed_row_and_exit_1(tmp_path, capsys):
    clips = _clips(tmp_path / "clips")
    (clips / "10_05.amc").write_text(":FULLY-SPECIFIED\n1\nroot not numbers\n")
    out = tmp_path / "out"
    argv = ["batch", str(EVAL), *QUICK, "--inputs", str(clips / "*.amc"), "--out", str(out), "--workers", "2"]
    assert main([*argv, "--quiet"]) == 1
    captured = capsys.readouterr()
    assert captured.out == f"{out / 'results.md'}\n"
    status = _status(out)
    assert [(r["name"], r["state"]) for r in status] == [("10_02", "done"), ("10_03", "done"), ("10_05", "failed")]
    assert "10_05.amc" in status[2]["error"] and "\n" not in status[2]["error"]
    md = (out / "results.md").read_text()
    assert "| 10_05 | failed: " in md and md.endswith("3 items: 2 done, 0 skipped (complete before), 1 failed.\n")
    assert sorted(p.name for p in out.iterdir()) == ["10_02", "10_03", "results.json", "results.md", "status.csv"]
    assert json.loads((out / "results.json").read_text())["counts"] == {"done": 2, "skipped": 0, "failed": 1}


def test_resume_skips_complete_runs_and_redoes_half_written_ones(tmp_path):
    clips = _clips(tmp_path / "clips", ("10_02", "10_03", "10_04"))
    out = tmp_path / "out"
    inputs = ",".join(str(clips / f"10_0{k}.amc") for k in (2, 3))
    assert batch(EVAL, inputs, out, QUICK, workers=1).done == 2
    done = (out / "10_02" / "metrics.json").stat().st_mtime_ns
    (out / "10_03" / "result.npz").unlink()  # a folder missing a file
    partial = out / ".10_04.partial"  # what a run killed while writing left (no live process holds it)
    partial.mkdir()
    (partial / "pid").write_text("1\n")
    with pytest.raises(InputError, match="not empty"):  # without --resume the folder is refused
        batch(EVAL, str(clips / "*.amc"), out, QUICK, workers=1)
    summary = batch(EVAL, str(clips / "*.amc"), out, QUICK, workers=1, resume=True)
    assert (summary.done, summary.skipped, summary.failed) == (2, 1, 0)
    assert (out / "10_02" / "metrics.json").stat().st_mtime_ns == done  # not run again
    assert [(r["name"], r["state"]) for r in _status(out)] == [
        ("10_02", "skipped"),
        ("10_03", "done"),
        ("10_04", "done"),
    ]
    for name in ("10_03", "10_04"):
        assert (out / name / "result.npz").is_file()
    assert not partial.exists()
    assert sorted(json.loads((out / "results.json").read_text())["settings"][""]) == ["10_02", "10_03", "10_04"]


def _dies_on_10_03(item: Item, progress: bool | None) -> dict | str:
    """A worker's per-item function that kills its own process inside 10_03's run (while its folder is being
    written), as the kernel's OOM killer would."""
    import ptrack.pipeline.run as run

    estimate = run.estimate

    def killed(cfg, *args, **kwargs):
        if cfg.data.amc.endswith("10_03.amc"):
            os.kill(os.getpid(), signal.SIGKILL)
        return estimate(cfg, *args, **kwargs)

    run.estimate = killed
    try:
        return run_item(item, progress)
    finally:
        run.estimate = estimate


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL is POSIX")
@pytest.mark.parametrize("executor", ["local", "ray"])
def test_a_worker_killed_inside_an_item_costs_that_item_only(tmp_path, executor):
    if executor == "ray":
        ray = pytest.importorskip("ray", reason="the ray extra is not installed")
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray's workers cannot import this file
    clips = _clips(tmp_path / "clips", ("10_02", "10_03", "10_04"))
    out = tmp_path / "out"
    summary = batch(
        EVAL, str(clips / "*.amc"), out, QUICK, workers=2, executor=executor, progress=False, run=_dies_on_10_03
    )
    assert (summary.done, summary.failed) == (2, 1)
    status = {r["name"]: r for r in _status(out)}
    assert status["10_03"]["state"] == "failed"
    died = "worker process died (killed by SIGKILL" if executor == "local" else "Ray task failed: "
    assert status["10_03"]["error"].startswith(died), status["10_03"]["error"]
    assert status["10_02"]["state"] == status["10_04"]["state"] == "done"
    assert sorted(p.name for p in out.iterdir()) == ["10_02", "10_04", "results.json", "results.md", "status.csv"]


def _pid(item: Item, progress: bool | None) -> dict:
    """A worker's per-item function: the process it ran in."""
    return {"pid": os.getpid()}


def test_a_local_worker_is_replaced_after_recycle_after_items(tmp_path):
    """What runs leave in a process stays bounded: a worker takes `recycle_after` items, then a fresh one."""
    items = [Item(f"i{k}", "unused.yaml", (), str(tmp_path / f"i{k}")) for k in range(5)]
    seen: dict[int, int] = {}
    pool = Local(1, recycle_after=2)
    try:
        pool.map(items, _pid, lambda i, outcome, seconds: seen.__setitem__(i, outcome["pid"]))
    finally:
        pool.close()
    pids = [seen[k] for k in range(5)]
    assert pids[0] == pids[1] and pids[2] == pids[3] and len({pids[0], pids[2], pids[4]}) == 3


def test_ray_local_runtime_gives_the_serial_numbers(tmp_path):
    pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]')")
    clips = _clips(tmp_path / "clips")
    one, ray = tmp_path / "one", tmp_path / "ray"
    batch(EVAL, str(clips / "*.amc"), one, [*QUICK, "data.start=50", "data.stop=74"], workers=1)
    summary = batch(
        EVAL, str(clips / "*.amc"), ray, [*QUICK, "data.start=50", "data.stop=74"], workers=2, executor="ray"
    )
    assert (summary.done, summary.failed) == (2, 0)
    _close(_metrics(one), _metrics(ray))
    assert all((ray / n / "result.npz").is_file() for n in ("10_02", "10_03"))


# ---------------------------------------------------------------- bad input: exit 2, nothing written


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--inputs", "{clips}/*.bvh"], "matches no file"),
        (["--inputs", "{clips}/gone.amc"], "input not found"),
        (["--inputs", "{manifest_unknown}"], "column 'camera.nope' is not a config key"),
        (["--inputs", "{manifest_missing}"], "line 3: input not found"),
        (["--set", "frame.iterations=3,many"], "frame.iterations"),
        (["--set", "frame.nope=1,2"], "'frame.nope' is not a config key"),
        (["--executor", "ray", "--ray-address", "127.0.0.1:1"], "cannot reach the Ray cluster at 127.0.0.1:1"),
        (["--executor", "dask"], "--executor must be one of local, ray"),
        (["--workers", "0"], "--workers must be a whole number >= 1"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, extra, message):
    if "ray" in extra:
        pytest.importorskip("ray", reason="the ray extra is not installed")
    clips = _clips(tmp_path / "clips")
    unknown, missing = tmp_path / "unknown.csv", tmp_path / "missing.csv"
    unknown.write_text("input,camera.nope\nclips/10_02.amc,1\n")
    missing.write_text("input\nclips/10_02.amc\nclips/10_09.amc\n")
    fill = {"clips": clips, "manifest_unknown": unknown, "manifest_missing": missing}
    extra = [e.format(**fill) for e in extra]
    inputs = [] if "--inputs" in extra else ["--inputs", str(clips / "*.amc")]
    out = tmp_path / "out"
    assert main(["batch", str(EVAL), *QUICK, *inputs, *extra, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ptrack: error:") and message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_executor_ray_without_ray_installed(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    clips = _clips(tmp_path / "clips")
    out = tmp_path / "out"
    assert (
        main(["batch", str(EVAL), *QUICK, "--inputs", str(clips / "*.amc"), "--out", str(out), "--executor", "ray"])
        == 2
    )
    assert capsys.readouterr().err == 'ptrack: error: --executor ray needs Ray: pip install -e ".[ray]"\n'
    assert not out.exists()


# ---------------------------------------------------------------- parts


def test_parse_sets():
    assert parse_sets([]) == [()]
    assert parse_sets(["costs.sigma_px=1,2", "method=frame,kjs"]) == [
        ("costs.sigma_px=1", "method=frame"),
        ("costs.sigma_px=1", "method=kjs"),
        ("costs.sigma_px=2", "method=frame"),
        ("costs.sigma_px=2", "method=kjs"),
    ]
    assert parse_sets(["model.freeze=[a,b],[c]"]) == [("model.freeze=[a,b]",), ("model.freeze=[c]",)]
    for bad, match in [(["seed"], "must look like"), (["seed=1", "seed=2"], "twice"), (["seed=1,"], "empty value")]:
        with pytest.raises(ValueError, match=match):
            parse_sets(bad)


def test_item_names_are_unique_folder_names(tmp_path):
    (tmp_path / "take 1").mkdir()
    paths = [tmp_path / "a.json", tmp_path / "sub" / "a.json", tmp_path / "take 1", tmp_path / ".hidden.npz"]
    assert item_names(paths) == ["a", "a-2", "take_1", "hidden"]


def test_progress_lines_count_done_failed_and_left(caplog):
    """Off a terminal (pytest's stderr), one line per item: how many are left and failed, and the time left."""
    now = [0.0]
    log = logging.getLogger("ptrack.test_engine")
    with caplog.at_level(logging.INFO, logger=log.name):
        bar = Progress(True, 4, "item", log, clock=lambda: now[0])
        now[0] = 10.0
        bar.finished("a")
        now[0] = 20.0
        bar.finished("b", failed=True)
        bar.close()
    assert [r.getMessage() for r in caplog.records] == [
        "item 1 of 4 done: a, 3 left, about 00:30 left",
        "item 2 of 4 failed: b, 1 failed, 2 left, about 00:20 left",
    ]


def test_real_keypoint_inputs_from_a_manifest(tmp_path):
    """Keypoint folders (observations.file) with per-row camera and subject settings from a manifest, one of them
    a corrupt keypoint file: the folder runs, the corrupt file is a failed row naming it."""
    from keypoint_fixtures import SHIPPED_FRAMES

    shutil.copytree(SHIPPED_FRAMES, tmp_path / "take01")
    (tmp_path / "take02.json").write_text("{not json")
    manifest = tmp_path / "takes.csv"
    manifest.write_text(
        "input,subject.height_m,camera.width,camera.height\ntake01,1.75,1920,1080\ntake02.json,1.6,1920,1080\n"
    )
    over = ["method=frame", "observations.fps=30", "subject.lengths=template", "progress=false"]
    over += ["frame.iterations=3", "frame.first_iterations=5"]
    summary = batch(REPO / "configs" / "video.yaml", str(manifest), tmp_path / "out", over, workers=1)
    assert (summary.done, summary.failed) == (1, 1)
    status = _status(tmp_path / "out")
    assert [(r["name"], r["state"]) for r in status] == [("take01", "done"), ("take02", "failed")]
    assert "take02.json" in status[1]["error"]
    cfg = (tmp_path / "out" / "take01" / "config.yaml").read_text()
    assert "height_m: 1.75" in cfg and f"file: {tmp_path / 'take01'}" in cfg


def test_input_kinds(tmp_path):
    from ptrack.pipeline.batch_run import input_overrides

    assert input_overrides(tmp_path / "a.MP4") == (f"observations.video={tmp_path / 'a.MP4'}",)
    assert input_overrides(tmp_path / "pose") == (f"observations.file={tmp_path / 'pose'}",)
    clips = _clips(tmp_path / "clips")
    assert input_overrides(clips / "10_02.amc") == (f"data.amc={clips / '10_02.amc'}", f"data.asf={clips / '10.asf'}")
