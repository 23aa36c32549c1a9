"""Benchmark the real-footage path from keypoints to result: the Pose2Sim balancing trial's cam01 (100 frames of
OpenPose BODY_25B, the calibration, height 1.72 m) through `configs/video.yaml`, against `method: frame` on the
same input as the baseline, alternately `--repeats` times (with `--defaults` and key=value overrides, the defaults
too: before and after in one invocation).

Timed: `ptrack.pipeline.run.estimate` (reading the keypoint folder, choosing the person, the camera, the scaled
skeleton, and the estimator), as a run's `seconds`; Python start-up and writing the folder are not. Detection
is timed apart (`scripts/bench_detect.py`). Prints frames per second (median over the repeats) and the ratio
of each configuration's time to the baseline's, with the machine line. The issue's target: 10 frames per second.

Usage (from the repo root):
    PYTHONPATH=. python scripts/bench_video.py [--repeats 3] [--stop N] [--defaults] [key=value ...]
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from _bench import machine_line

from ptrack.pipeline.config import load_config
from ptrack.pipeline.run import estimate

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "pose2sim"


def timed(overrides: list[str]) -> tuple[float, int]:
    """-> (seconds, frames) of one `estimate` of configs/video.yaml with `overrides`."""
    cfg = load_config(REPO / "configs" / "video.yaml", overrides)
    start = time.perf_counter()
    _, est = estimate(cfg)
    return time.perf_counter() - start, int(est.q.shape[0])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--stop", type=int, default=None, help="only the first STOP frames")
    p.add_argument("--defaults", action="store_true", help="with overrides: configs/video.yaml without them too")
    p.add_argument("overrides", nargs="*", help="key=value for the configuration measured (not the baseline)")
    args = p.parse_args(argv)
    if not DATA.is_dir():
        raise SystemExit(f"bench_video: no data at {DATA}")
    base = [
        f"observations.file={DATA / 'balancing' / 'pose' / 'cam01_json'}",
        f"camera.file={DATA / 'Calib_qualisys.toml'}",
    ]
    base += ["camera.name=cam01", "subject.height_m=1.72", "observations.fps=60", "progress=false"]
    if args.stop:
        base.append(f"data.stop={args.stop}")
    runs = {"configs/video.yaml" + (" " + " ".join(args.overrides) if args.overrides else ""): [*base, *args.overrides]}
    if args.defaults and args.overrides:
        runs["configs/video.yaml"] = base
    runs["baseline: method=frame"] = [*base, "method=frame"]
    print(machine_line(), f"torch threads {torch.get_num_threads()}")
    times: dict[str, list[float]] = {name: [] for name in runs}
    frames: dict[str, int] = {}
    for _ in range(args.repeats):
        for name, overrides in runs.items():
            seconds, frames[name] = timed(overrides)
            times[name].append(seconds)
    baseline = statistics.median(times["baseline: method=frame"])
    print(f"\n| configuration | frames | seconds (median of {args.repeats}) | frames/s | time / baseline |")
    print("|---|---|---|---|---|")
    for name, ts in times.items():
        t = statistics.median(ts)
        print(f"| {name} | {frames[name]} | {t:.1f} | {frames[name] / t:.2f} | {t / baseline:.2f}x |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
