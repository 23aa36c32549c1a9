"""Tests for `ptrack compare`: two evaluations side by side, seed by seed (ptrack.pipeline.compare)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from ptrack.cli import main
from ptrack.errors import InputError
from ptrack.pipeline.compare import compare, load_runs, markdown

REPO = Path(__file__).resolve().parents[1]
EVAL = REPO / "configs" / "eval_frame.yaml"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
QUICK = ["data.stop=24", "data.stride=4", "frame.iterations=3", "frame.first_iterations=5", "progress=false"]


def _results(folder: Path, runs: dict) -> Path:
    """A results.json as `ptrack evaluate --seeds` writes it (its "clips" means are not read by compare)."""
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps({"clips": {}, "runs": runs}))
    return folder


def _rows(md: str) -> list[list[str]]:
    return [[c.strip() for c in ln[1:-1].split("|")] for ln in md.splitlines() if ln.startswith("|")][2:]


def test_seed_by_seed(tmp_path):
    a = _results(
        tmp_path / "a",
        {
            "walk": {"0": {"mpjpe_mm": 10.0, "flip_error_rate": 0.1}, "1": {"mpjpe_mm": 14.0, "flip_error_rate": 0.2},
                     "2": {"mpjpe_mm": 30.0, "flip_error_rate": 0.0}, "7": {"mpjpe_mm": 1.0}},
            "run": {"0": "failed: too short"},
            "only_a": {"0": {"mpjpe_mm": 1.0}},
        },
    )  # fmt: skip
    b = _results(
        tmp_path / "b",
        {
            "walk": {"0": {"mpjpe_mm": 12.0, "flip_error_rate": 0.1}, "1": {"mpjpe_mm": 20.0, "flip_error_rate": 0.1},
                     "2": {"mpjpe_mm": 28.0, "flip_error_rate": 0.0}, "3": {"mpjpe_mm": 1.0}},
            "run": {"0": {"mpjpe_mm": 5.0}},
        },
    )  # fmt: skip
    rows = compare(load_runs(a), load_runs(b), ["mpjpe_mm", "flip_error_rate"])
    # seeds 7 (A only) and 3 (B only), the failed run and the clip only A ran are left out
    assert [(r.clip, r.metric, r.seeds) for r in rows] == [("walk", "mpjpe_mm", 3), ("walk", "flip_error_rate", 3)]
    mpjpe, flips = rows
    diffs = [-2.0, -6.0, 2.0]
    mean = sum(diffs) / 3
    assert mpjpe.a == pytest.approx(18.0) and mpjpe.b == pytest.approx(20.0) and mpjpe.diff == pytest.approx(mean)
    assert mpjpe.stderr == pytest.approx(math.sqrt(sum((d - mean) ** 2 for d in diffs) / 2 / 3))
    assert (mpjpe.a_lower, mpjpe.level) == (2, 0)
    assert (flips.a_lower, flips.level) == (0, 2) and flips.diff == pytest.approx(0.1 / 3)
    body = _rows(markdown(rows, "kjs", "frame"))
    assert body[0] == ["walk", "mpjpe_mm", "18.0", "20.0", f"{mean:.1f} ± {mpjpe.stderr:.1f}", "2 of 3"]
    assert body[1][2:4] == ["0.1000", "0.0667"] and body[1][-1] == "0 of 3 (2 level)"


def test_mean_over_the_clips(tmp_path):
    """With two clips or more, a row per metric over the clips: each seed's mean over the clips, on the seeds
    every clip ran (seed 2: only walk in B)."""
    a = _results(tmp_path / "a", {"walk": {"0": {"mpjpe_mm": 10.0}, "1": {"mpjpe_mm": 20.0}, "2": {"mpjpe_mm": 5.0}},
                                  "run": {"0": {"mpjpe_mm": 30.0}, "1": {"mpjpe_mm": 40.0}}})  # fmt: skip
    b = _results(tmp_path / "b", {"walk": {"0": {"mpjpe_mm": 14.0}, "1": {"mpjpe_mm": 18.0}, "2": {"mpjpe_mm": 9.0}},
                                  "run": {"0": {"mpjpe_mm": 30.0}, "1": {"mpjpe_mm": 44.0}}})  # fmt: skip
    rows = compare(load_runs(a), load_runs(b), ["mpjpe_mm"])
    assert [r.clip for r in rows] == ["walk", "run", "mean (2 clips)"]
    mean = rows[-1]  # seed 0: 20 against 22; seed 1: 30 against 31
    assert (mean.a, mean.b, mean.diff, mean.a_lower, mean.seeds, mean.clips) == (25.0, 26.5, -1.5, 2, 2, 2)
    assert mean.stderr == pytest.approx(0.5)
    assert _rows(markdown(rows, "a", "b"))[-1][0] == "**mean (2 clips)**"


def test_evaluations_without_seeds_count_one_run_per_clip(tmp_path):
    for name, v in (("a", 3.0), ("b", 4.0)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "results.json").write_text(json.dumps({"walk": {"mpjpe_mm": v}, "run": "failed: x"}))
    (row,) = compare(load_runs(tmp_path / "a"), load_runs(tmp_path / "b" / "results.json"), ["mpjpe_mm"])
    assert (row.diff, row.stderr, row.a_lower, row.seeds) == (-1.0, None, 1, 1)
    seeded = _results(tmp_path / "seeded" / "a", {"walk": {"0": {"mpjpe_mm": 1.0}}})
    with pytest.raises(InputError, match="pairs only with another without --seeds"):
        compare(load_runs(seeded), load_runs(tmp_path / "b"))


def test_two_folders_of_one_name_are_a_and_b(tmp_path, capsys):
    for side, v in (("x", 1.0), ("y", 2.0)):
        _results(tmp_path / side / "eval", {"walk": {"0": {"mpjpe_mm": v}}})
    assert main(["compare", str(tmp_path / "x" / "eval"), str(tmp_path / "y" / "eval" / "results.json")]) == 0
    assert capsys.readouterr().out.startswith("| clip | metric | A | B | A - B (± s.e.) | A lower on |")


def test_two_real_evaluations(tmp_path, capsys):
    """`ptrack evaluate` twice on the bundled clip, seeds 0-1 (the same observations: the seed draws them),
    then `ptrack compare`: its cells are the runs' own metrics."""
    out = {}
    for name, extra in (("three", []), ("one", ["frame.iterations=1"])):
        out[name] = tmp_path / name
        argv = ["evaluate", str(EVAL), *QUICK, *extra, "--clips", str(AMC), "--seeds", "0-1", "--out", str(out[name])]
        assert main([*argv, "--quiet"]) == 0
    capsys.readouterr()
    assert main(["compare", str(out["three"]), str(out["one"]), "--metrics", "mpjpe_mm", "reprojection_error_px"]) == 0
    body = _rows(capsys.readouterr().out)
    runs = {n: [json.loads((out[n] / "10_02" / f"seed-{s}" / "metrics.json").read_text()) for s in (0, 1)] for n in out}
    for row, metric in zip(body, ("mpjpe_mm", "reprojection_error_px")):
        a, b = ([m[metric] for m in runs[n]] for n in ("three", "one"))
        assert row[:4] == ["10_02", metric, f"{sum(a) / 2:.1f}", f"{sum(b) / 2:.1f}"]
        assert row[5] == f"{sum(x < y for x, y in zip(a, b))} of 2"
    assert main(["compare", str(out["three"]), str(out["one"]), "--json", "--names", "x", "y"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert (got["a"], got["b"]) == ("x", "y")
    assert [r["metric"] for r in got["rows"]] == ["mpjpe_mm", "flip_error_rate"]  # frame has no best-of-K


@pytest.mark.parametrize(
    "setup, extra, message",
    [
        ("missing", [], "no evaluation results at"),
        ("malformed", [], "is not valid JSON"),
        ("list", [], "is not a `ptrack evaluate` results.json"),
        ("other clip", [], "share no clip"),
        ("ok", ["--metrics", "mpjpe"], "no run of either evaluation has the metric 'mpjpe'"),
        ("other seed", [], "no seed of a shared clip in common"),
        ("no default", [], "any of the metrics mpjpe_mm, best_of_k_mpjpe_mm, flip_error_rate"),
    ],
)
def test_bad_input_is_one_line(tmp_path, capsys, setup, extra, message):
    a = _results(tmp_path / "a", {"walk": {"0": {"seconds": 1.0} if setup == "no default" else {"mpjpe_mm": 1.0}}})
    b = tmp_path / "b"
    if setup != "missing":
        b.mkdir()
        text = {
            "malformed": "{not json",
            "list": "[]",
            "other clip": json.dumps({"runs": {"run": {"0": {"mpjpe_mm": 1.0}}}}),
            "ok": json.dumps({"runs": {"walk": {"0": {"mpjpe_mm": 2.0}}}}),
            "other seed": json.dumps({"runs": {"walk": {"1": {"mpjpe_mm": 2.0}}}}),
            "no default": json.dumps({"runs": {"walk": {"0": {"seconds": 2.0}}}}),
        }[setup]
        (b / "results.json").write_text(text)
    assert main(["compare", str(a), str(b), *extra]) == 2
    err = capsys.readouterr()
    assert err.out == "" and err.err.count("\n") == 1 and err.err.startswith("ptrack: error: ") and message in err.err
