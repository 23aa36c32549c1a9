"""Camera calibration files: what a calibrated (or uncalibrated) real camera gives ptrack.

`read_cameras(path)` reads every camera of a file, `read_camera(path, name)` one of them, as
`CameraFile` records (numpy float64, OpenCV conventions). `to_camera` turns one into ptrack's pinhole
`Camera`; `undistort_points` removes the lens distortion from detected keypoints first (ptrack's
camera has none). `default_intrinsics` is the camera of a video nobody calibrated.

Conventions (all formats): pixels (u right, v down); the camera frame is OpenCV's (x right, y down,
z forward); extrinsics are world -> camera, ``x_cam = R @ x_world + t``, t in metres (ptrack does
not rescale: a calibration made with a board measured in millimetres must be converted first).
Distortion is OpenCV's model, coefficients in OpenCV's order ``k1, k2, p1, p2[, k3[, k4, k5, k6
[, s1, s2, s3, s4[, tau_x, tau_y]]]]`` (the tilt terms must be zero), or OpenCV's fisheye
(equidistant) model ``k1, k2, k3, k4`` when ``fisheye`` is true.

Formats, detected from the content (then the file name):

**Pose2Sim / aniposelib TOML** (``Calib*.toml``): one table per camera, other tables skipped when
they are Pose2Sim's non-camera sections (``metadata``, ``capture_volume``, ``charuco``,
``checkerboard``; Pose2Sim/common.py ``retrieve_calib_params``)::

    [cam_01]                         # aniposelib writes cam_0, cam_1, ... (CameraGroup.dump)
    name = "cam_01"
    size = [ 1088.0, 1920.0]         # width, height (aniposelib Camera.set_size: "(width, height)")
    matrix = [ [ fx, 0.0, cx], [ 0.0, fy, cy], [ 0.0, 0.0, 1.0]]
    distortions = [ k1, k2, p1, p2]  # or 5 values (aniposelib); k1..k4 when fisheye
    rotation = [ rx, ry, rz]         # Rodrigues vector, world -> camera
    translation = [ tx, ty, tz]      # metres
    fisheye = false                  # aniposelib FisheyeCamera.get_dict writes fisheye = true

(aniposelib/cameras.py ``Camera.get_dict``, ``CameraGroup.dump``; Pose2Sim/calibration.py
``toml_write``.) Pose2Sim's world is Z up: its triangulation turns it into the Y-up TRC with
``zup2yup`` unconditionally (Pose2Sim/triangulation.py, common.py), so `world_up` says +Z here.

**OpenCV FileStorage** YAML (``%YAML:1.0`` header, matrices tagged ``!!opencv-matrix`` with
``rows``, ``cols``, ``dt``, ``data`` row-major; OpenCV core docs "XML/YAML/JSON Persistence") or
its JSON form (``{"type_id": "opencv-matrix", "rows", "cols", "dt", "data"}``), or the same keys
with plain nested lists, or ROS's camera_info YAML (untagged ``rows/cols/data`` maps). One camera:

    image_width, image_height                  (or width/height, or image_size/size [w, h])
    camera_matrix | cameraMatrix | K            3 x 3
    distortion_coefficients | distCoeffs | dist_coeffs | dist | D     4, 5, 8, 12 or 14 values
    rvec + tvec  or  R + T (t)                  optional; R is a Rodrigues 3-vector or a 3 x 3 matrix
    camera_name                                 optional (default: the file's stem)
    distortion_model: equidistant | fisheye     optional (ROS's name for OpenCV's fisheye model),
    or fisheye: true

**EasyMocap** ``intri.yml`` + ``extri.yml`` (OpenCV FileStorage; easymocap/mytools/camera_utils.py
``write_intri``, ``write_extri``, ``read_camera``): ``names`` (a list of camera names), in intri
``K_<name>`` (3 x 3), ``dist_<name>`` or ``D_<name>`` (1 x 5), optional ``H_<name>``, ``W_<name>``;
in extri ``R_<name>`` (Rodrigues 3 x 1, which EasyMocap's reader uses) or ``Rot_<name>`` (3 x 3),
and ``T_<name>`` (3 x 1, metres). Give the folder holding both, or either file (the other one is
looked for beside it; intri alone gives intrinsics only). EasyMocap's world frame has no fixed up
axis (it is the calibration board's), so `world_up` says None unless told.

Names (`read_camera(path, name)`): a name selects the camera whose TOML section or ``name`` field
(EasyMocap: its entry of ``names``) equals it; failing that, the one equal after normalising both
(case folded, ``_ - . space`` removed, leading zeros of numbers dropped: ``cam01``, ``CAM_1`` and
``cam_01`` are the same); failing that, a bare number ``N`` selects the camera whose name ends in the
number N (``1`` -> ``cam_01``). Two cameras matching at the same step, or none, is an `InputError`
listing the file's names.
"""

from __future__ import annotations

import json
import logging
import math
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from torch import Tensor

from ptrack.body.rotations import axis_angle_matrix
from ptrack.errors import InputError
from ptrack.observe.camera import ROTATION_TOL, Camera

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

