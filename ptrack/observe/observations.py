"""2D observations of a moving skeleton, and the lossy channel that produces them from 3D joints.

The channel follows DiFranco, Cham & Rehg (2001), section 2: the true 3D states go through noise,
perspective projection and deletion. `simulate_observations` projects world joints with a `Camera`,
adds Gaussian pixel noise, then deletes keypoints at random, in contiguous occlusion bursts and in
whole dropped frames, and finally replaces a fraction of the kept keypoints with gross outliers
(left/right swaps or random displacements) that still carry confidence 1, as a real detector's would.

`Observations` is the record every estimator consumes; users bring their own 2D detections as a
plain ``.npz`` archive (numpy arrays, no pickles) with these keys:

    keypoints       float (T, K, 2)  pixels (u right, v down); may be NaN where confidence is 0
    confidence      float (T, K)     in [0, 1]; 0 = missing
    times           float (T,)       seconds, strictly increasing
    keypoint_names  str   (K,)
    camera          str   ()         JSON of `Camera.to_dict()`: {"K", "R", "t", "width", "height"}
      or the arrays K (3, 3), R (3, 3), t (3,), width (), height () instead of `camera`
    masks           bool  (T, H, W)  optional silhouettes (any integer dtype: nonzero = foreground)

`load_npz(path, camera=...)` may supply the camera instead of the file.
"""

from __future__ import annotations

import json
import math
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.checks import as_float_tensor
from ptrack.errors import InputError
from ptrack.observe.camera import Camera


