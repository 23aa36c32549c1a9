"""Evaluation harness: one config over several clips, one markdown table.

`evaluate(config, clips)` runs the config once per AMC clip (its ASF is the .asf file in the AMC's
folder), each into `<out>/<clip>/`, and writes `<out>/results.md` (metrics per clip and their
mean) and `<out>/results.json`. Estimator issues paste the table into docs/results.md.

With `seeds` (`ptrack evaluate --seeds 0-4`) every clip runs once per seed (the seed draws the
observation noise, the missing keypoints and the samplers' randomness) into `<out>/<clip>/seed-<s>/`;
each clip's row is then the mean over its seeds, a second table gives each seed's mean over the clips
(the spread a single seed hides), and results.json holds {"clips": {clip: mean}, "runs": {clip:
{seed: metrics}}}.

The runs are items of the batch engine (`ptrack.pipeline.engine`, which `ptrack batch` shares): with
`jobs` > 1 (`--jobs N`) that many runs go at once, each in a worker process on one intra-op thread. Every
run is seeded by its own config and the trackers and `method: batch` run on one thread either way, so their
results are those of the runs made one after another (`frame` and `pca` use torch's threads when run in
this process: their sums may round differently).
"""

from __future__ import annotations

import json
import logging
import math
import statistics
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

from ptrack.body.acclaim import skeleton_beside
from ptrack.clips import parse_clips
from ptrack.errors import InputError
from ptrack.pipeline.compare import is_number
from ptrack.pipeline.config import load_config, parse_override
from ptrack.pipeline.engine import Item, Progress, check_workers, open_executor, run_items
from ptrack.pipeline.run import json_safe

log = logging.getLogger(__name__)

#: (metrics.json key, column title, format)
COLUMNS = (
    ("frames", "frames", "{:d}"),
    ("mpjpe_mm", "MPJPE mm", "{:.1f}"),
    ("pa_mpjpe_mm", "PA-MPJPE mm", "{:.1f}"),
    ("mpjpe_abs_mm", "abs MPJPE mm", "{:.1f}"),
    ("accel_error_mm_per_frame2", "accel mm/f²", "{:.1f}"),
    ("accel_error_abs_mm_per_frame2", "abs accel mm/f²", "{:.1f}"),
    ("flip_error_rate", "flip rate", "{:.3f}"),
    ("reprojection_error_px", "reproj px", "{:.2f}"),
    ("visible_fraction", "visible", "{:.2f}"),
    ("joint_limit_violation_fraction", "limit viol.", "{:.3f}"),
    ("gt_joint_limit_violation_fraction", "GT limit viol.", "{:.3f}"),
    ("best_of_k_mpjpe_mm", "best-of-K mm", "{:.1f}"),
    ("heaviest_mpjpe_mm", "heaviest mm", "{:.1f}"),
    ("heaviest_is_best_share", "heaviest≈best", "{:.2f}"),
    ("depth_order_brier", "order Brier", "{:.3f}"),
    ("depth_order_in_modes", "order in modes", "{:.3f}"),
    ("distinct_modes_5cm", "modes 5 cm apart", "{:.1f}"),
    ("joint_within_2std", "within 2 std", "{:.3f}"),
    ("seconds", "seconds", "{:.1f}"),
    ("seeds", "seeds", "{:d}"),  # with several seeds: how many ran (the row is their mean)
)


def parse_seeds(spec: str) -> list[int]:
    """Seeds from "3", "0-4" or "0,2,7-9": integers >= 0, each at most once, in the order given."""
    seeds: list[int] = []
    for item in spec.split(","):
        item = item.strip()
        lo, sep, hi = item.partition("-")
        try:
            first, last = int(lo), int(hi) if sep else int(lo)
            if first < 0 or last < first:
                raise ValueError
        except ValueError:
            msg = f"--seeds {spec!r}: {item!r} is not a seed (an integer >= 0) or a range like 0-4"
            raise InputError(msg) from None
        for seed in range(first, last + 1):
            if seed in seeds:
                raise InputError(f"--seeds {spec!r}: seed {seed} is given twice")
            seeds.append(seed)
    return seeds


