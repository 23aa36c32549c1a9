"""Benchmark: the batch engine (`ptrack batch`) serial, in local worker processes and on a local Ray runtime.

    python scripts/bench_batch_engine.py [--workers 2] [--stop 240] [--clips 8] [--items 60] [--no-ray]
        [--config configs/eval_kjs.yaml]

(a) The dev clips (configs/clips/dev.txt, the first `--clips`) under configs/eval_frame.yaml with few iterations,
    AMC frames 0..`--stop` (short items: a few seconds each), or under `--config` at its own settings (e.g. the
    trackers' dev evaluation, configs/eval_kjs.yaml, which runs on one thread in every executor):
    serial (`--workers 1`, in this process), `--workers N` and `--executor ray` (a local runtime of N CPUs). Printed:
    each wall time, the ratios written like `1.9x` (serial time / other time), whether the tables agree (the
    results.md text without its seconds column, and every metric to float32 rounding), and Ray's extra time per
    item against the local workers.
(b) A simulated sweep: `--items` runs of 10 frames each (the bundled clip 10_02, a CSV manifest giving each row
    its own seed) through the local workers and Ray. Printed: items per second, the engine's time per item
    beside the runs' own (estimation) time, and the peak memory of the whole process tree (this process and
    every process below it, resident set summed, sampled every 0.2 s from /proc).

Every timing starts from a cold executor (worker start-up and Ray's start included): that is what a command pays.
The machine line and the load average before and after are printed: other jobs slow every part.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path

from _bench import machine_line

from ptrack.pipeline.batch_run import BatchSummary, batch

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs" / "eval_frame.yaml"
DEV = REPO / "configs" / "clips" / "dev.txt"
CLIP = REPO / "ptrack" / "data" / "10_02.amc"
CHEAP = ["progress=false", "frame.iterations=10", "frame.first_iterations=30"]


class PeakMemory:
    """The peak resident memory of this process and all its descendants (summed), sampled every `every` s."""

    def __init__(self, every: float = 0.2) -> None:
        self.every, self.peak, self._stop = every, 0, threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def __enter__(self) -> PeakMemory:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, tree_rss(os.getpid()))
            self._stop.wait(self.every)


def tree_rss(root: int) -> int:
    """Resident bytes of `root` and every process below it (Linux /proc; 0 elsewhere)."""
    parents, rss = {}, {}
    page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
    for entry in Path("/proc").glob("[0-9]*"):
        try:
            stat = (entry / "stat").read_text()
            statm = (entry / "statm").read_text().split()
        except OSError:
            continue
        pid = int(entry.name)
        parents[pid] = int(stat[stat.rindex(")") + 2 :].split()[1])
        rss[pid] = int(statm[1]) * page
    total, todo, seen = 0, [root], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        total += rss.get(p, 0)
        todo.extend(c for c, pp in parents.items() if pp == p)
    return total


def run(
    inputs: str, out: Path, overrides: list[str], workers: int, executor: str, config: Path = CONFIG
) -> tuple[float, int, BatchSummary]:
    """One batch of `config`: -> (wall seconds, peak bytes of the process tree, summary)."""
    with PeakMemory() as mem:
        t0 = time.perf_counter()
        summary = batch(config, inputs, out, overrides, workers=workers, executor=executor, progress=False)
        seconds = time.perf_counter() - t0
    if summary.failed:
        raise SystemExit(f"{summary.failed} items failed in {out}: see {out / 'status.csv'}")
    return seconds, mem.peak, summary


def untimed_table(out: Path) -> list[str]:
    """results.md without its seconds column."""
    lines = (out / "results.md").read_text().splitlines()
    head = next(ln for ln in lines if ln.startswith("| input"))
    col = [c.strip() for c in head.strip("|").split("|")].index("seconds")
    return ["|".join(c for k, c in enumerate(ln.strip("|").split("|")) if k != col) for ln in lines if "|" in ln]


def metrics(out: Path) -> dict:
    rows = json.loads((out / "results.json").read_text())["settings"][""]
    return {n: {k: v for k, v in m.items() if k not in ("seconds", "fps")} for n, m in rows.items()}


def agree(a: dict, b: dict, rel: float = 1e-4) -> bool:
    """The same metrics, numbers to float32 rounding (a serial run's torch threads may sum in another order)."""
    if a.keys() != b.keys():
        return False
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, dict):
            if not isinstance(y, dict) or not agree(x, y, rel):
                return False
        elif isinstance(x, float) and isinstance(y, float):
            if abs(x - y) > rel * max(abs(x), abs(y)) + 1e-6:
                return False
        elif x != y:
            return False
    return True


