"""MOT: joint angles over time in OpenSim's motion layout (what `opensim.Storage` and
`opensim.TimeSeriesTable` read, and OpenSim's GUI plots).

    result
    version=1
    nRows=100
    nColumns=63
    inDegrees=yes
    ptrack joint angles: rotations in degrees, the root translation in metres ... (Y up), 60 frames per second
    endheader
    time  root.tx  root.ty ...     (tab separated)
    0     0.012    0.954   ...

`ptrack export --format mot` writes ptrack's own joint angles: result.npz's `q` under its `dof_names`, the
root translation in metres (the model frame, Y up), every rotation dof in degrees, at the times of
`ptrack.io.markers.frame_times`. With `--opensim MODEL.osim` it instead writes OpenSim's inverse kinematics
of the run's TRC on that model (`ptrack.io.opensim_ik`): the model's own coordinates.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ptrack.errors import InputError
from ptrack.io.markers import frame_times, markers
from ptrack.io.run_folder import RunFolder
from ptrack.io.trc import rate_text, write_trc


def write_mot(
    path: Path, names: list[str], times: np.ndarray, values: np.ndarray, in_degrees: bool, note: str = ""
) -> None:
    """Write an OpenSim motion file. names: (C,) column names; times: (T,) seconds; values: (T, C); note: a
    free line of the header (OpenSim's readers skip what is not key=value), e.g. the units and axes."""
    T, C = values.shape
    lines = [
        path.stem,
        "version=1",
        f"nRows={T}",
        f"nColumns={C + 1}",
        f"inDegrees={'yes' if in_degrees else 'no'}",
        *([note] if note else []),
        "endheader",
        "\t".join(["time", *names]),
    ]
    for k in range(T):
        lines.append("\t".join([f"{times[k]:.8f}", *(f"{v:.8f}" for v in values[k])]))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def ptrack_angles(run: RunFolder) -> tuple[list[str], np.ndarray]:
    """(D,) dof names and (T, D) float64 values: q with its rotation dofs in degrees, translations in metres."""
    q = run.arrays["q"].astype(np.float64).copy()
    angular = run.skeleton.angular_dofs()
    q[:, angular] = np.degrees(q[:, angular])
    return [str(n) for n in run.arrays["dof_names"]], q


def export_mot(run: RunFolder, out_dir: Path, options) -> list[Path]:
    """`ptrack export --format mot` (an `ptrack.io.exporters.Writer`): result.mot in `out_dir`, ptrack's
    angles or, with `options.opensim`, OpenSim's IK of the run's markers on that model."""
    if options.up not in (None, "y"):
        raise InputError("--up z does not apply to MOT: its angles are the model's (and OpenSim's models are Y up)")
    path = out_dir / "result.mot"
    if options.opensim is None:
        names, values = ptrack_angles(run)
        note = (
            f"ptrack joint angles: rotations in degrees, the root translation in metres along the model frame"
            f" (Y up), {rate_text(run.fps)} frames per second"
        )
        write_mot(path, names, frame_times(run), values, in_degrees=True, note=note)
        return [path]
    from ptrack.io.opensim_ik import inverse_kinematics

    trc = out_dir / "ik_markers.trc"
    write_trc(trc, markers(run, options.points, "y"))
    inverse_kinematics(options.opensim, trc, path, out_dir)
    trc.unlink()
    return [path]