@dataclass(frozen=True, eq=False)
class Observations:
    """2D keypoint observations of one camera over T observation frames.

    keypoints: (T, K, 2) pixels; entries with confidence 0 may hold anything, NaN included.
    confidence: (T, K) in [0, 1], 0 = missing; converted to keypoints' dtype and device.
    times: (T,) seconds, strictly increasing (a reconstruction may have more frames than this).
    camera: the `Camera`, cast to keypoints' dtype and device.
    keypoint_names: (K,) names.
    masks: optional (T, H, W) bool silhouettes with H, W = camera.height, camera.width.

    Array-likes are converted to tensors. Inconsistent shapes, non-finite visible keypoints,
    confidence outside [0, 1], non-increasing times and all-zero confidence raise `InputError`.
    """

    keypoints: Tensor
    confidence: Tensor
    times: Tensor
    camera: Camera
    keypoint_names: tuple[str, ...]
    masks: Tensor | None = None

    def __post_init__(self) -> None:
        kp = as_float_tensor(self.keypoints, "Observations.keypoints")
        if kp.ndim != 3 or kp.shape[-1] != 2:
            raise InputError(f"Observations.keypoints must have shape (T, K, 2), got {tuple(kp.shape)}")
        T, K = kp.shape[:2]
        if T == 0 or K == 0:
            raise InputError(f"Observations.keypoints is empty, shape {tuple(kp.shape)}")
        conf = as_float_tensor(self.confidence, "Observations.confidence", like=kp)
        if tuple(conf.shape) != (T, K):
            raise InputError(
                f"Observations.confidence must have shape (T, K) = {(T, K)} to match keypoints "
                f"{tuple(kp.shape)}, got {tuple(conf.shape)}"
            )
        times = as_float_tensor(self.times, "Observations.times", like=kp)
        if tuple(times.shape) != (T,):
            raise InputError(f"Observations.times must have shape (T,) = {(T,)}, got {tuple(times.shape)}")
        if not isinstance(self.camera, Camera):
            raise InputError(f"Observations.camera must be a Camera, got {type(self.camera).__name__}")
        names = self.keypoint_names
        if isinstance(names, str) or not all(isinstance(n, str) for n in names):
            raise InputError(f"Observations.keypoint_names must be a sequence of strings, got {names!r}")
        names = tuple(names)
        if len(names) != K:
            raise InputError(f"Observations.keypoint_names must have K = {K} names, got {len(names)}")
        with torch.no_grad():
            if not bool(((conf >= 0) & (conf <= 1)).all()):
                raise InputError("Observations.confidence has values outside [0, 1] (or NaN)")
            seen = conf > 0
            if not bool(seen.any()):
                raise InputError("Observations: the camera sees none of the keypoints (all confidence 0)")
            bad = seen & ~torch.isfinite(kp).all(dim=-1)
            if bool(bad.any()):
                t, k = (int(i) for i in bad.nonzero()[0])
                raise InputError(
                    f"Observations.keypoints has NaN/inf where confidence > 0, first at frame {t}, "
                    f"keypoint {k} ({names[k]!r})"
                )
            if not bool(torch.isfinite(times).all()):
                raise InputError("Observations.times has non-finite values")
            if T > 1 and not bool((times[1:] > times[:-1]).all()):
                t = int((times[1:] <= times[:-1]).nonzero()[0])
                raise InputError(
                    f"Observations.times must be strictly increasing, got {float(times[t])} then "
                    f"{float(times[t + 1])} at frames {t}, {t + 1}"
                )
        masks = self.masks
        if masks is not None:
            masks = torch.as_tensor(masks, device=kp.device)
            expected = (T, self.camera.height, self.camera.width)
            if tuple(masks.shape) != expected:
                raise InputError(
                    f"Observations.masks must have shape (T, H, W) = {expected} (camera "
                    f"{self.camera.width}x{self.camera.height}), got {tuple(masks.shape)}"
                )
            if masks.dtype != torch.bool:
                raise InputError(f"Observations.masks must be bool, got {masks.dtype}")
        object.__setattr__(self, "keypoints", kp)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "camera", self.camera.to(kp.device, kp.dtype))
        object.__setattr__(self, "keypoint_names", names)
        object.__setattr__(self, "masks", masks)

    @property
    def num_frames(self) -> int:
        return self.keypoints.shape[0]

    @property
    def frame_interval(self) -> float:
        """Seconds between observed frames: the median step of `times` (1/30 for a single frame)."""
        times = self.times.detach().double()
        return float(torch.median(times[1:] - times[:-1])) if times.numel() > 1 else 1.0 / 30

    @property
    def num_keypoints(self) -> int:
        return self.keypoints.shape[1]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Observations:
        """A copy on ``device`` with floating tensors (and the camera) cast to ``dtype``."""
        masks = None if self.masks is None else self.masks.to(device)
        return Observations(
            keypoints=self.keypoints.to(device=device, dtype=dtype),
            confidence=self.confidence.to(device=device, dtype=dtype),
            times=self.times.to(device=device, dtype=dtype),
            camera=self.camera,
            keypoint_names=self.keypoint_names,
            masks=masks,
        )

    def save_npz(self, path: str | Path) -> None:
        """Write the layout described in the module docstring (compressed, exactly at ``path``)."""
        arrays = {
            "keypoints": self.keypoints.detach().cpu().numpy(),
            "confidence": self.confidence.detach().cpu().numpy(),
            "times": self.times.detach().cpu().numpy(),
            "keypoint_names": np.array(self.keypoint_names, dtype=str),
            "camera": np.array(json.dumps(self.camera.to_dict())),
        }
        if self.masks is not None:
            arrays["masks"] = self.masks.cpu().numpy()
        with open(path, "wb") as f:
            np.savez_compressed(f, **arrays)  # type: ignore[arg-type]  # numpy's stub: a key could be allow_pickle

    @classmethod
    def load_npz(cls, path: str | Path, camera: Camera | None = None) -> Observations:
        """Read the layout described in the module docstring; ``camera`` overrides the file's.

        Float arrays keep their dtype (float16 and integers become float32). A missing file, a
        missing key or a wrong dtype/shape raises `InputError` naming the file and key.
        """
        path = Path(path)
        arrays = read_npz(path, "observation file")

        def need(key: str) -> np.ndarray:
            if key not in arrays:
                raise InputError(f"{path}: missing key {key!r} (has {sorted(arrays)})")
            return arrays[key]

        def numeric(key: str) -> np.ndarray:
            a = need(key)
            if a.dtype.kind not in "fiu":
                raise InputError(f"{path}: key {key!r} must be a numeric array, got dtype {a.dtype}")
            return a if a.dtype in (np.float32, np.float64) else a.astype(np.float32)

        kp = torch.from_numpy(numeric("keypoints"))
        name_array = need("keypoint_names")
        if name_array.dtype.kind not in "US" or name_array.ndim != 1:
            raise InputError(
                f"{path}: key 'keypoint_names' must be a 1-D string array, got dtype {name_array.dtype} "
                f"shape {name_array.shape}"
            )
        names = tuple(n.decode() if isinstance(n, bytes) else str(n) for n in name_array.tolist())
        if camera is None:
            camera = _camera_from_arrays(arrays, path)
        mask_array = arrays.get("masks")
        masks = None
        if mask_array is not None:
            if mask_array.dtype.kind not in "biu":
                raise InputError(f"{path}: key 'masks' must be bool or integer, got dtype {mask_array.dtype}")
            masks = torch.from_numpy(mask_array != 0)
        try:
            return cls(
                keypoints=kp,
                confidence=torch.from_numpy(numeric("confidence")),
                times=torch.from_numpy(numeric("times")),
                camera=camera,
                keypoint_names=names,
                masks=masks,
            )
        except InputError as e:
            raise InputError(f"{path}: {e}") from None


