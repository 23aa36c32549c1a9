"""Benchmark the silhouette cost's exact distance transform: the previous O(H W^2) torch version
against the current `ptrack.costs.distance_transform` (scipy's linear-time exact transform).

Masks are real: the bundled CMU soccer kick (ptrack/data/10.asf, 10_02.amc, every 4th frame =
30 fps) rendered by `render_silhouettes` as capsule silhouettes, 640 x 480, seen by
`camera_for_motion` with the demo config's camera (6 m, azimuth 30, elevation 10, f = 1000 px).

Methodology: torch.set_num_threads(--threads); one warm-up call of each on 2 frames; then each
implementation transforms the whole clip once per repetition (time.perf_counter) and the median
is reported. The previous implementation is slow (seconds per frame), so by default it is timed
on the first --old-frames frames and its clip time is extrapolated linearly (it is linear in the
number of frames: one independent pass per image); --old-frames 0 times it on the whole clip.
Before timing, both are checked to give the same distances on those frames.
Ratio = previous time / current time (> 1: the current one is faster).

Usage (from the repo root, with ptrack installed):
    python scripts/bench_silhouette.py [--frames 90] [--old-frames 10] [--repeats 3] [--threads N]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _bench import machine_line
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.costs import distance_transform
from ptrack.observe.camera import camera_for_motion
from ptrack.observe.silhouette import capsule_radii, render_silhouettes

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"


def previous_distance_transform(mask: Tensor) -> Tensor:
    """The previous implementation (ptrack/costs/silhouette.py before this change), verbatim:
    a 1-D pass down columns, then a brute-force lower envelope along rows, O(H W^2) per image.
    mask (..., H, W) bool -> (..., H, W) float64, inf for an image with no True pixel."""
    mask = torch.as_tensor(mask, dtype=torch.bool)
    h, w = mask.shape[-2:]
    rows = torch.arange(h, dtype=torch.float64, device=mask.device)[:, None].expand(h, w)
    inf = torch.tensor(math.inf, dtype=torch.float64, device=mask.device)
    above = torch.where(mask, rows, -inf).cummax(-2).values
    below = torch.where(mask, rows, inf).flip(-2).cummin(-2).values.flip(-2)
    g = torch.minimum(rows - above, below - rows).square().reshape(-1, w)
    cols = torch.arange(w, dtype=torch.float64, device=mask.device)
    d2 = (cols[:, None] - cols[None, :]).square()
    chunk = max(1, 2**22 // (w * w))
    out = torch.cat([(c[:, None, :] + d2).amin(-1) for c in g.split(chunk)]) if g.numel() else g
    return out.sqrt().reshape(mask.shape)


def clip_masks(frames: int) -> Tensor:
    """(frames, 480, 640) bool silhouettes of the bundled soccer kick at 30 fps."""
    sk = Skeleton.from_asf(DATA / "10.asf")
    motion = sk.load_amc(DATA / "10_02.amc").slice(0, None, 4)
    if frames > motion.q.shape[0]:
        raise SystemExit(f"the bundled clip has {motion.q.shape[0]} frames at 30 fps, asked {frames}")
    joints = sk.forward_kinematics(motion.q[:frames])
    camera = camera_for_motion(joints, 6.0, 30.0, 10.0, 1000.0, 640, 480)
    bones = torch.as_tensor(sk.bones(), dtype=torch.long)
    names = [sk.joint_names[b] for _, b in sk.bones()]
    radii = capsule_radii(names, torch.as_tensor(sk.lengths[bones[:, 1]], dtype=joints.dtype))
    return render_silhouettes(joints, bones, radii, camera)


def median_time(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=90, help="clip length in frames (default 90)")
    ap.add_argument(
        "--old-frames",
        type=int,
        default=10,
        help="frames on which to time the previous implementation, extrapolated to the "
        "clip (default 10; 0 = the whole clip)",
    )
    ap.add_argument("--repeats", type=int, default=3, help="repetitions, median reported (default 3)")
    ap.add_argument(
        "--threads", type=int, default=len(os.sched_getaffinity(0)), help="torch threads (default: all available)"
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(machine_line())

    masks = clip_masks(args.frames)
    n_old = args.old_frames if 0 < args.old_frames < args.frames else args.frames
    print(
        f"clip: {args.frames} frames, {masks.shape[-1]} x {masks.shape[-2]} px, foreground "
        f"{masks.double().mean().item():.1%}; torch {torch.__version__}, {args.threads} threads"
    )

    previous_distance_transform(masks[:2]), distance_transform(masks[:2])  # warm-up
    old, new = previous_distance_transform(masks[:n_old]), distance_transform(masks[:n_old])
    present = masks[:n_old].flatten(1).any(1)  # empty masks: inf before, hypot(H, W) now
    diff = (old - new)[present].abs().max().item()
    print(f"check on {int(present.sum())} non-empty frames: max |previous - current| = {diff:.1e} px")
    if not diff < 1e-9:
        print("FAILED: the two implementations disagree")
        return 1

    t_new = median_time(lambda: distance_transform(masks), args.repeats)
    t_old = median_time(lambda: previous_distance_transform(masks[:n_old]), args.repeats)
    t_old_clip = t_old * args.frames / n_old
    how = (
        "measured"
        if n_old == args.frames
        else f"extrapolated from {t_old:.2f} s on {n_old} frames (x {args.frames / n_old:g})"
    )
    print(f"previous (O(H W^2) torch): {t_old_clip:8.2f} s for {args.frames} frames, {how}")
    print(f"current  (scipy EDT):      {t_new:8.2f} s for {args.frames} frames, measured")
    print(f"ratio previous / current:  {t_old_clip / t_new:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
