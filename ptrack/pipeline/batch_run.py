"""`ptrack batch`: one config over many real inputs (keypoint files or folders, videos, AMC clips), and over the
cross product of `--set` values, through the batch engine (`ptrack.pipeline.engine`).

    batch(config, inputs, overrides, out, workers, executor, ray_address, resume, sets) -> BatchSummary

Inputs (`--inputs`): a comma-separated list, a text file listing one per line (`.txt`, `#` comments, relative to the
file), a glob (`videos/*.mp4`, `**` allowed) (these three: `ptrack.clips.list_paths`), or a CSV manifest (`.csv`) with
an `input` column (relative to the manifest) and optional columns named by config keys (`camera.name`,
`subject.height_m`) whose cells override the config for their row, parsed as command-line overrides are (an empty
cell: no override). A video (.mp4, .mov, ...) sets observations.video, an .amc file data.amc and its subject's ASF (as
`ptrack evaluate`), anything else observations.file.

Output, in `--out`:

    <name>/ ...              one run folder per input (name: the input's file name without its suffix, made
                             unique with -2, -3, ...); with --set, under one folder per setting,
                             `<key>=<value>[+<key>=<value>...]/<name>/`
    status.csv               every item: name, input, setting, state (pending, done, failed, skipped), seconds
                             (the item's wall time, load and writing included), error, run_dir; rewritten
                             atomically as each item finishes
    results.md               per setting, a table of the inputs' metrics (failed rows with their error) and the
                             counts of done, skipped and failed items
    results.json             {"counts": {...}, "settings": {setting: {name: metrics or error}}} (setting "" without
                             --set)

Everything is checked before anything runs or is written (a user error: `InputError`): the inputs exist, the
manifest's columns are config keys, every item's config loads (so a `--set` value of the wrong type, a bad
manifest cell), the executor can start. `--resume` continues an output folder: an item whose run folder is
complete (config.yaml, metrics.json, result.npz) is skipped, a half-written one is removed and redone.
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import logging
import math
import os
import re
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ptrack.body.acclaim import skeleton_beside
from ptrack.clips import list_paths
from ptrack.errors import InputError
from ptrack.pipeline.config import RunConfig, config_reference, load_config, parse_override
from ptrack.pipeline.engine import (
    Item,
    Outcome,
    Progress,
    RunFn,
    check_workers,
    default_workers,
    open_executor,
    run_item,
    run_items,
)
from ptrack.pipeline.evaluate import markdown_table
from ptrack.pipeline.run import json_safe, remove_partial

log = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
LIST_SUFFIXES = (".txt", ".list")
#: the files a complete run folder holds at least (`ptrack.pipeline.run.execute` writes them)
COMPLETE = ("config.yaml", "metrics.json", "result.npz")
STATUS_FIELDS = ("name", "input", "setting", "state", "seconds", "error", "run_dir")


@dataclass(frozen=True)
class Input:
    """One row of `--inputs`: the input's absolute path and its own overrides (a manifest's cells)."""

    path: Path
    overrides: tuple[str, ...] = ()


@dataclass(frozen=True)
class BatchSummary:
    """What `batch` wrote: the table's path and how many items were done, skipped (complete from before) and
    failed."""

    table: Path
    done: int
    skipped: int
    failed: int


# ---------------------------------------------------------------- inputs and settings


def parse_inputs(spec: str, cwd: Path | None = None) -> list[Input]:
    """`--inputs` (module docstring) -> the inputs in order; InputError / FileNotFoundError naming the first
    problem (nothing matched, a missing file, an unknown manifest column)."""
    cwd = Path(cwd or Path.cwd())
    p = cwd / spec
    if p.is_file() and p.suffix.lower() == ".csv":
        return read_manifest(p)
    paths = list_paths(spec, "--inputs", "input", cwd, is_list=lambda f: f.suffix.lower() in LIST_SUFFIXES)
    return [Input(path) for path in paths]


def read_manifest(path: Path) -> list[Input]:
    """A CSV manifest: an `input` column, other columns config keys (module docstring)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"manifest {path} is not UTF-8 text") from None
    reader = csv.DictReader(io.StringIO(text))
    columns = [c.strip() for c in reader.fieldnames or []]
    if "input" not in columns:
        raise InputError(f"manifest {path} has no `input` column (its columns: {', '.join(columns) or 'none'})")
    keys = {k.key for k in config_reference()}
    unknown = [c for c in columns if c != "input" and c not in keys]
    if unknown:
        raise InputError(f"manifest {path}: column {unknown[0]!r} is not a config key (see `ptrack config --list`)")
    if len(set(columns)) != len(columns):
        raise InputError(f"manifest {path} names a column twice")
    inputs = []
    for line, row in enumerate(reader, start=2):
        cells = {(k or "").strip(): (v or "").strip() for k, v in row.items() if k is not None}
        if None in row:
            raise InputError(f"manifest {path} line {line} has more cells than columns")
        if not cells.get("input"):
            raise InputError(f"manifest {path} line {line} has no input")
        file = (path.resolve().parent / cells["input"]).resolve()
        if not file.exists():
            raise FileNotFoundError(f"manifest {path} line {line}: input not found: {file}")
        inputs.append(Input(file, tuple(f"{k}={v}" for k, v in cells.items() if k != "input" and v)))
    if not inputs:
        raise InputError(f"manifest {path} lists no input")
    return inputs