log = logging.getLogger(__name__)

#: the diagonal field of view of the default focal length sqrt(W^2 + H^2): 2 atan(1/2) = 53.13 degrees
DEFAULT_DIAGONAL_FOV_DEG = math.degrees(2.0 * math.atan(0.5))

#: Pose2Sim's top-level TOML tables that are not cameras (Pose2Sim/common.py retrieve_calib_params)
_TOML_NOT_CAMERAS = ("metadata", "capture_volume", "charuco", "checkerboard")
#: numbers of OpenCV distortion coefficients (cv::projectPoints: 4, 5, 8, 12 or 14)
_DIST_SIZES = (4, 5, 8, 12, 14)

# one-camera OpenCV files: accepted keys, first found wins
_K_KEYS = ("camera_matrix", "cameraMatrix", "K")
_DIST_KEYS = ("distortion_coefficients", "distCoeffs", "dist_coeffs", "dist", "D")
_ROT_KEYS = ("rvec", "R")
_TRANS_KEYS = ("tvec", "T", "t")


@dataclass(frozen=True, eq=False)
class CameraFile:
    """One camera of a calibration file, validated (numpy float64, read-only arrays).

    name: the camera's name. width, height: image size in pixels, None when the file does not say.
    K: (3, 3) ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, fx, fy > 0.
    dist: (n,) OpenCV distortion coefficients (n in 4, 5, 8, 12, 14; 4 when fisheye), zeros if none.
    R: (3, 3) rotation world -> camera, t: (3,) metres, ``x_cam = R @ x_world + t``; both None when
    the file has no extrinsics. fisheye: OpenCV's fisheye model instead of the standard one.
    source: the file it was read from. file_format: "pose2sim-toml", "opencv" or "easymocap" (or
    any other label for a camera built in code).

    Invalid values raise `InputError` naming the source, the camera and the problem.
    """

    name: str
    width: int | None
    height: int | None
    K: np.ndarray
    dist: np.ndarray
    R: np.ndarray | None
    t: np.ndarray | None
    fisheye: bool = False
    source: str = ""
    file_format: str = ""

    def __post_init__(self) -> None:
        where = f"{self.source}: camera {self.name!r}" if self.source else f"camera {self.name!r}"
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"{self.source}: a camera needs a non-empty name, got {self.name!r}")
        for key in ("width", "height"):
            value = getattr(self, key)
            if value is not None:
                object.__setattr__(self, key, _positive_int(value, f"{where}: image {key}"))
        K = _float_array(self.K, f"{where}: K")
        if K.shape != (3, 3):
            raise InputError(f"{where}: K must be 3 x 3, got shape {K.shape}")
        if K[2].tolist() != [0.0, 0.0, 1.0] or K[1, 0] != 0.0:
            raise InputError(f"{where}: K must be upper triangular [[fx, s, cx], [0, fy, cy], [0, 0, 1]]: {K.tolist()}")
        if not (K[0, 0] > 0.0 and K[1, 1] > 0.0):
            raise InputError(f"{where}: K is singular or has a non-positive focal length (fx, fy > 0): {K.tolist()}")
        dist = _float_array(self.dist, f"{where}: distortion").reshape(-1)
        sizes = (4,) if self.fisheye else _DIST_SIZES
        if dist.size not in sizes:
            model, takes = ("fisheye k1..k4", "4") if self.fisheye else ("OpenCV's model", "4, 5, 8, 12 or 14")
            raise InputError(f"{where}: {dist.size} distortion coefficients, {model} takes {takes}")
        if dist.size == 14 and (dist[12] != 0.0 or dist[13] != 0.0):
            raise InputError(f"{where}: the tilted-sensor distortion terms (tau_x, tau_y) are not supported")
        if (self.R is None) != (self.t is None):
            raise InputError(f"{where}: extrinsics need both a rotation and a translation")
        R = t = None
        if self.R is not None and self.t is not None:
            R = _float_array(self.R, f"{where}: rotation")
            t = _float_array(self.t, f"{where}: translation").reshape(-1)
            if R.shape != (3, 3):
                raise InputError(f"{where}: rotation matrix must be 3 x 3, got shape {R.shape}")
            if t.shape != (3,):
                raise InputError(f"{where}: translation must have 3 values, got {t.size}")
            ortho = float(np.abs(R @ R.T - np.eye(3)).max())
            det = float(np.linalg.det(R))
            if ortho > ROTATION_TOL or abs(det - 1.0) > ROTATION_TOL:
                raise InputError(f"{where}: R is not a rotation: |R R^T - I| = {ortho:.3g}, det = {det:.6g}")
        for key, value in (("K", K), ("dist", dist), ("R", R), ("t", t)):
            if value is not None:
                value.flags.writeable = False
            object.__setattr__(self, key, value)
        object.__setattr__(self, "fisheye", bool(self.fisheye))

    @property
    def has_extrinsics(self) -> bool:
        """Whether the file gave R and t."""
        return self.R is not None