def _camera_from_arrays(arrays: dict[str, np.ndarray], path: Path) -> Camera:
    try:
        if "camera" in arrays:
            text = arrays["camera"]
            if text.dtype.kind not in "US" or text.ndim != 0:
                raise InputError(f"key 'camera' must be a JSON string, got dtype {text.dtype} shape {text.shape}")
            try:
                d = json.loads(str(text.item().decode() if text.dtype.kind == "S" else text.item()))
            except json.JSONDecodeError as e:
                raise InputError(f"key 'camera' is not valid JSON ({e})") from None
            return Camera.from_dict(d, dtype=torch.float64)
        missing = [k for k in ("K", "R", "t", "width", "height") if k not in arrays]
        if missing:
            raise InputError(f"no key 'camera' and missing camera keys {missing} (pass camera= to load_npz)")
        size = {}
        for key in ("width", "height"):
            a = arrays[key]
            if a.dtype.kind not in "iu" or a.size != 1:
                raise InputError(f"key {key!r} must be one integer, got dtype {a.dtype} shape {a.shape}")
            size[key] = int(a.reshape(()))
        mats = {}
        for key in ("K", "R", "t"):
            if arrays[key].dtype.kind not in "fiu":
                raise InputError(f"key {key!r} must be numeric, got dtype {arrays[key].dtype}")
            mats[key] = torch.from_numpy(arrays[key].astype(np.float64))
        return Camera(K=mats["K"], R=mats["R"], t=mats["t"], width=size["width"], height=size["height"])
    except InputError as e:
        raise InputError(f"{path}: {e}") from None


#: the lossy channel's numeric settings: (lowest, highest, whether the highest is excluded); checked by
#: `ChannelConfig` and, under the same intervals, by the run config's `observations.*` keys
CHANNEL_RANGES: dict[str, tuple[float, float, bool]] = {
    "noise_px": (0.0, math.inf, True),
    "missing": (0.0, 1.0, True),
    "occlusion_bursts": (0.0, math.inf, True),
    "dropped_frames": (0.0, 1.0, True),
    "outliers": (0.0, 1.0, False),
    "outlier_px": (0.0, math.inf, True),
    "swap_fraction": (0.0, 1.0, False),
}


def channel_range_error(name: str, value: object) -> str | None:
    """None when `value` suits the channel setting `name` (see CHANNEL_RANGES), else what it must be."""
    lo, hi, hi_open = CHANNEL_RANGES[name]
    ok = (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and lo <= value
        and (value < hi if hi_open else value <= hi)
    )
    if ok:
        return None
    return f"must be a number in [{lo:g}, {hi:g}{')' if hi_open else ']'}, got {value!r}"


