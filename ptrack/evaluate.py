"""Evaluation harness: one config over several clips, one markdown table.

`evaluate(config, clips)` runs the config once per AMC clip (its ASF is the .asf file in the AMC's
folder), each into `<out>/<clip>/`, and writes `<out>/results.md` (metrics per clip and their
mean) and `<out>/results.json`. Estimator issues paste the table into docs/results.md.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from collections.abc import Iterable
from datetime import datetime
from pathlib import Path

from ptrack.config import load_config, skeleton_beside
from ptrack.errors import EstimationError, InputError
from ptrack.run import execute, json_safe

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
    ("seconds", "seconds", "{:.1f}"),
)


def parse_clips(spec: str, cwd: Path | None = None) -> list[Path]:
    """AMC paths from a comma-separated list or a text file (one path per line, `#` comments,
    relative to the file's folder)."""
    cwd = Path(cwd or Path.cwd())
    p = cwd / spec
    if p.is_file() and p.suffix.lower() not in (".amc", ".asf"):
        base = p.resolve().parent
        items = [ln.split("#", 1)[0].strip() for ln in p.read_text(encoding="utf-8").splitlines()]
        paths = [(base / it).resolve() for it in items if it]
    else:
        paths = [(cwd / it.strip()).resolve() for it in spec.split(",") if it.strip()]
    if not paths:
        raise InputError(f"--clips {spec!r} names no clip")
    for path in paths:
        if not path.exists():
            raise FileNotFoundError(f"clip not found: {path}")
        if path.suffix.lower() != ".amc":
            raise InputError(f"clip {path} is not an .amc file")
    return paths


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
) -> Path:
    """Run `config` on every clip; returns the path of the markdown table.

    progress: show progress bars (None: as the config's `progress` says)."""
    paths = parse_clips(clips)
    base = load_config(config, overrides)  # validates the config once, before any run
    out_dir = Path(out) if out else Path("logs") / f"eval-{base.name}-{datetime.now().strftime('%Y%m%d-%H%M%S')}"
    if out_dir.exists() and any(out_dir.iterdir()):
        raise InputError(f"evaluation folder {out_dir} already exists and is not empty")
    rows: list[tuple[str, dict | str]] = []
    show = base.progress if progress is None else progress
    on_terminal = sys.stderr.isatty()
    clips_shown: Iterable[Path] = paths
    if show and on_terminal:
        from tqdm.auto import tqdm

        clips_shown = tqdm(paths, desc="clips", unit="clip")
    for i, amc in enumerate(clips_shown):
        if show and not on_terminal:  # a file or CI log: one short line per clip, no bar
            log.info("clip %d of %d: %s", i + 1, len(paths), amc.stem)
        clip_over = [
            *overrides,
            f"data.amc={amc}",
            f"data.asf={asf_for(amc)}",
            f"out_dir={(out_dir / amc.stem).resolve()}",
        ]
        try:
            cfg = load_config(config, clip_over)
            run_dir = execute(cfg, progress=progress)
            rows.append((amc.stem, json.loads((run_dir / "metrics.json").read_text())))
        except (InputError, EstimationError) as e:  # a clip that does not fit the config (too short, ...)
            # or that the estimator failed on is reported, not fatal
            log.warning("clip %s failed: %s", amc.stem, e)
            rows.append((amc.stem, str(e)))
    out_dir.mkdir(parents=True, exist_ok=True)
    table = out_dir / "results.md"
    table.write_text(markdown_table(base.name, base.method, rows), encoding="utf-8")
    (out_dir / "results.json").write_text(
        json.dumps(json_safe(dict(rows)), indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    return table


def markdown_table(config_name: str, method: str, rows: list[tuple[str, dict | str]]) -> str:
    """Markdown table of per-clip metrics and their mean over the clips that ran."""
    cols = [c for c in COLUMNS if any(isinstance(m, dict) and m.get(c[0]) is not None for _, m in rows)]
    head = f"Config `{config_name}`, method `{method}`.\n\n"
    lines = ["| clip | " + " | ".join(c[1] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
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
        lines.append(f"| **mean ({len(ok)} clips)** | " + " | ".join(means) + " |")
    return head + "\n".join(lines) + "\n"


def _fmt(v, f: str) -> str:
    if v is None:
        return "–"
    return f.format(v)