def run_seconds(out: Path) -> float:
    """The sum of the runs' own (estimation) seconds."""
    rows = json.loads((out / "results.json").read_text())["settings"][""]
    return sum(m["seconds"] for m in rows.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2, help="local workers, and the local Ray runtime's CPUs")
    ap.add_argument(
        "--config",
        type=Path,
        default=None,
        help="(a): this config at its own settings (e.g. configs/eval_kjs.yaml, the dev evaluation of the trackers) "
        "instead of eval_frame.yaml with few iterations to data.stop=--stop",
    )
    ap.add_argument("--stop", type=int, default=240, help="(a): AMC frames 0..stop of each dev clip (240: 60 frames)")
    ap.add_argument("--clips", type=int, default=8, help="(a): the first this many dev clips")
    ap.add_argument("--items", type=int, default=60, help="(b): items of 10 frames each (the issue's: 1000; 0: none)")
    ap.add_argument("--no-ray", action="store_true", help="leave Ray out")
    args = ap.parse_args()
    executors = [("local", args.workers)] + ([] if args.no_ray else [("ray", args.workers)])
    print(machine_line())
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        listed = [ln.split("#")[0].strip() for ln in DEV.read_text().splitlines()]
        clips = [c for c in listed if c][: args.clips]
        listing = root / "clips.txt"
        listing.write_text("".join(f"{(DEV.parent / c).resolve()}\n" for c in clips))
        config = args.config.resolve() if args.config else CONFIG
        over = ["progress=false"] if args.config else [*CHEAP, f"data.stop={args.stop}"]
        print(f"\n(a) {len(clips)} dev clips, {config.name}, {' '.join(over)}")
        serial, _, _ = run(str(listing), root / "a-serial", over, 1, "local", config)
        print(f"serial: {serial:.1f} s")
        times = {}
        for executor, workers in executors:
            out = root / f"a-{executor}"
            times[executor], _, _ = run(str(listing), out, over, workers, executor, config)
            same = untimed_table(out) == untimed_table(root / "a-serial") and agree(
                metrics(out), metrics(root / "a-serial")
            )
            print(
                f"{executor} --workers {workers}: {times[executor]:.1f} s, {serial / times[executor]:.1f}x serial; "
                f"same table: {'yes' if same else 'NO'}"
            )
        if "ray" in times:
            extra = (times["ray"] - times["local"]) / len(clips)
            print(f"Ray's extra time per item against the local workers: {extra:+.2f} s")

        if args.items > 0:  # (b)
            manifest = root / "items.csv"
            manifest.write_text("input,seed\n" + "".join(f"{CLIP},{k}\n" for k in range(args.items)))
            over = [*CHEAP, "data.stop=40", "data.stride=4"]  # 10 frames
            print(f"\n(b) {args.items} items of 10 frames (10_02, one seed each)")
            for executor, workers in executors:
                out = root / f"b-{executor}"
                seconds, peak, _ = run(str(manifest), out, over, workers, executor)
                per_item = seconds * workers / args.items
                own = run_seconds(out) / args.items
                print(
                    f"{executor} --workers {workers}: {args.items / seconds:.2f} items/s ({seconds:.1f} s), "
                    f"{per_item:.2f} s of a worker per item of which the run's own {own:.2f} s "
                    f"(the rest, {per_item - own:.2f} s: loading, metrics, writing the folder, the engine); "
                    f"peak memory {peak / 2**20:.0f} MiB"
                )
    print(f"\nload average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