# -- reading -----------------------------------------------------------------------------------


def read_cameras(path: str | Path) -> dict[str, CameraFile]:
    """Every camera of a calibration file (or an EasyMocap folder), by name, in file order.

    The keys are the TOML section names (``cam_01``), the EasyMocap ``names`` or, for a one-camera
    OpenCV file, its ``camera_name`` or the file's stem. A missing or unreadable file, an unknown
    layout, a camera without intrinsics or with invalid values raise `InputError` naming the file.
    """
    path = Path(path)
    if path.is_dir():
        return _read_easymocap_folder(path)
    text = _read_text(path)
    head = text.lstrip("\ufeff \t\r\n")
    suffix = path.suffix.lower()
    if head.startswith("%YAML") or head.startswith("---"):
        kind = "yaml"
    elif head.startswith("{"):
        kind = "json"
    elif suffix == ".toml" or head.startswith("["):
        kind = "toml"
    elif suffix == ".json":
        kind = "json"
    else:
        kind = "yaml"
    if kind == "toml":
        return _read_toml(path, text)
    data, _ = _load_json(path, text) if kind == "json" else _load_opencv_yaml(path, text)
    if not isinstance(data, Mapping):
        raise InputError(f"{path}: not a camera file (expected a mapping of keys, got {type(data).__name__})")
    if "names" in data:
        return _read_easymocap_file(path, data)
    cam = _opencv_camera(path, data)
    return {cam.name: cam}


def read_camera(path: str | Path, name: str | int | None = None) -> CameraFile:
    """One camera of a calibration file: `name` (see the module docstring for how names match), or
    the file's only camera when `name` is None. An `InputError` lists the file's cameras when the
    name matches none, or several, or when `name` is None and the file has more than one."""
    cameras = read_cameras(path)
    if name is None:
        if len(cameras) == 1:
            return next(iter(cameras.values()))
        raise InputError(f"{path} holds {len(cameras)} cameras ({_listing(cameras)}): give the name of one")
    return cameras[_find_name(cameras, str(name), path)]


def _listing(cameras: Mapping[str, CameraFile]) -> str:
    return ", ".join(key if cam.name == key else f"{key} (name {cam.name!r})" for key, cam in cameras.items())


def _normalise(name: str) -> str:
    """Case folded, separators removed, leading zeros of numbers dropped: cam_01 -> cam1."""
    s = re.sub(r"[\s_.\-]", "", name.casefold())
    return re.sub(r"\d+", lambda m: str(int(m.group())), s)


def _find_name(cameras: Mapping[str, CameraFile], name: str, path: str | Path) -> str:
    """The key of the one camera `name` selects (module docstring: exact, normalised, number)."""
    trailing = re.compile(r"(\d+)\D*$")

    def ends_in(label: str, number: int) -> bool:
        m = trailing.search(label)
        return m is not None and int(m.group(1)) == number

    steps = [
        lambda key, cam: name in (key, cam.name),
        lambda key, cam: _normalise(name) in (_normalise(key), _normalise(cam.name)),
    ]
    if name.strip().isdigit():
        number = int(name)
        steps.append(lambda key, cam: ends_in(key, number) or ends_in(cam.name, number))
    for matches_at in steps:
        found = [key for key, cam in cameras.items() if matches_at(key, cam)]
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise InputError(f"{path}: camera name {name!r} is ambiguous, it matches {', '.join(found)}")
    raise InputError(f"{path} has no camera {name!r}; its cameras: {_listing(cameras)}")


def _read_text(path: Path) -> str:
    if not path.exists():
        raise InputError(f"camera file not found: {path}")
    if not path.is_file():
        raise InputError(f"camera file is not a file: {path}")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not a text camera file ({e.reason} at byte {e.start})") from e
    except OSError as e:
        raise InputError(f"cannot read camera file {path}: {e.strerror}") from e


def _one_line(message: str) -> str:
    return " ".join(str(message).split())


# -- Pose2Sim / aniposelib TOML ------------------------------------------------------------------


def _read_toml(path: Path, text: str) -> dict[str, CameraFile]:
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML: {_one_line(str(e))}") from e
    cameras = {}
    for key, table in doc.items():
        if key in _TOML_NOT_CAMERAS or not isinstance(table, dict):
            continue
        where = f"{path}: [{key}]"
        if "matrix" not in table:
            raise InputError(f"{where} has no intrinsics (no 'matrix' key)")
        name = table.get("name", key)
        size = table.get("size")
        width = height = None
        if size is not None:
            wh = _float_array(size, f"{where} size").reshape(-1)
            if wh.shape != (2,):
                raise InputError(f"{where}: size must be [width, height], got {size!r}")
            width, height = _positive_int(wh[0], f"{where} width"), _positive_int(wh[1], f"{where} height")
        fisheye = table.get("fisheye", False)
        if not isinstance(fisheye, bool):
            raise InputError(f"{where}: fisheye must be true or false, got {fisheye!r}")
        R = t = None
        if "rotation" in table or "translation" in table:
            if "rotation" not in table or "translation" not in table:
                raise InputError(f"{where}: extrinsics need both 'rotation' and 'translation'")
            R = _rotation(table["rotation"], f"{where} rotation", matrix_allowed=False)
            t = _float_array(table["translation"], f"{where} translation")
        dist = table.get("distortions")
        cameras[key] = CameraFile(
            name=str(name),
            width=width,
            height=height,
            K=_float_array(table["matrix"], f"{where} matrix"),
            dist=np.zeros(4 if fisheye else 5) if dist is None else _float_array(dist, f"{where} distortions"),
            R=R,
            t=t,
            fisheye=fisheye,
            source=str(path),
            file_format="pose2sim-toml",
        )
    if not cameras:
        raise InputError(f"{path}: no camera sections (tables with a 'matrix') in this TOML file")
    return cameras


