"""Key postures of a motion type: the frames of a clip where its stereotyped postures happen.

A motion model (`ptrack.motion.motion_model`) aligns its training clips on key postures (for the golf swing,
Urtasun, Fleet & Fua 2004, fig. 2: start of upswing, top of upswing, ball hit, end of downswing), and
the PCA tracker starts from the same postures found in the image (their section 5.1). Both are found
from one tracked point, the mean of a few joints (the wrists for golf), by rules written in the config
(`motion.key_postures`, a mapping name -> rule, in temporal order):

    RULE  := [first | last] (max | min) (height | speed) [RANGE]  |  rest RANGE
    RANGE := (before | after) KEY [within SECONDS s]

- `max height`: the frame where the point is highest, over the clip, or over the frames before / after
  the frame of another key posture KEY (and, with `within`, at most SECONDS from it).
- `first max height ...` / `last ...`: the first / last local extremum in that range whose prominence
  is at least `motion.prominence` times the signal's range over the clip (ignores small wiggles).
- `rest before KEY`: the last frame before the fastest motion preceding KEY at which the point moves
  slower than `motion.rest_fraction` times the clip's top speed (the start of a movement);
  `rest after KEY`: the first such frame after the fastest motion following KEY (its end).

Signals: height is world Y for 3D joints (Y up, metres) and minus the image row for 2D points (image
y grows downward, see `ptrack.observe.camera`), speed the norm of the point's velocity (m/s or px/s), both
after Gaussian smoothing over `motion.smooth_s` seconds.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ptrack.errors import InputError

_EXTREMA = ("max", "min")
_SIGNALS = ("height", "speed")


@dataclass(frozen=True)
class Rule:
    """One parsed key-posture rule (see the module docstring)."""

    kind: str  # "max", "min" or "rest"
    signal: str  # "height" or "speed" ("speed" for rest)
    which: str  # "global", "first" or "last"
    side: str | None  # "before", "after" or None (whole clip)
    ref: str | None  # the key posture the range is relative to
    within_s: float | None = None  # the range ends this many seconds from `ref`


def parse_rule(text: str, key: str = "motion.key_postures") -> Rule:
    """`"first max height after top"` -> Rule; InputError naming the config key if malformed."""
    words = str(text).split()
    bad = InputError(
        f"config key {key!r}: cannot read rule {text!r}; expected '[first|last] max|min "
        "height|speed [before|after KEY [within SECONDS s]]' "
        "or 'rest before|after KEY [within SECONDS s]'"
    )
    within = None
    if len(words) >= 2 and words[-1] == "s":
        words = words[:-1]
    if len(words) >= 2 and words[-2] == "within":
        try:
            within = float(words[-1].removesuffix("s"))
        except ValueError:
            raise bad from None
        if not within > 0 or len(words) < 4 or words[-4] not in ("before", "after"):
            raise bad
        words = words[:-2]
    if words and words[0] == "rest":
        if len(words) != 3 or words[1] not in ("before", "after"):
            raise bad
        return Rule("rest", "speed", "global", words[1], words[2], within)
    which = "global"
    if words and words[0] in ("first", "last"):
        which, words = words[0], words[1:]
    if len(words) not in (2, 4) or words[0] not in _EXTREMA or words[1] not in _SIGNALS:
        raise bad
    side = ref = None
    if len(words) == 4:
        if words[2] not in ("before", "after"):
            raise bad
        side, ref = words[2], words[3]
    return Rule(words[0], words[1], which, side, ref, within)


def parse_rules(rules: Mapping[str, str], key: str = "motion.key_postures") -> dict[str, Rule]:
    """Parse and check a name -> rule mapping: at least 2 postures, known references, no cycles."""
    if len(rules) < 2:
        raise InputError(f"config key {key!r} must define at least 2 key postures, got {len(rules)}")
    parsed = {name: parse_rule(text, f"{key}.{name}") for name, text in rules.items()}
    for name, r in parsed.items():
        if r.ref is not None and r.ref not in parsed:
            raise InputError(
                f"config key '{key}.{name}': rule refers to unknown key posture {r.ref!r} (known: {', '.join(parsed)})"
            )
    _resolution_order(parsed, key)
    return parsed


def _resolution_order(rules: dict[str, Rule], key: str = "motion.key_postures") -> list[str]:
    order: list[str] = []
    while len(order) < len(rules):
        ready = [n for n, r in rules.items() if n not in order and (r.ref is None or r.ref in order)]
        if not ready:
            left = [n for n in rules if n not in order]
            raise InputError(f"config key {key!r}: the rules of {', '.join(left)} refer to each other in a cycle")
        order.extend(ready)
    return order


def signals(points: np.ndarray, fps: float, smooth_s: float, up_sign: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Smoothed height and speed of a tracked point. points: (T, 2|3) -> height (T,), speed (T,).

    Height is points[:, 1] * up_sign (3D, Y up: +1; image rows: -1); speed is per second.
    """
    from scipy.ndimage import gaussian_filter1d  # scipy's modules are imported on use: see `_apply`

    sigma = smooth_s * fps
    p = gaussian_filter1d(points, sigma, axis=0, mode="nearest") if sigma > 0 else points
    height = p[:, 1] * up_sign
    speed = np.linalg.norm(np.gradient(p, axis=0), axis=1) * fps if len(p) > 1 else np.zeros(len(p))
    return height, speed