def input_overrides(path: Path) -> tuple[str, ...]:
    """The overrides that make `path` a run's input: a video's observations.video, an AMC clip's data.amc and
    data.asf (its subject's skeleton beside it), else observations.file."""
    suffix = path.suffix.lower()
    if suffix == ".amc":
        asf = skeleton_beside(path)
        if asf is None:
            raise InputError(f"cannot tell which ASF skeleton belongs to {path}: no .asf in its folder")
        return (f"data.amc={path}", f"data.asf={asf}")
    if suffix in VIDEO_SUFFIXES:
        return (f"observations.video={path}",)
    return (f"observations.file={path}",)


def parse_sets(specs: Sequence[str]) -> list[tuple[str, ...]]:
    """`--set key=v1,v2` (repeatable) -> the settings, the cross product of the values in the order given, each
    a tuple of overrides: ["a=1,2", "b=x"] -> [("a=1", "b=x"), ("a=2", "b=x")]; [()] without --set. Commas
    inside brackets belong to a value (`--set x=[1,2],[3,4]`)."""
    keys: list[str] = []
    values: list[list[str]] = []
    known = {k.key for k in config_reference()}
    for spec in specs:
        key, sep, rest = spec.partition("=")
        key = key.strip()
        if not sep or not key:
            raise InputError(f"--set {spec!r} must look like dotted.key=value1,value2")
        if key not in known:
            raise InputError(f"--set {spec!r}: {key!r} is not a config key (see `ptrack config --list`)")
        if key in keys:
            raise InputError(f"--set gives {key!r} twice")
        vals = _split_top(rest)
        if not vals or any(not v for v in vals):
            raise InputError(f"--set {spec!r} has an empty value")
        for v in vals:
            parse_override(f"{key}={v}")  # YAML that parses
        keys.append(key)
        values.append(vals)
    return [tuple(f"{k}={v}" for k, v in zip(keys, combo)) for combo in itertools.product(*values)]


def _split_top(text: str) -> list[str]:
    """Split at commas outside brackets and quotes."""
    parts: list[str] = []
    cur: list[str] = []
    depth, quote = 0, ""
    for ch in text:
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    parts.append("".join(cur).strip())
    return parts


def item_names(paths: Sequence[Path]) -> list[str]:
    """Run folder names: each input's file name without its suffix (a folder's name), characters other than
    letters, digits, `.`, `-` and `_` as `_`, made unique in order with -2, -3, ..."""
    names: list[str] = []
    for path in paths:
        stem = path.name if path.is_dir() else path.stem
        base = re.sub(r"[^A-Za-z0-9._-]", "_", stem).lstrip(".") or "input"
        name, k = base, 2
        while name in names:
            name, k = f"{base}-{k}", k + 1
        names.append(name)
    return names


def setting_folder(setting: tuple[str, ...]) -> str:
    """A setting's folder: "costs.sigma_px=1+frame.iterations=3" (path separators as `_`)."""
    return re.sub(r"[/\\\s]", "_", "+".join(setting)).lstrip(".")


# ---------------------------------------------------------------- resumption and status


def is_complete(run_dir: Path) -> bool:
    """Whether `run_dir` holds a finished run (the files of `COMPLETE`, metrics.json readable)."""
    if not all((run_dir / f).is_file() for f in COMPLETE):
        return False
    try:
        return isinstance(json.loads((run_dir / "metrics.json").read_text(encoding="utf-8")), dict)
    except (OSError, ValueError):
        return False