# -- OpenCV FileStorage YAML / JSON --------------------------------------------------------------


class _MatrixError(ValueError):
    pass


class _OpenCVLoader(yaml.SafeLoader):
    """PyYAML's safe loader plus OpenCV's ``!!opencv-matrix`` and ``!!opencv-nd-matrix`` tags."""


def _construct_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> np.ndarray:
    if not isinstance(node, yaml.MappingNode):
        raise _MatrixError(f"line {node.start_mark.line + 1}: an opencv-matrix must be a mapping")
    fields = loader.construct_mapping(node, deep=True)
    return _matrix_from_fields(fields, f"line {node.start_mark.line + 1}")


def _construct_nd_matrix(loader: yaml.SafeLoader, node: yaml.Node) -> np.ndarray:
    if not isinstance(node, yaml.MappingNode):
        raise _MatrixError(f"line {node.start_mark.line + 1}: an opencv-nd-matrix must be a mapping")
    fields = loader.construct_mapping(node, deep=True)
    sizes, data = fields.get("sizes"), fields.get("data")
    try:
        shape = tuple(int(s) for s in sizes)  # type: ignore[union-attr]
        return np.asarray(data, dtype=np.float64).reshape(shape)
    except (TypeError, ValueError) as e:
        raise _MatrixError(f"line {node.start_mark.line + 1}: bad opencv-nd-matrix ({e})") from e


_OpenCVLoader.add_constructor("tag:yaml.org,2002:opencv-matrix", _construct_matrix)
_OpenCVLoader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix", _construct_nd_matrix)


def _matrix_from_fields(fields: Mapping[Any, Any], where: str) -> np.ndarray:
    """An OpenCV matrix ``{rows, cols, dt, data}`` -> (rows, cols * channels) float64; ``dt`` is the
    element type with an optional channel count in front ("d", "3d": a matrix of 3-vectors)."""
    try:
        rows, cols = int(fields["rows"]), int(fields["cols"])
        data = np.asarray(fields["data"], dtype=np.float64).reshape(-1)
    except KeyError as e:
        raise _MatrixError(f"{where}: an OpenCV matrix needs rows, cols and data, {e} is missing") from e
    except (TypeError, ValueError) as e:
        raise _MatrixError(f"{where}: an OpenCV matrix with non-numeric rows, cols or data ({e})") from e
    counted = re.match(r"\s*(\d+)", str(fields.get("dt", "")))
    channels = int(counted.group(1)) if counted else 1
    if data.size != rows * cols * channels:
        shape = f"{rows} x {cols}" + (f" x {channels} channels" if channels > 1 else "")
        raise _MatrixError(f"{where}: an OpenCV matrix of {shape} with {data.size} values")
    return data.reshape(rows, cols * channels)


def _load_opencv_yaml(path: Path, text: str) -> tuple[Any, list[str] | None]:
    """(the document, the raw text of the ``names`` entries if any). PyYAML refuses OpenCV's
    ``%YAML:1.0`` directive (YAML writes ``%YAML 1.0``), so that line is dropped first."""
    body = re.sub(r"\A\ufeff?\s*%YAML[:\s]\s*\d+\.\d+[^\n]*\n", "", text)
    loader = _OpenCVLoader(body)
    try:
        node = loader.get_single_node()
        data = loader.construct_document(node) if node is not None else None
    except _MatrixError as e:
        raise InputError(f"{path}: {e}") from e
    except yaml.YAMLError as e:
        raise InputError(f"{path}: not a valid OpenCV YAML file: {_one_line(str(e))}") from e
    finally:
        loader.dispose()
    raw_names = None
    # the names as written: an unquoted `- 01` would otherwise become the integer 1, not "01"
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            if key_node.value == "names" and isinstance(value_node, yaml.SequenceNode):
                raw_names = [v.value for v in value_node.value if isinstance(v, yaml.ScalarNode)]
    return data, raw_names


