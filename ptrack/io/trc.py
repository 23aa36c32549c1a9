"""TRC: marker trajectories in OpenSim's text layout (what `opensim.TRCFileAdapter` and Pose2Sim read).

The file, tab separated:

    PathFileType  4  (X/Y/Z)  result.trc
    DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
    60        60          100        21          m      60            1                   100
    Frame#  Time  RHip        RKnee ...        (each name over its three columns)
                  X1  Y1  Z1  X2  Y2  Z2 ...
    1       0     x   y   z   ...

Metres; Y up by default (OpenSim's convention; `--up z` for a Z-up lab, see `ptrack.io.markers`); the rate
is the run's exact frame rate (60, 29.97002997...), Frame# the input's frame number + 1 (TRC counts from
1) and Time the seconds of `ptrack.io.markers.frame_times` (input frame / fps for footage). The points are
a footage run's keypoints under Pose2Sim's marker names, or the skeleton's joints (`--points`).
"""

from __future__ import annotations

from pathlib import Path

from ptrack.errors import InputError
from ptrack.io.markers import Markers, markers
from ptrack.io.run_folder import RunFolder


def rate_text(fps: float) -> str:
    """A frame rate as text, exactly: "60" for 60.0, the shortest round-trip decimal otherwise."""
    return str(int(fps)) if float(fps).is_integer() else repr(float(fps))


def write_trc(path: Path, m: Markers) -> None:
    """Write markers `m` to `path` as an OpenSim TRC file (metres)."""
    T, M = m.xyz.shape[:2]
    rate = rate_text(m.fps)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{T}\t{M}\tm\t{rate}\t{int(m.frames[0]) + 1 if T else 1}\t{T}",
        "Frame#\tTime\t" + "\t".join(f"{n}\t\t" for n in m.names),
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, M + 1)),
        "",
    ]
    flat = m.xyz.reshape(T, 3 * M)
    for k in range(T):
        values = "\t".join(f"{v:.6f}" for v in flat[k])
        lines.append(f"{int(m.frames[k]) + 1}\t{m.times[k]:.8f}\t{values}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def export_trc(run: RunFolder, out_dir: Path, options) -> list[Path]:
    """`ptrack export --format trc` (an `ptrack.io.exporters.Writer`): result.trc in `out_dir`."""
    if options.opensim is not None:
        raise InputError("--opensim applies to --format mot only")
    path = out_dir / "result.trc"
    write_trc(path, markers(run, options.points, options.up or "y"))
    return [path]
