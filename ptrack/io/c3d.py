"""C3D: marker trajectories in the biomechanics lab binary format (Visual3D, Vicon Nexus, Mokka, ezc3d),
written with ezc3d (the optional `export` extra).

The points are those of the TRC (`ptrack.io.markers`: a footage run's keypoints under Pose2Sim's marker
names, or the skeleton's joints), in millimetres (POINT:UNITS "mm"), as 32-bit floats (POINT:SCALE -1),
every point valid in every frame (residual 0: the model estimates a keypoint the detector missed too).
POINT:RATE is the run's exact frame rate; POINT:LABELS the names, POINT:DESCRIPTIONS what each point
is and along which axes. Axes: Y up by default (the model frame); `--up z` turns them Z up as Visual3D
labs expect (out (X, Y, Z) = model (Z, X, Y), the calibration's own world for a Z-up lab). POINT:X_SCREEN
and POINT:Y_SCREEN say which axis points right and which up on a viewer's screen ("+X" and "+Y", or "+X"
and "+Z"), as C3D readers take them. The file's frames start at 1 whatever the run's first input frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ptrack.errors import InputError
from ptrack.io.markers import Markers, markers
from ptrack.io.run_folder import RunFolder


def import_ezc3d():
    """The `ezc3d` module; InputError naming the extra when it is absent."""
    try:
        import ezc3d
    except ImportError:
        raise InputError("--format c3d needs ezc3d: pip install 'ptrack[export]' (or pip install ezc3d)") from None
    return ezc3d


def write_c3d(path: Path, m: Markers) -> None:
    """Write markers `m` (metres) to `path` as a C3D file in millimetres."""
    ezc3d = import_ezc3d()
    T, M = m.xyz.shape[:2]
    c = ezc3d.c3d()
    point = c["parameters"]["POINT"]
    point["RATE"]["value"] = [float(m.fps)]
    point["UNITS"]["value"] = ["mm"]
    point["LABELS"]["value"] = list(m.names)
    axes = "Y up (OpenSim)" if m.up == "y" else "Z up (lab)"
    source = f"{m.keypoint_set} keypoint" if m.what == "keypoints" else "skeleton joint"
    point["DESCRIPTIONS"]["value"] = [f"ptrack {source}, mm, {axes}"] * M
    c.add_parameter("POINT", "X_SCREEN", ["+X"])
    c.add_parameter("POINT", "Y_SCREEN", ["+Y" if m.up == "y" else "+Z"])
    data = np.ones((4, M, T), dtype=np.float64)
    data[:3] = (m.xyz * 1000.0).transpose(2, 1, 0)
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = np.zeros((1, M, T))
    c["data"]["meta_points"]["camera_masks"] = np.zeros((7, M, T), dtype=bool)
    c.write(str(path))


def export_c3d(run: RunFolder, out_dir: Path, options) -> list[Path]:
    """`ptrack export --format c3d` (an `ptrack.io.exporters.Writer`): result.c3d in `out_dir`."""
    import_ezc3d()  # before any work: a missing package is the first thing to say
    if options.opensim is not None:
        raise InputError("--opensim applies to --format mot only")
    path = out_dir / "result.c3d"
    write_c3d(path, markers(run, options.points, options.up or "y"))
    return [path]
