"""`ptrack export`: a run folder into the formats of the user's own tools.

`export_run(run_dir, fmt, out, options)` reads the run (`ptrack.io.run_folder.load_run`), asks the format's
writer for its files and moves them into place only when all are written: an error leaves nothing behind.
Every writer is a function `(run, out_dir, options) -> list[Path]` that writes its files into `out_dir` (a
fresh temporary folder) and returns them; `FORMATS` maps each format name to its writer, and the writers
live in their own modules (one format each), registered below.

Default output: `RUN_DIR/export/`. `out` may be a folder (kept: its files are replaced one by one) or, for
a format that writes one file, that file's path.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ptrack.errors import InputError
from ptrack.io import c3d, mot, trc
from ptrack.io.run_folder import RunFolder, load_run


@dataclass(frozen=True)
class ExportOptions:
    """What a writer may be asked besides the run. up: the output's up axis ("y" or "z"; the format's
    default when None); names: a joint name map for retargeting rigs (e.g. "mixamo"); rest: the BVH rest
    pose ("asf": the skeleton's own, the default; "tpose"); opensim: an OpenSim model (.osim) to run its inverse
    kinematics on; points: "keypoints" (a footage run's keypoints under the input's names) or "joints"
    (the skeleton's joints); None: keypoints where the run has them, else joints."""

    up: str | None = None
    names: str | None = None
    rest: str | None = None
    opensim: str | None = None
    points: str | None = None

    def refuse(self, fmt: str, accepted: tuple[str, ...] = (), up: tuple[str, ...] = ("y", "z")) -> None:
        """InputError when an option that `fmt` does not take is given (`accepted`: those it takes of names,
        rest, opensim, points; `up`: the up axes it can write)."""
        for name in ("names", "rest", "opensim", "points"):
            if name not in accepted and getattr(self, name) is not None:
                raise InputError(f"--{name} does not apply to --format {fmt}")
        if self.up is not None and self.up not in up:
            axes = " or ".join(a.upper() for a in up)
            raise InputError(f"--format {fmt} is written {axes} up only: --up {self.up} is not available for it")


Writer = Callable[[RunFolder, Path, ExportOptions], list[Path]]


def _bvh(run: RunFolder, out_dir: Path, options: ExportOptions) -> list[Path]:
    from ptrack.io.export import export_bvh

    return export_bvh(run, out_dir, options)


def _json(run: RunFolder, out_dir: Path, options: ExportOptions) -> list[Path]:
    from ptrack.io.json_csv import export_json

    return export_json(run, out_dir, options)


def _csv(run: RunFolder, out_dir: Path, options: ExportOptions) -> list[Path]:
    from ptrack.io.json_csv import export_csv

    return export_csv(run, out_dir, options)


#: format name -> writer
FORMATS: dict[str, Writer] = {
    "bvh": _bvh,
    "json": _json,
    "csv": _csv,
    "trc": trc.export_trc,
    "mot": mot.export_mot,
    "c3d": c3d.export_c3d,
}


def export_run(
    run_dir: str | Path, fmt: str, out: str | Path | None = None, options: ExportOptions | None = None
) -> list[Path]:
    """Export the run in `run_dir` as `fmt` (a `FORMATS` key) into `out` (default RUN_DIR/export/); returns the
    files written. Raises InputError for a folder that is not a run, an unknown format, an unwritable `out`
    or options the format cannot honour; nothing is written then."""
    fmt = fmt.lower()
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}: one of {', '.join(sorted(FORMATS))}")
    run = load_run(run_dir)
    options = options or ExportOptions()
    target = Path(out) if out is not None else run.path / "export"
    as_file = target.suffix != "" and not target.is_dir()  # out names the file itself
    out_dir = target.parent if as_file else target
    created = next((p for p in reversed([out_dir, *out_dir.parents]) if not p.exists()), None)  # removed on error
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the output folder {out_dir}: {e.strerror or e}") from None
    if not os.access(out_dir, os.W_OK):
        raise InputError(f"the output folder {out_dir} is not writable")
    tmp = Path(tempfile.mkdtemp(prefix=".ptrack-export-", dir=out_dir))
    try:
        written = FORMATS[fmt](run, tmp, options)
        if as_file and len(written) != 1:
            raise InputError(f"--out {target} names one file but {fmt} writes {len(written)}: give a folder")
        final = [target] if as_file else [out_dir / p.name for p in written]
        for src, dst in zip(written, final):
            os.replace(src, dst)
        return final
    except BaseException:
        if created is not None:  # the folders this call made go too: nothing is left behind
            shutil.rmtree(created, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