def _load_json(path: Path, text: str) -> tuple[Any, list[str] | None]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON: {e.msg} (line {e.lineno})") from e

    def matrices(x: Any) -> Any:  # OpenCV's JSON form of a matrix: {"type_id": "opencv-matrix", ...}
        if isinstance(x, dict):
            if x.get("type_id") == "opencv-matrix":
                try:
                    return _matrix_from_fields(x, "a matrix")
                except _MatrixError as e:
                    raise InputError(f"{path}: {e}") from e
            return {k: matrices(v) for k, v in x.items()}
        return x

    data = matrices(data)
    names = data.get("names") if isinstance(data, dict) else None
    return data, [str(n) for n in names] if isinstance(names, list) else None


def _first(data: Mapping[str, Any], keys: Sequence[str]) -> tuple[str, Any] | tuple[None, None]:
    for key in keys:
        if key in data and data[key] is not None:
            return key, data[key]
    return None, None


def _opencv_camera(path: Path, data: Mapping[str, Any]) -> CameraFile:
    where = str(path)
    k_key, K = _first(data, _K_KEYS)
    if k_key is None:
        raise InputError(f"{path}: a camera without intrinsics: none of the keys {', '.join(_K_KEYS)}")
    d_key, dist = _first(data, _DIST_KEYS)
    width, height = _opencv_size(path, data)
    model = str(data.get("distortion_model", "")).lower()
    fisheye = model in ("equidistant", "fisheye") or data.get("fisheye") is True
    r_key, rot = _first(data, _ROT_KEYS)
    t_key, trans = _first(data, _TRANS_KEYS)
    if (r_key is None) != (t_key is None):
        given, missing = (r_key, "/".join(_TRANS_KEYS)) if t_key is None else (t_key, "/".join(_ROT_KEYS))
        raise InputError(f"{path}: extrinsics need a rotation and a translation: has {given!r}, no {missing}")
    name = data.get("camera_name")
    return CameraFile(
        name=str(name) if name else path.stem,
        width=width,
        height=height,
        K=_float_array(K, f"{where} {k_key}"),
        dist=np.zeros(4 if fisheye else 5) if d_key is None else _float_array(dist, f"{where} {d_key}"),
        R=None if rot is None else _rotation(rot, f"{where} {r_key}", matrix_allowed=True),
        t=None if trans is None else _float_array(trans, f"{where} {t_key}"),
        fisheye=fisheye,
        source=str(path),
        file_format="opencv",
    )


def _opencv_size(path: Path, data: Mapping[str, Any]) -> tuple[int | None, int | None]:
    for wkey, hkey in (("image_width", "image_height"), ("width", "height")):
        if wkey in data or hkey in data:
            if wkey not in data or hkey not in data:
                raise InputError(f"{path}: image size needs both {wkey} and {hkey}")
            return _positive_int(data[wkey], f"{path} {wkey}"), _positive_int(data[hkey], f"{path} {hkey}")
    _, size = _first(data, ("image_size", "imageSize", "size"))
    if size is None:
        return None, None
    wh = _float_array(size, f"{path} image size").reshape(-1)
    if wh.shape != (2,):
        raise InputError(f"{path}: image size must be [width, height], got {np.asarray(size).tolist()}")
    return _positive_int(wh[0], f"{path} image width"), _positive_int(wh[1], f"{path} image height")


# -- EasyMocap intri.yml / extri.yml ------------------------------------------------------------


def _easymocap_pair(path: Path, data: Mapping[str, Any]) -> tuple[Path | None, Path | None]:
    """(intri, extri) paths for a file that is one of them; the other is looked for beside it."""
    names = data.get("names") or []
    is_intri = any(f"K_{n}" in data for n in names) or "intri" in path.name
    if is_intri:
        if any(f"T_{n}" in data for n in names):  # intrinsics and extrinsics in one file
            return path, path
        other = path.with_name(path.name.replace("intri", "extri")) if "intri" in path.name else None
        return path, other if other is not None and other != path and other.is_file() else None
    other = path.with_name(path.name.replace("extri", "intri")) if "extri" in path.name else None
    return (other if other is not None and other != path and other.is_file() else None), path


def _read_easymocap_folder(folder: Path) -> dict[str, CameraFile]:
    intri = next((folder / n for n in ("intri.yml", "intri.yaml") if (folder / n).is_file()), None)
    extri = next((folder / n for n in ("extri.yml", "extri.yaml") if (folder / n).is_file()), None)
    if intri is None:
        raise InputError(f"camera folder {folder} has no intri.yml (EasyMocap's intrinsics file)")
    return _read_easymocap(intri, extri)


def _read_easymocap_file(path: Path, data: Mapping[str, Any]) -> dict[str, CameraFile]:
    intri, extri = _easymocap_pair(path, data)
    if intri is None:
        raise InputError(
            f"{path}: a camera without intrinsics: an EasyMocap extri file (R_/T_) with no intri.yml beside it"
        )
    return _read_easymocap(intri, extri)


def _easymocap_doc(path: Path) -> tuple[Mapping[str, Any], list[str]]:
    text = _read_text(path)
    data, raw = _load_json(path, text) if text.lstrip().startswith("{") else _load_opencv_yaml(path, text)
    if not isinstance(data, Mapping) or not isinstance(data.get("names"), list):
        raise InputError(f"{path}: not an EasyMocap camera file (no 'names' list)")
    names = raw if raw is not None and len(raw) == len(data["names"]) else [str(n) for n in data["names"]]
    return data, names


