"""Two evaluations side by side, seed by seed: `ptrack compare A B`.

A and B are `ptrack evaluate` folders (or their results.json). For every clip both evaluated, and every
seed both ran on that clip (the same observations, since the seed draws them), each metric's mean in A
and in B, the mean of the differences A - B with its standard error over the seeds, and on how many
seeds A is lower. A claim such as "A beats B on this clip" is then read against the seed-to-seed spread
instead of one mean. A folder evaluated without `--seeds` counts as one run per clip.

    rows = compare(load_runs(a), load_runs(b), ["mpjpe_mm", "flip_error_rate"])
    print(markdown(rows, "A", "B"))
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TypeGuard

from ptrack.errors import InputError

#: metrics compared unless others are named (lower is better for each)
DEFAULT_METRICS = ("mpjpe_mm", "best_of_k_mpjpe_mm", "flip_error_rate")

Runs = dict[str, dict[str, dict]]  # clip -> seed ("-" without seeds) -> that run's metrics


@dataclass(frozen=True)
class Row:
    """One clip (or, with `clips` > 1, the mean over that many clips) and metric: means over the seeds both
    ran, A - B's mean and standard error (None with one seed), the seeds where A is lower, where the two
    are level, and where both have the metric."""

    clip: str
    metric: str
    a: float
    b: float
    diff: float
    stderr: float | None
    a_lower: int
    level: int
    seeds: int
    clips: int = 1


def load_runs(path: str | Path) -> Runs:
    """The runs of an evaluation folder or results.json: {clip: {seed: metrics}}; a failed run (a message
    in results.json) is left out."""
    p = Path(path)
    file = p / "results.json" if p.is_dir() else p
    if not file.is_file():
        raise FileNotFoundError(
            f"no evaluation results at {file} (give a `ptrack evaluate` folder or its results.json)"
        )
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{file} is not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise InputError(f"{file} is not a `ptrack evaluate` results.json (expected a mapping of clips)")
    if "runs" in data:  # with --seeds: {"clips": {clip: mean}, "runs": {clip: {seed: metrics}}}
        runs = data["runs"]
        if not isinstance(runs, dict):
            raise InputError(f"{file}: 'runs' is not a mapping of clips")
    else:  # without --seeds: {clip: metrics}
        runs = {clip: {"-": m} for clip, m in data.items()}
    out: Runs = {}
    for clip, by_seed in runs.items():
        if not isinstance(by_seed, dict):
            raise InputError(f"{file}: clip {clip!r} holds no runs")
        out[clip] = {str(s): m for s, m in by_seed.items() if isinstance(m, dict)}
    return out


def is_number(v: object) -> TypeGuard[int | float]:
    """Whether a metrics.json value counts as a number: an int or float, not a boolean, not NaN."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v)


def _number(m: dict, metric: str) -> float | None:
    v = m.get(metric)
    return float(v) if is_number(v) else None


def compare(a: Runs, b: Runs, metrics: list[str] | tuple[str, ...] | None = None) -> list[Row]:
    """Rows for every clip in both (in A's order) and metric, over the seeds both ran with that metric; then,
    with two clips or more, a row per metric over the clips ("mean (N clips)"): each seed's mean over the
    clips in A and in B, over the seeds every clip ran. metrics: None for those of `DEFAULT_METRICS` that
    some run has (`frame` has no best-of-K); a metric named here that no run has is an error."""
    clips = [c for c in a if c in b]
    if not clips:
        raise InputError(
            f"the two evaluations share no clip (A: {', '.join(a) or 'none'}; B: {', '.join(b) or 'none'})"
        )

    def present(metric: str) -> bool:
        return any(_number(m, metric) is not None for runs in (a, b) for c in clips for m in runs[c].values())

    if metrics is None:
        metrics = [m for m in DEFAULT_METRICS if present(m)]
        if not metrics:
            raise InputError(f"no run of either evaluation has any of the metrics {', '.join(DEFAULT_METRICS)}")
    for metric in metrics:
        if not present(metric):
            raise InputError(f"no run of either evaluation has the metric {metric!r}")
    rows = []
    pairs = {(clip, metric): _pairs(a[clip], b[clip], metric) for clip in clips for metric in metrics}
    for (clip, metric), by_seed in pairs.items():
        if by_seed:
            rows.append(_row(clip, metric, list(by_seed.values())))
    if not rows:
        raise InputError(
            "the two evaluations ran no seed of a shared clip in common (one evaluated without --seeds pairs "
            "only with another without --seeds)"
        )
    for metric in metrics:  # over the clips: each seed's mean over the clips, the seeds every clip ran
        ran = [pairs[clip, metric] for clip in clips if pairs[clip, metric]]
        seeds = [s for s in ran[0] if all(s in p for p in ran)] if len(ran) > 1 else []
        if seeds:
            means = [(sum(p[s][0] for p in ran) / len(ran), sum(p[s][1] for p in ran) / len(ran)) for s in seeds]
            rows.append(_row(f"mean ({len(ran)} clips)", metric, means, clips=len(ran)))
    return rows


def _pairs(a: dict[str, dict], b: dict[str, dict], metric: str) -> dict[str, tuple[float, float]]:
    """One clip's runs in A and B -> {seed: (A's metric, B's)} for the seeds where both have it."""
    out = {}
    for seed, ma in a.items():
        x, y = _number(ma, metric), _number(b[seed], metric) if seed in b else None
        if x is not None and y is not None:
            out[seed] = (x, y)
    return out


def _row(label: str, metric: str, pairs: list[tuple[float, float]], clips: int = 1) -> Row:
    n = len(pairs)
    diffs = [x - y for x, y in pairs]
    mean = sum(diffs) / n
    stderr = math.sqrt(sum((d - mean) ** 2 for d in diffs) / (n - 1) / n) if n > 1 else None
    return Row(
        label,
        metric,
        sum(x for x, _ in pairs) / n,
        sum(y for _, y in pairs) / n,
        mean,
        stderr,
        sum(d < 0 for d in diffs),
        sum(d == 0 for d in diffs),
        n,
        clips,
    )


def _fmt(v: float, fine: bool) -> str:
    return f"{v:.4f}" if fine else f"{v:.1f}"


def markdown(rows: list[Row], name_a: str, name_b: str) -> str:
    """The rows as a markdown table, A and B called by their names."""
    lines = [
        f"| clip | metric | {name_a} | {name_b} | {name_a} - {name_b} (± s.e.) | {name_a} lower on |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        fine = max(abs(r.a), abs(r.b)) < 1  # rates to four places, millimetres and seconds to one
        spread = "" if r.stderr is None else f" ± {_fmt(r.stderr, fine)}"
        cells = [
            f"**{r.clip}**" if r.clips > 1 else r.clip,
            r.metric,
            _fmt(r.a, fine),
            _fmt(r.b, fine),
            _fmt(r.diff, fine) + spread,
        ]
        level = f" ({r.level} level)" if r.level else ""
        lines.append("| " + " | ".join(cells) + f" | {r.a_lower} of {r.seeds}{level} |")
    return "\n".join(lines) + "\n"


def as_json(rows: list[Row], name_a: str, name_b: str) -> str:
    """The rows as JSON: {"a": name, "b": name, "rows": [Row fields, ...]}."""
    return json.dumps({"a": name_a, "b": name_b, "rows": [asdict(r) for r in rows]}, indent=2) + "\n"