def find_frames(
    height: np.ndarray,
    speed: np.ndarray,
    fps: float,
    rules: Mapping[str, str],
    prominence: float,
    rest_fraction: float,
    clip: str = "clip",
) -> np.ndarray:
    """Apply the rules to the signals (T,) at `fps`: key-posture frames (P,) int64 in the rules' order.

    Raises InputError naming `clip` and the posture when a rule finds no frame or the frames are not
    strictly increasing in the rules' order.
    """
    parsed = parse_rules(rules)
    t = len(height)
    found: dict[str, int] = {}
    for name in _resolution_order(parsed):
        r = parsed[name]
        lo, hi = 0, t
        span = t if r.within_s is None else round(r.within_s * fps)
        if r.side == "before":
            assert r.ref is not None  # a rule with a side names the key it refers to
            hi = found[r.ref]
            lo = max(0, hi - span)
        elif r.side == "after":
            assert r.ref is not None
            lo = found[r.ref] + 1
            hi = min(t, found[r.ref] + 1 + span)
        frame = _apply(r, height, speed, lo, hi, prominence, rest_fraction)
        if frame is None:
            raise InputError(f"{clip}: key posture {name!r} ({rules[name]}) not found")
        found[name] = frame
    frames = np.array([found[n] for n in parsed], dtype=np.int64)
    if np.any(np.diff(frames) <= 0):
        listing = ", ".join(f"{n} {f}" for n, f in zip(parsed, frames))
        raise InputError(f"{clip}: key postures not in order (frames {listing})")
    return frames


def _apply(
    r: Rule, height: np.ndarray, speed: np.ndarray, lo: int, hi: int, prominence: float, rest_fraction: float
) -> int | None:
    if hi - lo < 1:
        return None
    if r.kind == "rest":
        thr = rest_fraction * speed.max()
        if r.side == "before":
            peak = lo + int(np.argmax(speed[lo:hi]))
            still = np.nonzero(speed[lo:peak] < thr)[0]
            return lo + int(still[-1]) if len(still) else None
        peak = lo + int(np.argmax(speed[lo:hi]))
        still = np.nonzero(speed[peak:hi] < thr)[0]
        return peak + int(still[0]) if len(still) else None
    sig = height if r.signal == "height" else speed
    sig = sig if r.kind == "max" else -sig
    seg = sig[lo:hi]
    if r.which == "global":
        return lo + int(np.argmax(seg))
    # imported here, not with the module: loading scipy.signal takes ~1 s, which every import of the estimators
    # (and so of the config, `ptrack config --list`) would pay
    from scipy.signal import find_peaks

    span = float(np.ptp(sig))
    peaks, _ = find_peaks(seg, prominence=max(prominence * span, 1e-12))
    if len(peaks) == 0:
        return None
    return lo + int(peaks[0] if r.which == "first" else peaks[-1])


def detect_key_postures(joints_3d: Tensor, joint_names, fps: float, cfg, clip: str = "clip") -> Tensor:
    """Key-posture frames of a 3D clip, from the height and speed of the mean of `cfg.joints`.

    Args:
        joints_3d: (T, J, 3) world joint positions, metres, Y up.
        joint_names: (J,) names, or a `Skeleton` (its `joint_names`).
        fps: frames per second of the clip.
        cfg: a `MotionConfig` (joints, key_postures, smooth_s, prominence, rest_fraction).
        clip: name used in error messages.

    Returns:
        (P,) int64 frame indices, in the order of `cfg.key_postures`. InputError naming the clip if a
        posture is not found or the postures are out of order.
    """
    names = list(getattr(joint_names, "joint_names", joint_names))
    missing = [j for j in cfg.joints if j not in names]
    if missing:
        raise InputError(f"config key 'motion.joints': no joint {missing[0]!r} in {clip}'s skeleton")
    x = torch.as_tensor(joints_3d).detach().cpu().double().numpy()
    if x.ndim != 3 or x.shape[1] != len(names) or x.shape[2] != 3:
        raise InputError(f"{clip}: joints must have shape (T, {len(names)}, 3), got {tuple(x.shape)}")
    point = x[:, [names.index(j) for j in cfg.joints]].mean(axis=1)
    height, speed = signals(point, fps, cfg.smooth_s, up_sign=1.0)
    frames = find_frames(height, speed, fps, cfg.key_postures, cfg.prominence, cfg.rest_fraction, clip)
    return torch.from_numpy(frames)