def _read_easymocap(intri_path: Path, extri_path: Path | None) -> dict[str, CameraFile]:
    intri, names = _easymocap_doc(intri_path)
    extri: Mapping[str, Any] = {}
    if extri_path is not None:
        extri, extri_names = _easymocap_doc(extri_path)
        missing = [n for n in names if n not in extri_names]
        if missing:
            raise InputError(f"{extri_path}: no extrinsics for camera(s) {', '.join(missing)} of {intri_path}")
    if not names:
        raise InputError(f"{intri_path}: the 'names' list is empty")
    cameras = {}
    for name in names:
        where = f"{intri_path}: camera {name!r}"
        if f"K_{name}" not in intri:
            raise InputError(f"{where} has no intrinsics (no K_{name})")
        d_key, dist = _first(intri, (f"dist_{name}", f"D_{name}"))
        width = height = None
        if f"W_{name}" in intri and f"H_{name}" in intri:
            width = _positive_int(intri[f"W_{name}"], f"{where} W_{name}")
            height = _positive_int(intri[f"H_{name}"], f"{where} H_{name}")
        R = t = None
        if extri_path is not None:
            ewhere = f"{extri_path}: camera {name!r}"
            r_key, rot = _first(extri, (f"R_{name}", f"Rot_{name}"))
            if r_key is None or f"T_{name}" not in extri:
                raise InputError(f"{ewhere} needs R_{name} (or Rot_{name}) and T_{name}")
            R = _rotation(rot, f"{extri_path} {r_key}", matrix_allowed=True)
            t = _float_array(extri[f"T_{name}"], f"{extri_path} T_{name}")
        cameras[name] = CameraFile(
            name=name,
            width=width,
            height=height,
            K=_float_array(intri[f"K_{name}"], f"{intri_path} K_{name}"),
            dist=np.zeros(5) if d_key is None else _float_array(dist, f"{intri_path} {d_key}"),
            R=R,
            t=t,
            fisheye=False,
            source=str(intri_path) if extri_path in (None, intri_path) else f"{intri_path} + {extri_path.name}",
            file_format="easymocap",
        )
    return cameras


# -- value checks --------------------------------------------------------------------------------


def _float_array(value: Any, what: str) -> np.ndarray:
    if isinstance(value, Mapping):  # an untagged OpenCV / ROS matrix {rows, cols, data}
        try:
            value = _matrix_from_fields(value, what)
        except _MatrixError as e:
            raise InputError(str(e)) from e
    if _has_non_number(value):  # numpy would read "500" as 500.0
        raise InputError(f"{what}: expected numbers, got {value!r}")
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: expected numbers ({_one_line(str(e))})") from e
    if not np.isfinite(arr).all():
        raise InputError(f"{what}: non-finite values {arr.tolist()}")
    return arr


def _has_non_number(value: Any) -> bool:
    if isinstance(value, (list, tuple)):
        return any(_has_non_number(v) for v in value)
    return isinstance(value, (str, bytes, bool)) or value is None


def _positive_int(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{what} must be a positive whole number, got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0 and float(value) == int(value)):
        raise InputError(f"{what} must be a positive whole number, got {value!r}")
    return int(value)


def rodrigues(rvec: Any) -> np.ndarray:
    """Rotation matrix of a Rodrigues (axis-angle) vector, OpenCV's ``cv::Rodrigues``: (3,) -> (3, 3)."""
    r = np.asarray(rvec, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(r))
    if angle == 0.0:
        return np.eye(3)
    axis = torch.from_numpy(r / angle)
    return axis_angle_matrix(axis, torch.tensor(angle, dtype=torch.float64)).numpy()


def _rotation(value: Any, what: str, matrix_allowed: bool) -> np.ndarray:
    """A Rodrigues vector (3 values) or, where allowed, a 3 x 3 matrix -> (3, 3)."""
    arr = _float_array(value, what)
    if arr.size == 3:
        return rodrigues(arr)
    if matrix_allowed and arr.size == 9:
        return arr.reshape(3, 3)
    expected = "a Rodrigues vector (3 values) or a 3 x 3 matrix" if matrix_allowed else "a Rodrigues vector (3 values)"
    raise InputError(f"{what}: expected {expected}, got shape {arr.shape}")


# -- distortion ----------------------------------------------------------------------------------


