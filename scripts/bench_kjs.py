"""Benchmark: whole `ptrack run`s of the sampling trackers against the per-frame baseline.

    python scripts/bench_kjs.py [--stop 592] [--methods kjs css ss] [--samples 256] [--modes 8]
    python scripts/bench_kjs.py --clips configs/clips/heldout_batch.txt --methods kjs --stop 360  # clip by clip

Each run is `ptrack.pipeline.run.execute` on configs/kjs.yaml (the bundled CMU 10_02 soccer kick at 30 fps, 2 px
noise, 10% missing keypoints), data loading, observation simulation, metrics and every output file
included, so frames per second are what a user sees. The baseline, measured in the same process and
on the same clip, is `method: frame` (per-frame L-BFGS, one hypothesis). Printed per method: frames,
seconds, frames per second, the time ratio against frame written like `12.3x` (how many times longer
the tracker takes), best-trajectory and best-of-K MPJPE. The machine's load average is printed too:
on a shared 2-core machine other jobs slow every number.

--clips (a clip list, a glob or a comma list, as `ptrack evaluate --clips` takes; each clip's ASF is the one beside
it): the same runs of configs/kjs.yaml on each clip in turn (frames 0..--stop at 30 fps), frame first, a row per
clip and method, and the slowest clip's frames per second per method last.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from _bench import machine_line

from ptrack.clips import parse_clips
from ptrack.pipeline.config import load_config
from ptrack.pipeline.evaluate import asf_for
from ptrack.pipeline.run import execute

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "kjs.yaml"


def run(method: str, args: argparse.Namespace, root: Path, clip: Path | None = None) -> dict:
    data = [] if clip is None else [f"data.amc={clip}", f"data.asf={asf_for(clip)}"]
    cfg = load_config(
        CONFIG,
        [
            *data,
            f"method={method}",
            f"data.stop={args.stop}",
            f"kjs.samples={args.samples}",
            f"kjs.modes={args.modes}",
            f"out_dir={root / method}",
            "progress=false",
        ],
    )
    t0 = time.perf_counter()
    out = execute(cfg, progress=False)
    seconds = time.perf_counter() - t0
    m = json.loads((out / "metrics.json").read_text())
    return {**m, "seconds": seconds, "fps": m["frames"] / seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stop", type=int, default=592, help="AMC frames 0..stop (592: the whole clip, 148 frames)")
    ap.add_argument("--methods", nargs="+", default=["kjs", "css", "ss"], help="trackers (frame always runs first)")
    ap.add_argument("--samples", type=int, default=256, help="hypotheses per frame")
    ap.add_argument("--modes", type=int, default=8, help="K")
    ap.add_argument("--clips", default=None, help="clips to run one by one (list file, glob or comma list)")
    args = ap.parse_args()
    args.methods = [m for m in dict.fromkeys(args.methods) if m != "frame"]  # each once; frame is the baseline
    print(machine_line())
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    clips = parse_clips(args.clips) if args.clips else [None]
    slowest: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        print(
            f"{'clip':8s} {'method':8s} {'frames':>6s} {'seconds':>8s} {'fps':>6s} {'time vs frame':>14s} "
            f"{'MPJPE mm':>9s} {'best-of-K mm':>13s}"
        )
        for clip in clips:
            name = "10_02" if clip is None else clip.stem
            root = Path(tmp) / name
            base = run("frame", args, root, clip)
            rows = [("frame", base)] + [(m, run(m, args, root, clip)) for m in args.methods]
            for method, m in rows:
                ratio = m["seconds"] / base["seconds"]
                best = m.get("best_of_k_mpjpe_mm")
                slowest[method] = min(slowest.get(method, float("inf")), m["fps"])
                print(
                    f"{name:8s} {method:8s} {m['frames']:6d} {m['seconds']:8.1f} {m['fps']:6.1f} {ratio:13.1f}x "
                    f"{m['mpjpe_mm']:9.1f} {best if best is not None else float('nan'):13.1f}",
                    flush=True,
                )
    if len(clips) > 1:
        print("slowest clip, frames per second: " + ", ".join(f"{k} {v:.1f}" for k, v in slowest.items()))
    print(f"load average after: {os.getloadavg()[0]:.2f}; K={args.modes}, {args.samples} hypotheses per frame")


if __name__ == "__main__":
    main()
