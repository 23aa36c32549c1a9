"""Wall time of the whole default `ptrack run configs/batch.yaml` (flip restarts and uncertainty included)
against a baseline commit, both timed in this one invocation.

    python scripts/bench_batch_run.py                      # against c619760 (before issue 42's speed work)
    python scripts/bench_batch_run.py --repeats 3 --baseline <commit> [key=value ...]

The baseline is checked out into a temporary `git worktree add --detach` (removed afterwards) and run with
PYTHONPATH pointing there; the current code is this script's repository. Each repeat runs both, alternating
which goes first, as `python -m ptrack.cli run CONFIG progress=false out_dir=<tmp>` in a fresh process (imports,
data, the estimate and every output written: what a user waits for). Prints each run's wall time and MPJPE,
the ratio of the medians (`3.4x`: the baseline takes 3.4 times as long), and the machine line (CPU model,
cores, load averages: `_bench.machine_line`), since timings on a shared machine move with its load.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))

from _bench import machine_line  # noqa: E402

BASELINE = "c619760"  # main before issue 42's items 5 and 6


def run_once(tree: Path, config: str, overrides: list[str], out: Path) -> tuple[float, dict]:
    """One `ptrack run` of the code in `tree` -> (wall seconds, metrics.json)."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, "-m", "ptrack.cli", "run", config, "progress=false", f"out_dir={out}", *overrides]
    start = time.perf_counter()
    subprocess.run(cmd, cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    return wall, json.loads((out / "metrics.json").read_text(encoding="utf-8"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("overrides", nargs="*", help="key=value overrides given to both runs")
    ap.add_argument("--baseline", default=BASELINE, help="commit to compare against")
    ap.add_argument("--config", default="configs/batch.yaml", help="run config, relative to the repository")
    ap.add_argument("--repeats", type=int, default=2, help="runs of each (alternating)")
    args = ap.parse_args()
    print(machine_line(), flush=True)
    times: dict[str, list[float]] = {"current": [], "baseline": []}
    with tempfile.TemporaryDirectory(prefix="bench_batch_run-") as tmp:
        base = Path(tmp) / "baseline"
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "--detach", str(base), args.baseline],
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            trees = {"current": REPO, "baseline": base}
            for i in range(args.repeats):
                order = ("baseline", "current") if i % 2 == 0 else ("current", "baseline")
                for name in order:
                    wall, metrics = run_once(trees[name], args.config, args.overrides, Path(tmp) / f"{name}-{i}")
                    times[name].append(wall)
                    print(
                        f"{name:8s} run {i}: {wall:6.1f} s wall (estimate {metrics['seconds']:.1f} s), "
                        f"MPJPE {metrics['mpjpe_mm']:.2f} mm, load {os.getloadavg()[0]:.2f}",
                        flush=True,
                    )
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(base)], check=False)
    cur, old = statistics.median(times["current"]), statistics.median(times["baseline"])
    print(f"baseline {args.baseline}: {old:.1f} s, current: {cur:.1f} s (medians of {args.repeats}): {old / cur:.1f}x")
    print(machine_line())


if __name__ == "__main__":
    main()