@dataclass(frozen=True)
class ChannelConfig:
    """Parameters of the lossy channel (noise, projection, deletion, outliers). Rates are per
    (frame, keypoint) entry unless stated; burst and frame counts are in observation frames."""

    noise_px: float = 2.0  # std of Gaussian pixel noise
    missing: float = 0.0  # fraction of keypoints deleted at random, independently, in [0, 1)
    occlusion_bursts: float = 0.0  # expected contiguous occlusion bursts per keypoint per second
    burst_frames: tuple[int, int] = (5, 20)  # burst length range (inclusive), observation frames
    dropped_frames: float = 0.0  # fraction of whole frames dropped, in [0, 1)
    # fraction of the kept keypoints (those with confidence 1) that are gross outliers, in [0, 1]
    outliers: float = 0.0
    outlier_px: float = 50.0  # displacement scale: magnitude ~ U(0.5, 1.5) * outlier_px
    # share of the outliers that take their left/right partner's position (the rest are displaced)
    swap_fraction: float = 0.5

    def __post_init__(self) -> None:
        for name in CHANNEL_RANGES:
            error = channel_range_error(name, getattr(self, name))
            if error:
                raise InputError(f"ChannelConfig.{name} {error}")
        b = self.burst_frames
        if (
            isinstance(b, str)
            or not isinstance(b, Sequence)
            or len(b) != 2
            or not all(isinstance(x, int) and not isinstance(x, bool) for x in b)
            or not 1 <= b[0] <= b[1]
        ):
            raise InputError(f"ChannelConfig.burst_frames must be two integers 1 <= lo <= hi, got {b!r}")
        object.__setattr__(self, "burst_frames", (int(b[0]), int(b[1])))


class SimulationInfo(NamedTuple):
    """What the channel did, for tests and metrics (not carried by estimators).

    projected: (T, K, 2) exact projections (no noise).   visible: (T, K) in front and in the image.
    deleted: (T, K) random deletions.   occluded: (T, K) occlusion bursts.   dropped: (T,) frames.
    outlier_mask: (T, K) kept keypoints replaced by outliers (swapped or displaced).
    swapped: (T, K) the subset of outlier_mask that took the left/right partner's position.
    """

    projected: Tensor
    visible: Tensor
    deleted: Tensor
    occluded: Tensor
    dropped: Tensor
    outlier_mask: Tensor
    swapped: Tensor


def _rand(shape: tuple[int, ...], generator: torch.Generator, normal: bool = False) -> Tensor:
    """Uniform [0, 1) or standard normal float64 draws on the generator's device.

    Always float64, whatever the inputs' dtype, so that a seed gives the same channel in float32
    and float64; callers threshold in float64 and cast only the pixel offsets.
    """
    draw = torch.randn if normal else torch.rand
    return draw(shape, generator=generator, device=generator.device, dtype=torch.float64)


def _like(x: Tensor, like: Tensor) -> Tensor:
    """``x`` in ``like``'s dtype (floats only) and on its device."""
    if x.is_floating_point():
        x = x.to(like.dtype)
    return x.to(like.device)


def _partners(swap_pairs: Sequence[tuple[int, int]], K: int) -> list[int]:
    partner = [-1] * K
    for pair in swap_pairs:
        if len(pair) != 2 or not all(isinstance(i, (int, np.integer)) for i in pair):
            raise InputError(f"swap_pairs: each pair must be two keypoint indices, got {pair!r}")
        a, b = int(pair[0]), int(pair[1])
        if not (0 <= a < K and 0 <= b < K) or a == b:
            raise InputError(f"swap_pairs: pair {pair!r} must be two distinct indices in [0, {K})")
        if partner[a] >= 0 or partner[b] >= 0:
            raise InputError(f"swap_pairs: pair {pair!r} reuses a keypoint that is already paired")
        partner[a], partner[b] = b, a
    return partner


def _outlier_rates(kept: int, swappable: int, outliers: float, swap_fraction: float) -> tuple[float, float, float]:
    """Per-entry probabilities (outlier if swappable, outlier if not, swap given a swappable outlier).

    Chosen so that, in expectation over the clip, ``outliers * kept`` entries are outliers and a
    share ``swap_fraction`` of them are swaps, with outliers spread evenly over the keypoints when
    ``swap_fraction <= swappable / kept`` and shifted onto swappable keypoints otherwise; if even all
    swappable keypoints are too few, all of them are swapped and the outlier rate is kept.
    """
    if kept == 0 or outliers == 0.0:
        return 0.0, 0.0, 0.0
    if swappable == 0:
        return 0.0, outliers, 0.0
    swaps = min(outliers * swap_fraction * kept, float(swappable))
    rate_paired = max(outliers, swaps / swappable)
    swap_rate = swaps / (rate_paired * swappable)
    unpaired = kept - swappable
    rate_unpaired = 0.0 if unpaired == 0 else (outliers * kept - rate_paired * swappable) / unpaired
    return rate_paired, min(max(rate_unpaired, 0.0), 1.0), swap_rate


