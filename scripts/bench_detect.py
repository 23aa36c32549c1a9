"""Benchmark `ptrack detect`'s work: MediaPipe Pose (model_complexity=1) over a whole video, against decoding it.

Clips: the Pose2Sim balancing trial's cam01 (1080 x 1920, 100 frames) and the Sports2D demo (1768 x 994, 230
frames), from ../shared/data. For each clip, alternately `--repeats` times:
    decode   `ptrack.observe.video.read_frames`: every frame decoded and converted to RGB (what detection reads)
    detect   `ptrack.observe.detector.detect`: the same decoding plus MediaPipe Pose on every frame, a fresh
             MediaPipe graph each time (its start-up included, as in `ptrack detect`)
and reports frames per second (median over the repeats) and the ratio detect time / decode time (how many
times the decoding alone detection costs). MediaPipe picks its own thread count (XNNPACK); torch is not used.

Usage (from the repo root, with the video extra installed):
    PYTHONPATH=. python scripts/bench_detect.py [--repeats 3] [--stop N]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

from _bench import machine_line

from ptrack.observe.detector import detect
from ptrack.observe.video import read_frames, video_info

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
CLIPS = {
    "pose2sim cam01": SHARED / "pose2sim" / "balancing" / "videos" / "cam01.mp4",
    "sports2d demo": SHARED / "video" / "sports2d_demo.mp4",
}


def time_decode(path: Path, stop: int | None) -> tuple[float, int]:
    start = time.perf_counter()
    n = sum(1 for _ in read_frames(path, stop=stop))
    return time.perf_counter() - start, n


def time_detect(path: Path, stop: int | None) -> tuple[float, int, int]:
    start = time.perf_counter()
    lm = detect(path, stop=stop)
    return time.perf_counter() - start, len(lm.frames), int(lm.found.sum())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=3, help="alternating measurements per clip (median reported)")
    p.add_argument("--stop", type=int, default=None, help="only the first STOP frames of each clip")
    args = p.parse_args(argv)
    print(machine_line())
    print("\n| clip | size | frames | person in | decode fps | detect fps | detect / decode time |")
    print("|---|---|---|---|---|---|---|")
    for name, path in CLIPS.items():
        if not path.is_file():
            print(f"| {name} | missing: {path.resolve()} | | | | | |")
            continue
        info = video_info(path)
        decode, det = [], []
        for _ in range(args.repeats):
            seconds, n = time_decode(path, args.stop)
            decode.append(seconds)
            seconds, n_det, found = time_detect(path, args.stop)
            det.append(seconds)
            assert n_det == n, f"{name}: detect read {n_det} frames, decoding {n}"
        dec_s, det_s = statistics.median(decode), statistics.median(det)
        print(
            f"| {name} | {info.width} x {info.height} | {n} | {found} | {n / dec_s:.1f} | {n / det_s:.1f} "
            f"| {det_s / dec_s:.1f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