def _as_points(xy: Any, what: str) -> np.ndarray:
    if isinstance(xy, Tensor):
        xy = xy.detach().cpu().numpy()
    try:
        arr = np.array(xy, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: points must be numbers ({_one_line(str(e))})") from e
    if arr.ndim == 0 or arr.shape[-1] != 2:
        raise InputError(f"{what}: points must have shape (..., 2), got {arr.shape}")
    return arr


def _like_input(out: np.ndarray, xy: Any) -> np.ndarray | Tensor:
    if isinstance(xy, Tensor):
        dtype = xy.dtype if xy.is_floating_point() else torch.get_default_dtype()
        return torch.from_numpy(out).to(device=xy.device, dtype=dtype)
    return out


def _pixels_to_normalised(xy: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = (xy[..., 1] - K[1, 2]) / K[1, 1]
    x = (xy[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return x, y


def _normalised_to_pixels(x: np.ndarray, y: np.ndarray, K: np.ndarray) -> np.ndarray:
    return np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=-1)


def _coefficients(cam: CameraFile) -> np.ndarray:
    out = np.zeros(14)
    out[: cam.dist.size] = cam.dist
    return out


def _distort_normalised(x: np.ndarray, y: np.ndarray, cam: CameraFile) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's forward models on the z = 1 plane (cv::projectPoints, cv::fisheye::projectPoints)."""
    if cam.fisheye:
        k1, k2, k3, k4 = cam.dist
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = np.where(r > 1e-8, theta_d / np.where(r > 1e-8, r, 1.0), 1.0)
        return x * scale, y * scale
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _coefficients(cam)[:12]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
    return xd, yd


def distort_points(xy: Any, cam: CameraFile) -> np.ndarray | Tensor:
    """Ideal pinhole pixels to the pixels the lens makes, OpenCV's distortion model (the forward map
    `undistort_points` inverts): xy (..., 2) -> (..., 2), with the camera's K both ways.

    Numpy (float64) in and out, or a tensor of the input's dtype and device (not differentiable).
    """
    arr = _as_points(xy, "distort_points")
    x, y = _pixels_to_normalised(arr, cam.K)
    xd, yd = _distort_normalised(x, y, cam)
    return _like_input(_normalised_to_pixels(xd, yd, cam.K), xy)


def undistort_points(
    xy: Any, cam: CameraFile, max_iter: int = 200, tol: float = 1e-14, max_error_px: float = 1e-3
) -> np.ndarray | Tensor:
    """Remove the lens distortion from pixel coordinates: xy (..., 2) -> (..., 2) pixels of the ideal
    pinhole camera with the same K (`to_camera(cam)`), i.e. ``cv2.undistortPoints(xy, K, dist, P=K)``.

    The standard model is inverted by OpenCV's fixed-point iteration (cvUndistortPointsInternal:
    ``x <- (x0 - tangential(x)) / radial(x)``), the fisheye model by OpenCV's Newton iteration on the
    ray angle (cv::fisheye::undistortPoints), both run until the step is below `tol` (normalised
    units) or `max_iter` steps, where OpenCV stops after 5 by default. K's skew is honoured (OpenCV
    ignores it; the same when it is 0). A point whose result does not distort back to within
    `max_error_px` of the input (outside the region where the model can be inverted, e.g. far beyond
    the image of a strongly distorted lens) comes back NaN and is logged; NaN inputs stay NaN.
    Numpy (float64) in and out, or a tensor of the input's dtype and device (not differentiable).
    """
    if max_iter < 1 or not tol > 0 or not max_error_px > 0:
        raise InputError(
            f"undistort_points: needs max_iter >= 1, tol > 0, max_error_px > 0: {max_iter}, {tol}, {max_error_px}"
        )
    arr = _as_points(xy, "undistort_points")
    if not cam.dist.any():
        return _like_input(arr.copy(), xy)
    x0, y0 = _pixels_to_normalised(arr, cam.K)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        x, y, bad = (
            _undistort_fisheye(x0, y0, cam, max_iter, tol)
            if cam.fisheye
            else _undistort_standard(x0, y0, cam, max_iter, tol)
        )
        out = _normalised_to_pixels(x, y, cam.K)
        back = _normalised_to_pixels(*_distort_normalised(x, y, cam), cam.K)
        error = np.linalg.norm(back - arr, axis=-1)
        failed = (bad | ~(error <= max_error_px)) & np.isfinite(arr).all(axis=-1)
    if failed.any():
        log.warning(
            "%s: %d of %d points could not be undistorted (outside the region where the lens model inverts): NaN",
            cam.name,
            int(failed.sum()),
            failed.size,
        )
        out[failed] = np.nan
    return _like_input(out, xy)


def _undistort_standard(
    x0: np.ndarray, y0: np.ndarray, cam: CameraFile, max_iter: int, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _coefficients(cam)[:12]
    x, y = x0.copy(), y0.copy()
    bad = np.zeros(x0.shape, dtype=bool)
    for _ in range(max_iter):
        r2 = x * x + y * y
        icdist = (1 + r2 * (k4 + r2 * (k5 + r2 * k6))) / (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        bad |= icdist < 0  # OpenCV gives up on such a point (regression_14583)
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
        xn, yn = (x0 - dx) * icdist, (y0 - dy) * icdist
        step = np.maximum(np.abs(xn - x), np.abs(yn - y))
        x, y = xn, yn
        if not (step[np.isfinite(step)] > tol).any():
            break
    return x, y, bad


def _undistort_fisheye(
    x0: np.ndarray, y0: np.ndarray, cam: CameraFile, max_iter: int, tol: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    k1, k2, k3, k4 = cam.dist
    theta_d = np.minimum(np.hypot(x0, y0), math.pi / 2)  # the model covers less than 180 degrees
    theta = theta_d.copy()
    for _ in range(max_iter):
        t2 = theta * theta
        f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - theta_d
        df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
        fix = f / df
        theta = theta - fix
        if not (np.abs(fix)[np.isfinite(fix)] > tol).any():
            break
    bad = (theta < 0) | (theta >= math.pi / 2)  # flipped to the other side, or behind the camera
    scale = np.where(theta_d > 1e-12, np.tan(theta) / np.where(theta_d > 1e-12, theta_d, 1.0), 1.0)
    return x0 * scale, y0 * scale, bad


# -- cameras for ptrack --------------------------------------------------------------------------


def default_intrinsics(width: int, height: int, fov_deg: float | None = None) -> np.ndarray:
    """K (3, 3) float64 of a camera nobody calibrated: square pixels, no skew, principal point at
    the image centre (W/2, H/2, as `look_at` places it).

    The focal length is ``sqrt(W^2 + H^2)`` pixels when `fov_deg` is None, the convention of recent
    video-to-3D human pose tools (CLIFF's full-image camera; WHAM lib/utils/imutils.py
    ``compute_cam_intrinsics``), which is a diagonal field of view of `DEFAULT_DIAGONAL_FOV_DEG`
    (53.13 degrees). `fov_deg` is the **diagonal** field of view in degrees (0 < fov < 180), so that
    the same value means the same lens in portrait and landscape video:
    ``f = sqrt(W^2 + H^2) / 2 / tan(fov / 2)``.
    """
    width = _positive_int(width, "default_intrinsics: width")
    height = _positive_int(height, "default_intrinsics: height")
    diagonal = math.hypot(width, height)
    if fov_deg is None:
        focal = diagonal
    else:
        if isinstance(fov_deg, bool) or not isinstance(fov_deg, (int, float)) or not 0.0 < fov_deg < 180.0:
            raise InputError(f"camera field of view must be in (0, 180) degrees (diagonal), got {fov_deg!r}")
        focal = diagonal / 2.0 / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])


def to_camera(
    cam: CameraFile,
    extrinsics: bool = True,
    width: int | None = None,
    height: int | None = None,
    dtype: torch.dtype | None = None,
) -> Camera:
    """ptrack's pinhole `Camera` of a calibration (no distortion: give it `undistort_points`'s output).

    R, t are the file's when `extrinsics` is true and the file has them (results are then in the
    calibration's world frame), else R = I, t = 0 (the camera frame is the world). `width`, `height`
    override the file's image size (e.g. the size the video decodes at) and are required when the
    file has none. Tensors get `dtype` (default: torch's default dtype).
    """
    w = cam.width if width is None else width
    h = cam.height if height is None else height
    if w is None or h is None:
        raise InputError(f"{cam.source}: camera {cam.name!r} has no image size: give the width and height")
    use = extrinsics and cam.R is not None and cam.t is not None
    R = cam.R if use and cam.R is not None else np.eye(3)
    t = cam.t if use and cam.t is not None else np.zeros(3)
    dtype = dtype or torch.get_default_dtype()
    return Camera(
        K=torch.tensor(cam.K, dtype=dtype),
        R=torch.tensor(R, dtype=dtype),
        t=torch.tensor(t, dtype=dtype),
        width=w,
        height=h,
    )


_AXES = {"x": 0, "y": 1, "z": 2}


def world_up(cam: CameraFile, up: str | Sequence[float] | None = None) -> np.ndarray | None:
    """The calibration world's up direction, a unit (3,) float64 vector in world coordinates, or
    None when unknown (then a caller estimates it, e.g. from the person).

    `up` states it: an axis ``"x" "y" "z"`` with an optional sign (``"-y"``) or a 3-vector. Without
    it: +Z for Pose2Sim TOML files (Pose2Sim's world is Z up, see the module docstring), None for
    the other formats (OpenCV and EasyMocap worlds are wherever the calibration board was) and for
    any camera without extrinsics.
    """
    if up is not None:
        if isinstance(up, str):
            m = re.fullmatch(r"\s*([+-]?)\s*([xyzXYZ])\s*", up)
            if m is None:
                raise InputError(f"up axis must be x, y or z with an optional sign, got {up!r}")
            v = np.zeros(3)
            v[_AXES[m.group(2).lower()]] = -1.0 if m.group(1) == "-" else 1.0
            return v
        v = _float_array(up, "up vector").reshape(-1)
        norm = float(np.linalg.norm(v)) if v.shape == (3,) else 0.0
        if norm < 1e-9:
            raise InputError(f"up vector must be a non-zero 3-vector, got {np.asarray(up).tolist()}")
        return v / norm
    if cam.R is None or cam.file_format != "pose2sim-toml":
        return None
    return np.array([0.0, 0.0, 1.0])
