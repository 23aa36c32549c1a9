"""OpenSim's own inverse kinematics of a TRC file on an OpenSim model (the optional `export` extra).

`inverse_kinematics(model, trc, mot)` runs `opensim.InverseKinematicsTool` with one marker task per marker
that the model and the TRC both have, all weights 1, and no coordinate tasks: the model's markers the TRC
lacks are not used (OpenSim's marker reference holds only the markers found in both). The result is the
tool's own .mot: the model's coordinates (`pelvis_tx`, `hip_flexion_r`, `knee_angle_r`, ...), rotations in
degrees, translations in metres, at the TRC's times. OpenSim is silenced: its Logger is turned off (no
opensim.log in the working folder) and what the tool prints past it goes into `work_dir` (the export's
temporary folder), then to this module's `logging` at debug level.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from ptrack.errors import InputError

log = logging.getLogger(__name__)

#: how to get the packages the biomechanics exports use
EXTRA = "pip install 'ptrack[export]'"


def import_opensim():
    """The `opensim` module with its logging turned off; InputError naming the extra when it is absent."""
    try:
        import opensim
    except ImportError:
        raise InputError(f"--opensim needs OpenSim's Python package: {EXTRA} (or pip install opensim)") from None
    opensim.Logger.setLevelString("Off")
    opensim.Logger.removeFileSink()
    return opensim


def load_model(path: str | Path):
    """An `opensim.Model` read from `path`; InputError for a file that is absent or not an OpenSim model."""
    osim = import_opensim()
    p = Path(path)
    if not p.is_file():
        raise InputError(f"--opensim {p}: no such file")
    head = p.read_bytes()[:4096].lstrip()
    if b"<OpenSimDocument" not in head and b"<Model" not in head:
        raise InputError(f"--opensim {p} is not an OpenSim model (.osim XML with an <OpenSimDocument>/<Model>)")
    try:
        model = osim.Model(str(p))
        model.initSystem()
    except Exception as e:  # OpenSim's own exception type, raised from C++
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise InputError(f"--opensim {p} is not an OpenSim model OpenSim can load: {first}") from None
    return model


def marker_names(model) -> list[str]:
    """The names of an `opensim.Model`'s markers."""
    markers = model.getMarkerSet()
    return [markers.get(i).getName() for i in range(markers.getSize())]


def inverse_kinematics(model_path: str | Path, trc: Path, mot: Path, work_dir: Path) -> list[str]:
    """Run OpenSim's IK of `trc` on the model at `model_path`, writing `mot`; side files go to `work_dir`.
    Returns the markers used. InputError when the model is not one or shares no marker with the TRC."""
    osim = import_opensim()
    model = load_model(model_path)
    table = osim.TimeSeriesTableVec3(str(trc))
    in_trc = set(table.getColumnLabels())
    used = [n for n in marker_names(model) if n in in_trc]
    if not used:
        raise InputError(
            f"--opensim {model_path}: none of the model's markers ({', '.join(marker_names(model))}) is in the "
            f"TRC ({', '.join(sorted(in_trc))}): use a model with Pose2Sim's marker names for this keypoint set"
        )
    times = table.getIndependentColumn()
    tasks = osim.IKTaskSet()
    for name in used:
        task = osim.IKMarkerTask()
        task.setName(name)
        task.setApply(True)
        task.setWeight(1.0)
        tasks.cloneAndAppend(task)
    tool = osim.InverseKinematicsTool()
    tool.setModel(model)
    tool.setName(mot.stem)
    tool.set_IKTaskSet(tasks)
    tool.setMarkerDataFileName(str(trc))
    tool.setStartTime(float(times[0]))
    tool.setEndTime(float(times[-1]))
    tool.setResultsDir(str(work_dir))
    tool.setOutputMotionFileName(str(mot))
    tool.set_report_errors(False)
    tool.set_report_marker_locations(False)
    log.debug("OpenSim IK of %s on %s with %d markers", trc, model_path, len(used))
    try:
        with _console_to(work_dir / "opensim.log"):
            ok = tool.run()
    except Exception as e:
        raise InputError(f"OpenSim's inverse kinematics failed on {model_path}: {str(e).strip()[:300]}") from None
    if not ok or not mot.is_file():
        raise InputError(f"OpenSim's inverse kinematics on {model_path} wrote no motion")
    return used


@contextlib.contextmanager
def _console_to(path: Path) -> Iterator[None]:
    """Send what C++ code writes to the process's stdout and stderr (OpenSim's tools print the model's summary
    there, past its Logger) into `path` for the block; its text is logged at debug level afterwards."""
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(path, "wb") as sink:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            try:
                yield
            finally:
                os.dup2(saved[0], 1)
                os.dup2(saved[1], 2)
    finally:
        for fd in saved:
            os.close(fd)
        if path.is_file():
            log.debug("OpenSim: %s", path.read_text(encoding="utf-8", errors="replace").strip())
