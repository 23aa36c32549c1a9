"""Speed of the golf tracker (`method: pca`, full: joints + silhouettes) against `method: frame` on the same
observations, measured in the same run.

One held-out swing (default 64_01, with a motion model fitted on the other dev swings unless --model is
given) at 30 fps, 2 px noise, capsule silhouettes; the data, observations and silhouettes are made once
(`prepare`, timed apart), then each estimator runs `--repeats` times on the same problem and its median
time is kept. Prints frames per second of each, by wall-clock and by the process's CPU time (the machine
is shared), and each pca variant's ratio against frame (how many times faster it is), after the machine line
(`_bench.machine_line`). The full tracker runs once more with 40 simulated
point correspondences per frame (section 4.3; their simulation is part of `prepare`, not counted). First it
times fitting the motion model on all the dev swings (the issue asks under 10 s).

    OMP_NUM_THREADS=1 python scripts/bench_pca.py [--swing 64_01] [--repeats 3] [--model FILE]

`--threads` (run without OMP_NUM_THREADS=1, so that torch has its default threads, one per core) times instead
each of `pca` (the swing, `pca.after_swing: hold`, so that only the tracker's own windows are timed) and `frame`
(its first `--frames` frames) as they run (`ptrack.threads.one_thread`: one intra-op thread) against the same
estimator with torch's default threads (`one_thread` replaced by a no-op in the estimator's module, as before
issue 42), alternating the two `--repeats` times in the same run, and prints each one's ratio (how many times
faster one thread is) after the machine line, whose load says how busy the machine was:

    python scripts/bench_pca.py --threads [--repeats 3] [--frames 30]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _bench import machine_line  # noqa: E402

from ptrack.clips import parse_clips  # noqa: E402
from ptrack.estimators import ESTIMATORS  # noqa: E402
from ptrack.motion.motion_model import fit_motion_model, read_clips, save_motion_model  # noqa: E402
from ptrack.pipeline.config import load_config  # noqa: E402
from ptrack.pipeline.run import prepare  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--swing", default="64_01")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--model", default=None, help="motion model file (default: fitted on the other dev swings)")
    ap.add_argument("--threads", action="store_true", help="one intra-op thread against torch's default threads")
    ap.add_argument("--frames", type=int, default=30, help="--threads: frames of the frame run")
    args = ap.parse_args()
    print(machine_line())
    if args.threads:
        return threads(args)
    swings = parse_clips(str(REPO / "configs" / "clips" / "golf.txt"))
    swing = next(s for s in swings if s.stem == args.swing)
    cfg = load_config(REPO / "configs" / "golf.yaml", run=False)
    fits = []
    for _ in range(args.repeats):  # the fitting figure: a model of all the swings, reading included
        t = time.perf_counter()
        fit_motion_model(read_clips(swings), cfg.motion)
        fits.append(time.perf_counter() - t)
    print(
        f"motion model fitted on all {len(swings)} swings (reading the AMC files included): "
        f"{statistics.median(fits):.2f} s (median of {args.repeats})"
    )
    model = args.model
    if model is None:
        t = time.perf_counter()
        fitted = fit_motion_model(read_clips([s for s in swings if s != swing]), cfg.motion)
        model = str(save_motion_model(fitted, Path(tempfile.mkdtemp()) / "golf.npz"))
        print(f"motion model of the {len(swings) - 1} other swings: {time.perf_counter() - t:.1f} s (not counted)")
    base = [f"data.amc={swing}", f"data.asf={swing.parent / '64.asf'}", f"motion.model_file={model}", "progress=false"]
    cfg = load_config(REPO / "configs" / "golf.yaml", base)
    t = time.perf_counter()
    prep = prepare(cfg)
    print(
        f"{swing.stem}: {prep.problem.observations.num_frames} frames; data, observations and silhouettes: "
        f"{time.perf_counter() - t:.2f} s (not counted); torch threads {torch.get_num_threads()}"
    )
    corr = ["observations.correspondences=40", "observations.correspondence_outliers=0.05"]
    t = time.perf_counter()
    prep_corr = prepare(load_config(REPO / "configs" / "golf.yaml", [*base, *corr]))
    assert prep_corr.problem.correspondences is not None
    print(
        f"  the same with {prep_corr.problem.correspondences.num_pairs} correspondences: "
        f"{time.perf_counter() - t:.2f} s (not counted)"
    )
    results = {}
    for name, over in (
        ("pca (joints + silhouettes)", []),
        ("pca + correspondences", corr),
        ("pca joints only", ["pca.silhouette_weight=0"]),
        ("frame (per-frame L-BFGS)", ["method=frame"]),
    ):
        c = load_config(REPO / "configs" / "golf.yaml", [*base, *over])
        problem = prep_corr.problem if over is corr else prep.problem
        times, cpu = [], []
        for _ in range(args.repeats):
            t, p = time.perf_counter(), time.process_time()
            est = ESTIMATORS[c.method](problem, c, torch.Generator().manual_seed(1), lambda x: x)
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - p)
        sec, sec_cpu = statistics.median(times), statistics.median(cpu)
        n = est.q.shape[0]
        results[name] = (n / sec, n / sec_cpu)
        print(
            f"  {name:30s} wall {sec:6.2f} s {n / sec:6.1f} fps | CPU {sec_cpu:6.2f} s {n / sec_cpu:6.1f} fps"
            f"  (wall runs: {', '.join(f'{x:.2f}' for x in times)})"
        )
    frame = results["frame (per-frame L-BFGS)"]
    for name, (wall, cpu_fps) in results.items():
        if name.startswith("pca"):
            print(f"{name} vs frame: {wall / frame[0]:.1f}x (wall), {cpu_fps / frame[1]:.1f}x (CPU time)")
    print("CPU time is the process's own (on a machine shared with other jobs, wall time also counts the waits)")
    return 0


def threads(args: argparse.Namespace) -> int:
    """pca and frame on one intra-op thread (as they run) against torch's default threads, same run, alternating."""
    import contextlib

    import ptrack.estimators.frame as frame_module
    import ptrack.estimators.pca.track as pca_module

    swings = parse_clips(str(REPO / "configs" / "clips" / "golf.txt"))
    swing = next(s for s in swings if s.stem == args.swing)
    cfg = load_config(REPO / "configs" / "golf.yaml", run=False)
    model = args.model or str(
        save_motion_model(
            fit_motion_model(read_clips([s for s in swings if s != swing]), cfg.motion),
            Path(tempfile.mkdtemp()) / "golf.npz",
        )
    )
    base = [f"data.amc={swing}", f"data.asf={swing.parent / '64.asf'}", f"motion.model_file={model}", "progress=false"]
    default = torch.get_num_threads()
    print(f"{swing.stem}; torch's default intra-op threads here: {default}")
    for name, module, over in (
        ("pca", pca_module, ["pca.after_swing=hold"]),
        ("frame", frame_module, ["method=frame", f"data.stop={4 * args.frames}"]),
    ):
        c = load_config(REPO / "configs" / "golf.yaml", [*base, *over])
        problem = prepare(c).problem
        n = problem.observations.num_frames
        shipped = module.one_thread
        times: dict[str, list[float]] = {"one thread": [], f"default ({default})": []}
        for _ in range(args.repeats):
            for label in times:
                module.one_thread = shipped if label == "one thread" else contextlib.nullcontext  # type: ignore[attr-defined]
                try:
                    t = time.perf_counter()
                    ESTIMATORS[c.method](problem, c, torch.Generator().manual_seed(1), lambda x: x)
                    times[label].append(time.perf_counter() - t)
                finally:
                    module.one_thread = shipped  # type: ignore[attr-defined]
        med = {k: statistics.median(v) for k, v in times.items()}
        for label, sec in med.items():
            runs = ", ".join(f"{x:.2f}" for x in times[label])
            print(f"  {name:6s} {n:4d} frames, {label:12s} wall {sec:7.2f} s {n / sec:6.1f} fps  (runs: {runs})")
        one, many = med["one thread"], med[f"default ({default})"]
        print(f"{name}: one thread {many / one:.1f}x faster than torch's default threads")
    print(machine_line())
    return 0


if __name__ == "__main__":
    sys.exit(main())
