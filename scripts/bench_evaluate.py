"""Benchmark: `ptrack evaluate --jobs N` against the same evaluation run by run (`--jobs 1`).

    python scripts/bench_evaluate.py [--jobs 2] [--seeds 0-3] [--stop 240] [--config configs/eval_kjs.yaml]

Both evaluations run the config on the bundled CMU clip 10_02 (the first `--stop` AMC frames, 30 fps) once
per seed, each from a fresh `ptrack.pipeline.evaluate.evaluate` call in this process, into temporary folders. Printed:
the wall time of each (Python start-up of the workers included), the ratio written like `1.8x` (sequential
time / parallel time), and whether every run's metrics agree (timings apart), which they must: the runs are
seeded by their configs. The machine's load average is printed too: other jobs slow both.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from _bench import machine_line

from ptrack.pipeline.evaluate import evaluate, parse_seeds

REPO = Path(__file__).resolve().parents[1]
CLIP = REPO / "ptrack" / "data" / "10_02.amc"


def timed(config: Path, seeds: list[int], stop: int, jobs: int, out: Path) -> tuple[float, dict]:
    t0 = time.perf_counter()
    table = evaluate(config, str(CLIP), [f"data.stop={stop}", "progress=false"], out=out, seeds=seeds, jobs=jobs)
    seconds = time.perf_counter() - t0
    runs = json.loads(table.with_name("results.json").read_text())["runs"]
    return seconds, {
        clip: {s: {k: v for k, v in m.items() if k not in ("seconds", "fps")} for s, m in by_seed.items()}
        for clip, by_seed in runs.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=2, help="runs at once in the parallel evaluation")
    ap.add_argument("--seeds", default="0-3", help="seeds, one run each")
    ap.add_argument("--stop", type=int, default=240, help="AMC frames 0..stop (240: 2 s, 60 frames)")
    ap.add_argument("--config", default=str(REPO / "configs" / "eval_kjs.yaml"))
    args = ap.parse_args()
    seeds = parse_seeds(args.seeds)
    print(machine_line())
    print(f"load average before: {os.getloadavg()[0]:.2f}; {len(seeds)} runs of {Path(args.config).name}")
    with tempfile.TemporaryDirectory() as tmp:
        one, res_one = timed(Path(args.config), seeds, args.stop, 1, Path(tmp) / "one")
        many, res_many = timed(Path(args.config), seeds, args.stop, args.jobs, Path(tmp) / "many")
    print(f"--jobs 1: {one:.1f} s")
    print(f"--jobs {args.jobs}: {many:.1f} s")
    print(f"speed-up: {one / many:.1f}x; same metrics: {'yes' if res_one == res_many else 'NO'}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