def _bursts(T: int, K: int, rate: float, frames: tuple[int, int], generator: torch.Generator) -> Tensor:
    """(T, K) bool on the generator's device: a Poisson(rate) number of bursts per keypoint, uniform
    starts and lengths (all drawn in float64)."""
    device = generator.device
    if rate <= 0.0:
        return torch.zeros(T, K, dtype=torch.bool, device=device)
    rates = torch.full((K,), rate, dtype=torch.float64, device=device)
    counts = torch.poisson(rates, generator=generator)
    M = int(counts.max())
    if M == 0:
        return torch.zeros(T, K, dtype=torch.bool, device=device)
    lo, hi = frames
    starts = (_rand((K, M), generator) * T).floor()
    lengths = lo + (_rand((K, M), generator) * (hi - lo + 1)).floor()
    used = torch.arange(M, device=device) < counts[:, None]  # (K, M)
    f = torch.arange(T, device=device, dtype=torch.float64)[:, None, None]  # (T, 1, 1)
    inside = (f >= starts) & (f < starts + lengths) & used
    return inside.any(dim=-1)


def simulate_observations(
    joints: Tensor,
    keypoint_index: Tensor | Sequence[int],
    camera: Camera,
    times: Tensor,
    channel: ChannelConfig,
    generator: torch.Generator,
    keypoint_names: Sequence[str],
    swap_pairs: Sequence[tuple[int, int]] = (),
    masks: Tensor | None = None,
) -> tuple[Observations, SimulationInfo]:
    """Pass world joints through the lossy channel: project, add noise, delete, add outliers.

    joints: (T, J, 3) world, metres.  keypoint_index: (K,) indices into J.  times: (T,) seconds.
    keypoint_names: (K,).  swap_pairs: pairs of indices into K (e.g. left/right knee) whose
    members swap positions for swap outliers.  masks: optional (T, H, W) bool, passed through.

    Keypoints behind the camera or outside the image, deleted at random, in an occlusion burst or
    in a dropped frame get confidence 0 and NaN pixels; the rest get confidence 1 and the noisy
    projection (or an outlier).

    Outliers: a fraction ``outliers`` of the kept keypoints, over the clip, become gross outliers.
    The base is the kept keypoints, not the visible ones, so that the setting is the rate of wrong
    detections an estimator receives, whatever the deletion rates. A share ``swap_fraction`` of the
    outliers are left/right swaps, which take the noisy position of their partner and are drawn
    only among keypoints whose partner is visible ("swappable"); the rest are displaced by
    ``U(0.5, 1.5) * outlier_px`` in a uniform direction. Each kept keypoint is an outlier
    independently, so both shares hold in expectation (up to sampling error). While
    ``swap_fraction`` is at most the swappable share of the kept keypoints, every kept keypoint is
    an outlier with probability ``outliers``; above it (e.g. swap_fraction 1), the outliers are
    drawn preferentially on swappable keypoints so that the swap share stays right. Only when
    ``outliers * swap_fraction`` exceeds the swappable share are there too few partners: then every
    swappable keypoint is swapped, the outlier rate stays ``outliers`` and the realised swap share
    is (swappable share) / ``outliers``; without swap_pairs all outliers are displacements.
    ``SimulationInfo.outlier_mask`` and ``.swapped`` record what was drawn.

    Every draw comes from ``generator`` (on any device), in float64 and in a fixed order, so the
    same seed gives the same observations in float32 and float64 (same flags, pixels equal to the
    inputs' precision) and changing one rate leaves the other draws unchanged. Returns
    (Observations in joints' dtype/device, SimulationInfo on joints' device).
    Raises `InputError` for bad shapes/indices and when the camera sees none of the keypoints.
    """
    joints = as_float_tensor(joints, "simulate_observations: joints")
    if joints.ndim != 3 or joints.shape[-1] != 3 or joints.shape[0] == 0:
        raise InputError(f"simulate_observations: joints must have shape (T, J, 3), got {tuple(joints.shape)}")
    T, J, _ = joints.shape
    index = torch.as_tensor(keypoint_index, device=joints.device)
    if index.ndim != 1 or index.numel() == 0 or index.is_floating_point() or index.dtype == torch.bool:
        raise InputError(
            f"simulate_observations: keypoint_index must be (K,) integers, got {index.dtype} {tuple(index.shape)}"
        )
    if bool(((index < 0) | (index >= J)).any()):
        raise InputError(f"simulate_observations: keypoint_index has values outside [0, {J}): {index.tolist()}")
    K = index.shape[0]
    times = as_float_tensor(times, "simulate_observations: times", like=joints)
    if tuple(times.shape) != (T,):
        raise InputError(f"simulate_observations: times must have shape (T,) = {(T,)}, got {tuple(times.shape)}")
    if len(keypoint_names) != K:
        raise InputError(f"simulate_observations: keypoint_names must have K = {K} names, got {len(keypoint_names)}")
    partner = torch.tensor(_partners(swap_pairs, K), device=joints.device)
    cam = camera.to(joints.device, joints.dtype)

    proj = cam.project(joints[:, index])
    clean = proj.pixels  # (T, K, 2)
    visible = proj.in_front & cam.in_image(clean)
    if not bool(visible.any()):
        raise InputError(
            f"simulate_observations: the camera sees none of the keypoints (all {T}x{K} are behind "
            f"the camera or outside its {cam.width}x{cam.height} image)"
        )

    # float64 draws on the generator's device; thresholds in float64, then to joints' dtype/device
    noise = _rand((T, K, 2), generator, normal=True) * channel.noise_px
    deleted = _rand((T, K), generator) < channel.missing
    dropped = _rand((T,), generator) < channel.dropped_frames
    u_outlier = _rand((T, K), generator)
    u_swap = _rand((T, K), generator)
    angle = _rand((T, K), generator) * (2 * math.pi)
    magnitude = (0.5 + _rand((T, K), generator)) * channel.outlier_px
    span = float(times[-1].double() - times[0].double()) * T / (T - 1) if T > 1 else 0.0
    occluded = _bursts(T, K, channel.occlusion_bursts * span, channel.burst_frames, generator)
    offset = magnitude[..., None] * torch.stack([angle.cos(), angle.sin()], dim=-1)  # (T, K, 2)
    deleted, dropped, occluded = (_like(x, joints) for x in (deleted, dropped, occluded))

    kept = visible & ~deleted & ~occluded & ~dropped[:, None]
    noisy = clean + _like(noise, joints)
    safe_partner = partner.clamp_min(0)
    swappable = kept & visible[:, safe_partner] & (partner >= 0)
    rate_paired, rate_unpaired, swap_rate = _outlier_rates(
        int(kept.sum()), int(swappable.sum()), channel.outliers, channel.swap_fraction
    )
    below_paired, below_unpaired = (_like(u_outlier < r, joints) for r in (rate_paired, rate_unpaired))
    outlier = kept & torch.where(swappable, below_paired, below_unpaired)
    swapped = outlier & swappable & _like(u_swap < swap_rate, joints)
    displaced = noisy + _like(offset, joints)
    observed = torch.where(outlier[..., None], displaced, noisy)
    observed = torch.where(swapped[..., None], noisy[:, safe_partner], observed)
    keypoints = torch.where(kept[..., None], observed, torch.full_like(observed, math.nan))

    obs = Observations(
        keypoints=keypoints,
        confidence=kept.to(joints.dtype),
        times=times,
        camera=cam,
        keypoint_names=tuple(keypoint_names),
        masks=masks,
    )
    info = SimulationInfo(clean, visible, deleted, occluded, dropped, outlier, swapped)
    return obs, info


def read_npz(path: Path, what: str) -> dict[str, np.ndarray]:
    """Every array of an .npz file, read without pickles. A missing file, bytes that are not an .npz
    archive, a single .npy array or an unreadable member raise `InputError` naming the file (`what` names
    the kind of file in the not-found message)."""
    if not path.is_file():
        raise InputError(f"{what} not found: {path}")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        if isinstance(e, ValueError) and "pickle" in str(e):  # numpy's guess for bytes it does not know
            raise InputError(f"{path}: not an .npz archive (numpy cannot read it)") from e
        raise InputError(f"{path}: not an .npz archive ({e})") from e
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: not an .npz archive (a single .npy array?)")
    with data:
        try:
            return {key: data[key] for key in data.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise InputError(f"{path}: cannot read an array ({e})") from e