def detect_key_postures_2d(
    wrist_uv: Tensor, fps: float, cfg, valid: Tensor | None = None, clip: str = "observations"
) -> Tensor:
    """Key-posture frames from a 2D wrist track in pixels (image y grows downward).

    Args:
        wrist_uv: (T, 2) one point per frame, or (T, K, 2) several (e.g. both wrists), averaged.
        fps: frames per second of the track.
        cfg: a `MotionConfig` (key_postures, smooth_s, prominence, rest_fraction; `joints` unused).
        valid: optional (T,) or (T, K) bool, False where a point is missing (as are non-finite points);
            each point's track is filled by linear interpolation in time before the points are averaged.
        clip: name used in error messages.

    Returns:
        (P,) int64 frame indices in the order of `cfg.key_postures` (InputError if not found).
    """
    uv = torch.as_tensor(wrist_uv).detach().cpu().double().numpy()
    if uv.ndim == 2:
        uv = uv[:, None]
    if uv.ndim != 3 or uv.shape[-1] != 2 or uv.shape[0] < 2:
        raise InputError(
            f"{clip}: wrist track must have shape (T, 2) or (T, K, 2) with T >= 2, got "
            f"{tuple(torch.as_tensor(wrist_uv).shape)}"
        )
    ok = np.isfinite(uv).all(-1)
    if valid is not None:
        v = torch.as_tensor(valid).detach().cpu().numpy().astype(bool)
        v = v[:, None] if v.ndim == 1 else v
        if v.shape != ok.shape:
            raise InputError(f"{clip}: valid mask must have shape {ok.shape} or ({ok.shape[0]},), got {v.shape}")
        ok &= v
    tracks = [k for k in range(uv.shape[1]) if ok[:, k].sum() >= 2]  # each point filled in time, then averaged
    if not tracks:
        raise InputError(
            f"{clip}: the wrists are seen in {int(ok.any(1).sum())} frames; key postures need one seen in at least 2"
        )
    frames = np.arange(len(uv))
    point = np.mean(
        [np.stack([np.interp(frames, frames[ok[:, k]], uv[ok[:, k], k, c]) for c in range(2)], axis=1) for k in tracks],
        axis=0,
    )
    height, speed = signals(point, fps, cfg.smooth_s, up_sign=-1.0)
    return torch.from_numpy(find_frames(height, speed, fps, cfg.key_postures, cfg.prominence, cfg.rest_fraction, clip))


def initial_times(key_frames: Sequence[int] | Tensor, key_times: Tensor, num_frames: int) -> Tensor:
    """Normalised time of every frame from the key postures' frames (the paper's section 5.1).

    Monotone cubic (PCHIP) interpolation through (key frame, key time), extrapolated linearly from the
    outer segments and clamped to [0, 1]. key_frames: (P,) increasing; key_times: (P,) -> (T,) float
    in key_times' dtype.
    """
    from scipy.interpolate import PchipInterpolator

    kf = np.asarray(torch.as_tensor(key_frames).cpu(), dtype=np.float64)
    kt = np.asarray(torch.as_tensor(key_times).detach().cpu(), dtype=np.float64)
    if kf.shape != kt.shape or kf.ndim != 1 or len(kf) < 2 or np.any(np.diff(kf) <= 0):
        raise InputError(f"key frames {kf.tolist()} must be increasing and match key times {kt.tolist()}")
    f = np.arange(num_frames, dtype=np.float64)
    mu = PchipInterpolator(kf, kt, extrapolate=False)(f)
    lo_slope = (kt[1] - kt[0]) / (kf[1] - kf[0])
    hi_slope = (kt[-1] - kt[-2]) / (kf[-1] - kf[-2])
    mu = np.where(f < kf[0], kt[0] + (f - kf[0]) * lo_slope, mu)
    mu = np.where(f > kf[-1], kt[-1] + (f - kf[-1]) * hi_slope, mu)
    return torch.as_tensor(np.clip(mu, 0.0, 1.0), dtype=torch.as_tensor(key_times).dtype)