def write_atomic(path: Path, text: str) -> None:
    """Write `text` to `path` in one rename (a reader never sees half of it)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def status_csv(rows: Sequence[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=STATUS_FIELDS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


# ---------------------------------------------------------------- the command


def batch(
    config: str | Path,
    inputs: str,
    out: str | Path,
    overrides: Sequence[str] = (),
    workers: int | None = None,
    executor: str = "local",
    ray_address: str | None = None,
    resume: bool = False,
    sets: Sequence[str] = (),
    progress: bool | None = None,
    run: RunFn = run_item,
) -> BatchSummary:
    """Run `config` (with `overrides`) on every input of `inputs` once per setting of `sets` into `out` (module
    docstring). workers: runs at once (default: this machine's cores; with a Ray address, the cluster's CPUs
    decide). progress: one bar over the items (None: as the config's `progress`). run: the per-item function."""
    workers = default_workers() if workers is None else check_workers(workers)
    rows = parse_inputs(inputs)
    settings = parse_sets(sets)
    set_keys = {parse_override(o)[0] for o in settings[0]}
    clash = sorted(set_keys & {parse_override(o)[0] for r in rows for o in r.overrides})
    if clash:
        raise InputError(f"{clash[0]!r} is given both by --set and by the manifest; give it in one place")
    out_dir = Path(out).resolve()
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} is a file, not a folder")
    if not resume and out_dir.is_dir() and any(out_dir.iterdir()):
        raise InputError(f"--out {out_dir} already exists and is not empty (add --resume to continue it)")
    names = item_names([r.path for r in rows])
    items: list[Item] = []
    status: list[dict] = []
    configs: list[RunConfig] = []
    for setting in settings:
        folder = out_dir / setting_folder(setting) if setting else out_dir
        for row, name in zip(rows, names):
            over = (*overrides, *setting, *row.overrides, *input_overrides(row.path))
            try:
                cfg = load_config(config, over)  # every item's config, before any run
            except InputError as e:
                raise InputError(f"{row.path.name}{' with ' + ' '.join(setting) if setting else ''}: {e}") from None
            configs.append(cfg)
            run_dir = folder / name
            label = f"{' '.join(setting)}: {name}" if setting else name
            items.append(Item(label, str(config), over, str(run_dir)))
            status.append(
                {
                    "name": name,
                    "input": str(row.path),
                    "setting": " ".join(setting),
                    "state": "pending",
                    "seconds": "",
                    "error": "",
                    "run_dir": str(run_dir),
                }
            )
    show = configs[0].progress if progress is None else progress
    outcomes: list[Outcome | None] = [None] * len(items)
    with open_executor(executor, workers, ray_address) as ex:  # a Ray cluster not there: an error, nothing written
        out_dir.mkdir(parents=True, exist_ok=True)
        remove_partial(out_dir)  # what killed runs left
        todo = []
        for i, item in enumerate(items):
            run_dir = Path(item.run_dir)
            if resume and is_complete(run_dir):
                outcomes[i] = json.loads((run_dir / "metrics.json").read_text(encoding="utf-8"))
                _mark(status[i], "skipped", outcomes[i], math.nan)
            else:
                if run_dir.exists():  # half-written (files missing): redone
                    log.info("%s is incomplete: running it again", run_dir)
                    shutil.rmtree(run_dir)
                todo.append(i)
        status_path = out_dir / "status.csv"
        write_atomic(status_path, status_csv(status))
        if resume and len(todo) < len(items) and show:
            log.info("resuming %s: %d of %d items complete, skipped", out_dir, len(items) - len(todo), len(items))

        def finished(k: int, outcome: Outcome, seconds: float) -> None:
            i = todo[k]
            outcomes[i] = outcome
            _mark(status[i], "failed" if isinstance(outcome, str) else "done", outcome, seconds)
            write_atomic(status_path, status_csv(status))

        bar = Progress(show, len(todo), "item", log)
        try:
            run_items([items[i] for i in todo], ex, bar, run=run, report=finished)
        finally:
            bar.close()
    return _summary(out_dir, settings, names, configs, outcomes, status)


def _mark(row: dict, state: str, outcome: Outcome | None, seconds: float) -> None:
    """A status row's state, seconds (the item's wall time where it ran, load and writing included; empty when
    not measured) and error."""
    row["state"] = state
    row["seconds"] = "" if math.isnan(seconds) else f"{seconds:.1f}"
    row["error"] = outcome if isinstance(outcome, str) else ""


def _summary(
    out_dir: Path,
    settings: list[tuple[str, ...]],
    names: list[str],
    configs: list[RunConfig],
    outcomes: list[Outcome | None],
    status: list[dict],
) -> BatchSummary:
    """Write results.md and results.json; -> the summary."""
    counts = {s: sum(r["state"] == s for r in status) for s in ("done", "skipped", "failed")}
    n = len(names)
    parts, by_setting = [], {}
    for k, setting in enumerate(settings):
        rows = [(name, outcomes[k * n + j] or "not run") for j, name in enumerate(names)]
        cfg = configs[k * n]
        label = " ".join(setting)
        failed = sum(isinstance(m, str) for _, m in rows)
        note = (f"setting {label}" if setting else "") + (f"{', ' if setting else ''}{failed} failed" if failed else "")
        parts.append(markdown_table(cfg.name, cfg.method, rows, note=note or None, rows_are="input"))
        by_setting[label] = dict(rows)
    line = f"{len(status)} items: {counts['done']} done, {counts['skipped']} skipped (complete before), "
    line += f"{counts['failed']} failed.\n"
    table = out_dir / "results.md"
    write_atomic(table, "\n".join(parts) + "\n" + line)
    results = {"counts": counts, "settings": by_setting}
    write_atomic(out_dir / "results.json", json.dumps(json_safe(results), indent=2, allow_nan=False) + "\n")
    return BatchSummary(table, counts["done"], counts["skipped"], counts["failed"])
