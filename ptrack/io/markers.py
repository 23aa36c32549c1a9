"""Marker trajectories for the biomechanics formats (TRC, C3D): which 3D points a run exports, under which
names, along which axes.

`markers(run, points, up)` chooses the points: "keypoints", a footage run's reconstructed keypoints (the
model's 3D estimate of every keypoint of the input format that ptrack places on the skeleton, including
the frames where the detector missed it: those are where the fitted model puts it), named as Pose2Sim's
marker sets name them (`pose2sim_names`), so that Pose2Sim's scaled OpenSim models and IK setups use them
unchanged; or "joints", the skeleton's joints under their own names (any run; the only choice for
simulated CMU runs).

Axes: ptrack's model frame is Y up (`ptrack.io.run_folder`), OpenSim's convention. `up="z"` turns it
Z up by the cyclic permutation out (X, Y, Z) = model (Z, X, Y), a rotation, so right-handed still: for a
calibration whose world is Z up (Pose2Sim, Qualisys, Vicon labs) this is the calibration's own world,
and with `up="y"` the output is that world as OpenSim's TRC files write it (TRC (X, Y, Z) = lab (Y, Z, X)).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ptrack.body.keypoint_sets import KEYPOINT_SETS
from ptrack.errors import InputError
from ptrack.io.run_folder import RunFolder

#: landmark (`ptrack.body.keypoint_sets.LANDMARKS`) -> the marker name of Pose2Sim's marker sets
#: (Pose2Sim/skeletons.py and OpenSim_Setup/Markers_*.xml of github.com/perfanalytics/pose2sim); a landmark
#: missing here keeps the format's own keypoint name
_POSE2SIM: dict[str, str] = {
    "nose": "Nose",
    "head_top": "Head",
    "upper_neck": "Neck",  # BODY_25B's UpperNeck is Pose2Sim's "Neck"
    "neck": "Neck",
    "pelvis": "Hip",
    **{
        f"{s.lower()}_{part}": f"{s}{name}"
        for s in "LR"
        for part, name in (
            ("eye", "Eye"),
            ("ear", "Ear"),
            ("shoulder", "Shoulder"),
            ("elbow", "Elbow"),
            ("wrist", "Wrist"),
            ("pinky", "Pinky"),
            ("index", "Index"),
            ("thumb", "Thumb"),
            ("hip", "Hip"),
            ("knee", "Knee"),
            ("ankle", "Ankle"),
            ("heel", "Heel"),
            ("big_toe", "BigToe"),
            ("small_toe", "SmallToe"),
            ("foot_index", "BigToe"),  # Pose2Sim's BLAZEPOSE: the foot index is the big toe
        )
    },
}
#: per keypoint set, landmarks Pose2Sim names otherwise (its BODY_25 calls MidHip "CHip")
_POSE2SIM_SET: dict[str, dict[str, str]] = {"BODY_25": {"pelvis": "CHip"}}


class Markers(NamedTuple):
    """Named 3D points over a run's frames. names: (M,); xyz: (T, M, 3) float64 metres along the axes
    `up` names ("y": the model frame; "z": see the module docstring); frames: (T,) the input's frame
    numbers; times: (T,) seconds (`frame_times`); fps: frames per second, exactly; what: "keypoints" or
    "joints"; keypoint_set: the input's keypoint set for keypoints ("" for joints)."""

    names: list[str]
    xyz: np.ndarray
    frames: np.ndarray
    times: np.ndarray
    fps: float
    up: str
    what: str
    keypoint_set: str


def frame_times(run: RunFolder) -> np.ndarray:
    """(T,) float64 seconds on the exact frame grid: a footage run's input frame number over its frame rate
    (frame 0 at 0 s, as in the video); other runs (CMU clips, every `data.stride`-th AMC frame) from their
    first frame: result.npz's `times` rounded to whole frames of `run.fps`."""
    steps = np.rint(run.arrays["times"].astype(np.float64) * run.fps)
    start = float(run.arrays["frames"][0]) if run.is_footage else 0.0
    return (start + steps - steps[0]) / run.fps


def pose2sim_names(keypoint_set: str, names: list[str]) -> list[str]:
    """The Pose2Sim marker names of a keypoint set's keypoints `names` (the set's own spelling); a keypoint
    Pose2Sim has no name for keeps its own, and so do all keypoints of a set ptrack does not know."""
    definition = KEYPOINT_SETS.get(keypoint_set)
    if definition is None:
        return list(names)
    table = {**_POSE2SIM, **_POSE2SIM_SET.get(keypoint_set, {})}
    out = []
    for name in names:
        landmark = definition.landmarks[definition.index(name)]
        out.append(table.get(landmark, name))
    return out


def model_to_up(xyz: np.ndarray, up: str) -> np.ndarray:
    """(..., 3) model frame (Y up) -> the same points with `up` ("y" or "z") up; see the module docstring."""
    if up == "y":
        return xyz
    if up == "z":
        return xyz[..., [2, 0, 1]]
    raise InputError(f"--up must be y or z, got {up!r}")


def markers(run: RunFolder, points: str | None = None, up: str = "y") -> Markers:
    """The run's marker trajectories: points "keypoints" (footage runs), "joints", or None (keypoints where
    the run has them, else joints); up: "y" or "z". Raises InputError when the run has no keypoints."""
    if points is None:
        points = "keypoints" if run.is_footage else "joints"
    if points == "keypoints":
        kp = run.keypoints_model
        if kp is None:
            raise InputError(
                f"{run.path} has no keypoints (a run on simulated observations): export --points joints instead"
            )
        keypoint_set = str((run.metrics.get("footage") or {}).get("keypoint_set", ""))
        names, xyz = pose2sim_names(keypoint_set, run.keypoint_names), kp
    elif points == "joints":
        keypoint_set, names, xyz = "", run.joint_names, run.joints
    else:
        raise InputError(f"--points must be keypoints or joints, got {points!r}")
    if len(set(names)) != len(names):
        raise InputError(f"{run.path}: the {points}' names are not unique: {', '.join(names)}")
    if not np.isfinite(xyz).all():
        raise InputError(f"{run.path / 'result.npz'}: its {points} hold non-finite values")
    return Markers(
        names=names,
        xyz=model_to_up(xyz, up),
        frames=run.arrays["frames"].astype(np.int64),
        times=frame_times(run),
        fps=run.fps,
        up=up,
        what=points,
        keypoint_set=keypoint_set,
    )