def asf_for(amc: Path) -> Path:
    """The skeleton of an AMC clip: `<subject>.asf` beside it, or the only .asf there."""
    found = skeleton_beside(amc)
    if found is None:
        raise InputError(
            f"cannot tell which ASF skeleton belongs to {amc}: expected {amc.stem.split('_')[0]}.asf in its folder"
        )
    return found


def evaluate(
    config: str | Path,
    clips: str,
    overrides: list[str] | tuple[str, ...] = (),
    out: str | Path | None = None,
    progress: bool | None = False,
    seeds: Sequence[int] | None = None,
    jobs: int = 1,
) -> Path:
    """Run `config` on every clip (with `seeds`, once per seed); returns the path of the markdown table.

    progress: show progress bars (None: as the config's `progress` says). jobs: runs at once, each in a
    worker process on one intra-op thread (1: one after another in this process). With several at once each
    run's `seconds` and `fps` are measured while the others share the machine."""
    paths = parse_clips(clips)
    stems = [p.stem for p in paths]
    twice = sorted({x for x in stems if stems.count(x) > 1})
    if twice:  # each clip's runs go to <out>/<clip name>/
        raise InputError(f"--clips names {', '.join(twice)} more than once (clips are told apart by file name)")
    check_workers(jobs, "--jobs")
    base = load_config(config, overrides)  # validates the config once, before any run
    if seeds is not None:
        if not seeds:
            raise InputError("--seeds names no seed")
        if any(parse_override(o)[0] == "seed" for o in overrides):
            raise InputError("give the seed either as --seeds or as the override seed=..., not both")
    out_dir = Path(out) if out else Path("logs") / f"eval-{base.name}-{datetime.now().strftime('%Y%m%d-%H%M%S')}"
    if out_dir.exists() and any(out_dir.iterdir()):
        raise InputError(f"evaluation folder {out_dir} already exists and is not empty")
    jobs_list = [(amc, seed) for amc in paths for seed in (seeds if seeds is not None else [None])]
    runs: dict[str, dict[int | None, dict | str]] = {amc.stem: {} for amc in paths}
    show = base.progress if progress is None else progress
    unit = "clip" if seeds is None else "run"

    def item(amc: Path, seed: int | None) -> Item:
        run_dir = out_dir / amc.stem if seed is None else out_dir / amc.stem / f"seed-{seed}"
        seed_over = [] if seed is None else [f"seed={seed}"]
        over = (*overrides, *seed_over, f"data.amc={amc}", f"data.asf={asf_for(amc)}")
        return Item(_name(amc, seed), str(config), over, str(run_dir.resolve()))

    items = [item(amc, seed) for amc, seed in jobs_list]
    bar = Progress(show, len(items), unit, log)
    try:
        with open_executor("local", jobs) as executor:
            outcomes = run_items(items, executor, bar, run_progress=progress)
    finally:
        bar.close()
    for (amc, seed), outcome in zip(jobs_list, outcomes):
        runs[amc.stem][seed] = outcome
    out_dir.mkdir(parents=True, exist_ok=True)
    table = out_dir / "results.md"
    if seeds is None:
        rows = [(clip, by_seed[None]) for clip, by_seed in runs.items()]
        table.write_text(markdown_table(base.name, base.method, rows), encoding="utf-8")
        results: dict = dict(rows)
    else:
        rows = [(clip, seed_mean(list(by_seed.values()))) for clip, by_seed in runs.items()]
        per_seed = [(str(s), seed_mean([runs[c][s] for c in runs], count=False)) for s in seeds]
        listed = ", ".join(str(s) for s in seeds)
        table.write_text(
            markdown_table(base.name, base.method, rows, note=f"seeds {listed}: each clip's row is its mean over them")
            + "\n"
            + markdown_table(
                base.name, base.method, per_seed, note="each seed's mean over the clips", head=False, rows_are="seed"
            ),
            encoding="utf-8",
        )
        results = {
            "clips": dict(rows),
            "runs": {clip: {str(s): m for s, m in by_seed.items()} for clip, by_seed in runs.items()},
        }
    (out_dir / "results.json").write_text(
        json.dumps(json_safe(results), indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    if base.plots:
        spread = None if seeds is None else {clip: seed_spread(list(runs[clip].values())) for clip in runs}
        write_bar_chart(out_dir / "results.png", rows, f"config {base.name}, method {base.method}", spread)
    return table


def seed_spread(runs: list[dict | str], key: str = "mpjpe_mm") -> float:
    """The standard deviation of `key` over the runs (seeds) that have it; 0 with fewer than two."""
    vals = [m[key] for m in runs if isinstance(m, dict) and is_number(m.get(key))]
    return statistics.stdev(vals) if len(vals) > 1 else 0.0


def write_bar_chart(path: Path, rows: list[tuple[str, dict | str]], title: str, spread: dict | None) -> None:
    """results.png: the table's MPJPE per clip (`ptrack.io.plots.evaluation_figure`); a failure is a warning."""
    try:
        from ptrack.io.plots import evaluation_figure, save

        save(evaluation_figure(rows, title, spread), path)
    except Exception as e:
        log.warning("%s not written: %s: %s", path.name, type(e).__name__, e)


def _name(amc: Path, seed: int | None) -> str:
    return amc.stem if seed is None else f"{amc.stem} seed {seed}"


def seed_mean(runs: list[dict | str], count: bool = True) -> dict | str:
    """The mean of several runs' metrics (those that ran; each number metric over the runs that have
    it), with count: "seeds" = how many ran; the first failure's message if none ran."""
    ok = [m for m in runs if isinstance(m, dict)]
    if not ok:
        return next(m for m in runs if isinstance(m, str))
    mean: dict = {"seeds": len(ok)} if count else {}
    for key in ok[0]:
        vals = [m.get(key) for m in ok]
        nums = [v for v in vals if is_number(v)]
        if not nums:
            continue
        if all(isinstance(v, int) for v in nums) and len(set(nums)) == 1:
            mean[key] = nums[0]  # the same count in every run (frames)
        else:
            mean[key] = sum(nums) / len(nums)
    return mean


def markdown_table(
    config_name: str,
    method: str,
    rows: list[tuple[str, dict | str]],
    note: str | None = None,
    head: bool = True,
    rows_are: str = "clip",
) -> str:
    """Markdown table of per-clip metrics and their mean over the clips that ran; `note` follows the
    config and method in the line above it (with head=False, the note alone); `rows_are` names what a
    row is (clip, seed) in the first column's title and the mean row's label."""
    cols = [c for c in COLUMNS if any(isinstance(m, dict) and m.get(c[0]) is not None for _, m in rows)]
    title = ", ".join([*([f"Config `{config_name}`, method `{method}`"] if head else []), *([note] if note else [])])
    head_line = f"{title[:1].upper()}{title[1:]}.\n\n" if title else ""
    lines = [f"| {rows_are} | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    ok = [m for _, m in rows if isinstance(m, dict)]
    for name, m in rows:
        if isinstance(m, str):
            lines.append(f"| {name} | failed: {m} |" + " |" * (len(cols) - 1))
            continue
        lines.append(f"| {name} | " + " | ".join(_fmt(m.get(k), f) for k, _, f in cols) + " |")
    if ok:
        means = []
        for k, _, f in cols:
            vals = [m[k] for m in ok if m.get(k) is not None and not math.isnan(m[k])]
            means.append(_fmt(sum(vals) / len(vals) if vals else None, "{:.1f}" if f == "{:d}" else f))
        lines.append(f"| **mean ({len(ok)} {rows_are}s)** | " + " | ".join(means) + " |")
    return head_line + "\n".join(lines) + "\n"


def _fmt(v, f: str) -> str:
    if v is None:
        return "–"
    if f == "{:d}" and not isinstance(v, int):  # a count averaged over clips of different lengths
        return f"{v:.1f}"
    return f.format(v)
