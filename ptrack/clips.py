"""Lists of files named on a command line or in a config key: a comma-separated list, a list file (one path per
line, `#` comments, relative to the list's folder) or a glob (`cmu/subjects/*/*_0[1-3].amc`, `**` allowed).

    list_paths(spec, "--inputs", "input", cwd)                 # absolute paths, each checked to exist
    parse_clips(spec, cwd, what="config key 'motion.clips'")   # the same for AMC clips (.amc only)

One parser for every caller: the motion model (`motion.clips`), the evaluation harness (`--clips`) and the
batch runs (`--inputs`). A caller names itself (`what`: the flag or config key the user typed) and what one
item is (`noun`), and the errors say those words: `config key 'motion.clips' 'golf.txt': the list names no
clip`, `--inputs 'x/*.mp4' matches no file or folder`, `input not found: /abs/path`.
"""

from __future__ import annotations

import glob
from collections.abc import Callable
from pathlib import Path

from ptrack.errors import InputError

#: AMC clips; any other file a clip spec names is a list of clips
CLIP_SUFFIXES = (".amc", ".asf")


def list_paths(
    spec: str,
    what: str,
    noun: str,
    cwd: Path | None = None,
    is_list: Callable[[Path], bool] = lambda p: True,
) -> list[Path]:
    """The paths `spec` names, in order (a glob's matches sorted), resolved against `cwd` (default: the working
    folder); a list file's entries against the list's folder.

    spec: a comma-separated list, a list file (an existing file for which `is_list` is true) or a glob (a
    pattern that is not itself an existing path). what: the flag or config key (`--clips`, `config key
    'motion.clips'`); noun: one item (`clip`, `input`); both for the errors. InputError when nothing is named
    or matched; FileNotFoundError for a named path that does not exist.
    """
    cwd = Path(cwd or Path.cwd())
    p = cwd / spec
    if p.is_file() and is_list(p):
        base = p.resolve().parent
        items = [ln.split("#", 1)[0].strip() for ln in p.read_text(encoding="utf-8").splitlines()]
        paths = [(base / it).resolve() for it in items if it]
        if not paths:
            raise InputError(f"{what} {spec!r}: the list names no {noun}")
    elif not p.exists() and glob.has_magic(spec):
        paths = [Path(m).resolve() for m in sorted(glob.glob(str(p), recursive=True))]
        if not paths:
            raise InputError(f"{what} {spec!r} matches no file or folder")
    else:
        paths = [(cwd / it.strip()).resolve() for it in spec.split(",") if it.strip()]
        if not paths:
            raise InputError(f"{what} {spec!r} names no {noun}")
    for path in paths:
        if not path.exists():
            raise FileNotFoundError(f"{noun} not found: {path}")
    return paths


def parse_clips(spec: str, cwd: Path | None = None, what: str = "--clips") -> list[Path]:
    """AMC paths from a comma-separated list, a clip-list file (any file not .amc or .asf) or a glob (`list_paths`);
    InputError naming `what` when none is named, or naming a path that is not an .amc file."""
    paths = list_paths(spec, what, "clip", cwd, is_list=lambda p: p.suffix.lower() not in CLIP_SUFFIXES)
    for path in paths:
        if path.suffix.lower() != ".amc":
            raise InputError(f"{what}: clip {path} is not an .amc file")
    return paths
