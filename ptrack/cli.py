"""Command line: `ptrack run CONFIG [key=value ...]`, `ptrack evaluate CONFIG --clips LIST`,
`ptrack compare EVAL_A EVAL_B`, `ptrack fit-motion CONFIG [--out FILE]`, `ptrack replay RUN_DIR`,
`ptrack config --list [SECTION]`, `ptrack detect VIDEO [--out FILE]`.

stdout carries only what a script reads: the run folder's path (the table's for `evaluate`), or with
`--json` the metrics (`results.json` for `evaluate`); messages and progress go to stderr, progress bars
only on a terminal. A closed stdout (`| head`) ends the command quietly with status 141, as SIGPIPE would.

The only module that reads argv. User errors (`InputError`, missing files, bad YAML) print one
line `ptrack: error: ...` and exit 2; an estimator failure (`EstimationError`, e.g. non-finite
poses) prints one such line and exits 1; anything else is a bug and keeps its traceback.

Ctrl-C ends a command with `ptrack: interrupted` and status 130; SIGTERM (`kill PID`) and SIGHUP end it the
same way (`ptrack: terminated`, status 128 + the signal's number: 143, 129): the signal is raised as
`Terminated` (a KeyboardInterrupt) in the main thread, so the same cleanup runs: an evaluation's workers
are stopped, replay's viewer or server is stopped, a run's half-written folder is removed.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path

from ptrack import __version__
from ptrack.errors import EstimationError, InputError, log_to_stderr  # light: torch is imported only by the commands


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ptrack", description="3D human motion from a single camera.")
    p.add_argument("--version", action="version", version=f"ptrack {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run", help="run a config: writes config.yaml, metrics.json, result.npz, result.bvh, run.rrd")
    r.add_argument("config", help="YAML run config, e.g. configs/demo.yaml")
    r.add_argument("overrides", nargs="*", help="dotted.key=value overrides, e.g. seed=3 data.stride=2")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--json", action="store_true", help="print metrics.json on stdout instead of the run folder's path")
    e = sub.add_parser("evaluate", help="run a config over several clips and write a markdown table")
    e.add_argument("config", help="YAML run config, e.g. configs/eval_frame.yaml")
    e.add_argument("overrides", nargs="*", help="dotted.key=value overrides applied to every clip")
    e.add_argument(
        "--clips",
        required=True,
        help="AMC files: a comma-separated list, a text file with one path per line (relative to that file) or a "
        "glob ('cmu/subjects/*/*_01.amc'); each clip's ASF is the .asf in the AMC's folder",
    )
    e.add_argument(
        "--seeds",
        default=None,
        help="run every clip once per seed, e.g. 0-4 or 0,3,7: each clip's row is the mean over the seeds, "
        "a second table gives each seed's mean over the clips",
    )
    e.add_argument("--out", default=None, help="output folder (default logs/eval-<config>-<time>)")
    e.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="runs at once, each in its own process on one thread (default 1); the results do not change",
    )
    e.add_argument("--quiet", action="store_true", help="no progress (bar on a terminal, one line per clip elsewhere)")
    e.add_argument("--json", action="store_true", help="print results.json on stdout instead of the table's path")
    b = sub.add_parser("batch", help="run a config over many inputs (keypoint files, videos), resumable, local or Ray")
    b.add_argument("config", help="YAML run config, e.g. configs/video.yaml")
    b.add_argument("overrides", nargs="*", help="dotted.key=value overrides applied to every input")
    b.add_argument(
        "--inputs",
        required=True,
        help="a comma-separated list, a .txt list, a glob ('videos/*.mp4') or a CSV manifest (an `input` column, "
        "other columns config keys overriding per row)",
    )
    b.add_argument("--out", required=True, help="output folder: one run folder per input, status.csv, results.md")
    b.add_argument("--workers", type=int, default=None, help="runs at once (default: the number of cores)")
    b.add_argument("--executor", default="local", help="local (worker processes, default) or ray")
    b.add_argument("--ray-address", default=None, help="with --executor ray: auto or HOST:PORT (default: a local Ray)")
    b.add_argument("--resume", action="store_true", help="continue --out: skip the complete runs, redo the others")
    b.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="run every value (repeatable: the cross product), each setting in its own sub-folder",
    )
    b.add_argument("--quiet", action="store_true", help="no progress (bar on a terminal, one line per item elsewhere)")
    b.add_argument("--json", action="store_true", help="print results.json on stdout instead of the table's path")
    c = sub.add_parser("compare", help="two evaluations seed by seed: means, differences with their spread, wins")
    c.add_argument("a", help="a `ptrack evaluate` folder (or its results.json)")
    c.add_argument("b", help="another, on the same clips and seeds")
    c.add_argument(
        "--metrics",
        nargs="+",
        default=None,
        help="metrics.json keys to compare (default: mpjpe_mm best_of_k_mpjpe_mm flip_error_rate)",
    )
    c.add_argument("--names", nargs=2, default=None, metavar=("A", "B"), help="column names (default: the folders')")
    c.add_argument("--json", action="store_true", help="print the comparison as JSON instead of a markdown table")
    f = sub.add_parser("fit-motion", help="fit a PCA motion model to the config's motion.clips and write it")
    f.add_argument("config", help="YAML config with a motion: section, e.g. configs/golf_motion.yaml")
    f.add_argument("overrides", nargs="*", help="dotted.key=value overrides, e.g. motion.components=3")
    f.add_argument(
        "--out",
        default=None,
        help="model file to write (default: motion.model_file, else ~/.cache/ptrack/motion/<config>.npz)",
    )
    v = sub.add_parser("replay", help="open a run's recording in the rerun viewer")
    v.add_argument("run_dir", help="a run folder (holding run.rrd) or an .rrd file")
    v.add_argument(
        "--web",
        action="store_true",
        help="serve rerun's web viewer instead (no display needed) and print the address to open",
    )
    v.add_argument("--bind", default="127.0.0.1", help="with --web: the address to listen on (default 127.0.0.1)")
    d = sub.add_parser(
        "detect", help="MediaPipe Pose on every frame of a video (the video extra): writes its landmarks"
    )
    d.add_argument("video", help="a video file OpenCV decodes, e.g. an .mp4")
    d.add_argument(
        "--out", default=None, help="landmarks file to write (default: VIDEO_STEM.landmarks.npz in the current folder)"
    )
    d.add_argument(
        "--quiet", action="store_true", help="no progress (bar on a terminal, a line now and then elsewhere)"
    )
    x = sub.add_parser(
        "export", help="a run folder as TRC, MOT, C3D, BVH, JSON or CSV for OpenSim, Blender and other tools"
    )
    x.add_argument("run_dir", help="a run folder written by `ptrack run`")
    x.add_argument("--format", required=True, help="the output format (see docs/outputs.md): e.g. trc, bvh")
    x.add_argument("--out", default=None, help="output folder, or file for one-file formats (default RUN_DIR/export/)")
    x.add_argument("--up", choices=("y", "z"), default=None, help="the output's up axis (default: the format's own)")
    x.add_argument("--names", default=None, help="BVH: joint names for a retargeting rig, e.g. mixamo")
    x.add_argument("--rest", choices=("asf", "tpose"), default=None, help="BVH rest pose (default asf: the skeleton's)")
    x.add_argument(
        "--opensim", default=None, metavar="MODEL.osim", help="MOT: OpenSim's inverse kinematics on this model"
    )
    x.add_argument(
        "--points",
        choices=("keypoints", "joints"),
        default=None,
        help="TRC/C3D: the input's keypoints (footage runs) or the skeleton's joints (default: keypoints if any)",
    )
    k = sub.add_parser("config", help="list the config keys: default, type and one line of help each")
    k.add_argument(
        "--list",
        nargs="?",
        const="",
        default="",
        metavar="SECTION",
        help="one line per key, `key = default  (type)  help`; a section (e.g. kjs) lists its keys only",
    )
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Parse argv; the config, flags and `key=value` overrides may come in any order."""
    parser = _parser()
    args, extra = parser.parse_known_args(argv)
    # argparse hands the positional `overrides` only the run of them right after the config; later
    # ones (after a flag) come back as unknown arguments, in order
    unknown = [a for a in extra if a.startswith("-") or not hasattr(args, "overrides")]
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    if extra:
        args.overrides = [*args.overrides, *extra]
    if hasattr(args, "overrides"):
        _config_first(parser, args)
    return args


def _config_first(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The config file may stand anywhere among the `key=value` overrides (`ptrack run seed=3 x.yaml`):
    argparse takes the first positional as the config, so when that one is an override, the first
    argument without '=' is the config and the overrides keep their order. A config path that holds '='
    and exists is taken as it is."""
    if "=" not in args.config or Path(args.config).exists():
        return
    given = [args.config, *args.overrides]
    plain = [a for a in given if "=" not in a]
    if not plain:
        parser.error(f"no config file given: every argument is a key=value override ({' '.join(given)})")
    args.config = plain[0]
    given.remove(plain[0])
    args.overrides = given


def _eval_name(path: str) -> str:
    """An evaluation's name for `compare`: its folder's (the folder holding results.json if given the file)."""
    p = Path(path)
    return (p.parent if p.name == "results.json" else p).resolve().name or str(path)


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP received: raised where the main thread is, so that the cleanup Ctrl-C runs runs too."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _on_signals() -> dict[int, object]:
    """Turn SIGTERM and SIGHUP into `Terminated` (the first of them only: a second one does not cut the
    cleanup short); -> the handlers they replace. A signal ignored already (`nohup`) stays ignored. Only the
    main thread can set handlers: elsewhere, nothing."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    raised: list[int] = []

    def handler(signum: int, frame: object) -> None:
        if not raised:
            raised.append(signum)
            raise Terminated(signum)

    wanted = [getattr(signal, s) for s in ("SIGTERM", "SIGHUP") if hasattr(signal, s)]
    return {int(s): signal.signal(s, handler) for s in wanted if signal.getsignal(s) is not signal.SIG_IGN}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    previous = _on_signals()
    try:
        return _main(args)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)  # type: ignore[arg-type]  # what signal.signal returned


def _main(args: argparse.Namespace) -> int:
    log_to_stderr()
    logging.getLogger("ptrack.pipeline.evaluate").setLevel(logging.INFO)  # its one line per clip off a terminal
    try:
        if args.command == "run":
            from ptrack.pipeline.config import load_config
            from ptrack.pipeline.run import execute

            cfg = load_config(args.config, args.overrides)
            logging.getLogger("ptrack.pipeline.run.progress").setLevel(logging.INFO)  # its lines off a terminal
            out = execute(cfg, progress=False if args.quiet else None)
            print((out / "metrics.json").read_text() if args.json else out, end="" if args.json else "\n", flush=True)
        elif args.command == "evaluate":
            from ptrack.pipeline.evaluate import evaluate, parse_seeds

            seeds = None if args.seeds is None else parse_seeds(args.seeds)
            table = evaluate(
                args.config,
                args.clips,
                args.overrides,
                out=args.out,
                progress=False if args.quiet else None,
                seeds=seeds,
                jobs=args.jobs,
            )
            json_path = table.with_name("results.json")
            print(json_path.read_text() if args.json else table, end="" if args.json else "\n", flush=True)
        elif args.command == "batch":
            from ptrack.pipeline.batch_run import batch

            logging.getLogger("ptrack.pipeline.batch_run").setLevel(logging.INFO)  # its one line per item
            summary = batch(
                args.config,
                args.inputs,
                args.out,
                args.overrides,
                workers=args.workers,
                executor=args.executor,
                ray_address=args.ray_address,
                resume=args.resume,
                sets=args.set,
                progress=False if args.quiet else None,
            )
            json_path = summary.table.with_name("results.json")
            print(json_path.read_text() if args.json else summary.table, end="" if args.json else "\n", flush=True)
            return 1 if summary.failed else 0
        elif args.command == "compare":
            from ptrack.pipeline.compare import as_json, compare, load_runs, markdown

            names = args.names or [_eval_name(args.a), _eval_name(args.b)]
            if names[0] == names[1]:  # two folders of one name (runs/x/eval, runs/y/eval)
                names = ["A", "B"]
            rows = compare(load_runs(args.a), load_runs(args.b), args.metrics)
            print((as_json if args.json else markdown)(rows, *names), end="", flush=True)
        elif args.command == "fit-motion":
            import time

            from ptrack.motion.motion_model import check_writable, fit_from_config, model_path, save_motion_model
            from ptrack.pipeline.config import load_config

            cfg = load_config(args.config, args.overrides, run=False)
            out = check_writable(Path(args.out) if args.out else model_path(cfg))
            start = time.perf_counter()
            model = fit_from_config(cfg)
            seconds = time.perf_counter() - start
            save_motion_model(model, out)
            assert model.info is not None  # a fitted model records its clips
            shares = ", ".join(f"{100 * float(e):.1f}%" for e in model.explained)
            print(
                f"ptrack: {len(model.info['clips'])} clips, {model.num_components} components explain {shares} "
                f"of the variance ({100 * float(model.explained.sum()):.1f}% in all); fitted in {seconds:.1f} s",
                file=sys.stderr,
            )
            print(out, flush=True)
        elif args.command == "detect":
            import time

            from ptrack.observe.detector import check_output, default_output, detect
            from ptrack.observe.keypoint_files import write_mediapipe_landmarks
            from ptrack.pipeline.run import progress_display

            out = check_output(args.out or default_output(args.video))  # before minutes of detection
            logging.getLogger("ptrack.pipeline.run.progress").setLevel(logging.INFO)  # its lines off a terminal
            start = time.perf_counter()
            found = detect(args.video, progress=progress_display(not args.quiet, "detect"))
            seconds = time.perf_counter() - start
            write_mediapipe_landmarks(out, found)
            T = len(found.frames)
            print(
                f"ptrack: a person in {int(found.found.sum())} of {T} frames; {T / max(seconds, 1e-9):.1f} frames/s",
                file=sys.stderr,
            )
            print(out, flush=True)
        elif args.command == "export":
            from ptrack.io.exporters import ExportOptions, export_run

            options = ExportOptions(
                up=args.up, names=args.names, rest=args.rest, opensim=args.opensim, points=args.points
            )
            for path in export_run(args.run_dir, args.format, args.out, options):
                print(path, flush=True)
        elif args.command == "config":
            from ptrack.pipeline.config import config_reference

            for key in config_reference(args.list or None):
                print(f"{key.key} = {key.default}  ({key.type})  {key.help}")
        elif args.command == "replay":
            from ptrack.io.viz import open_viewer

            path = Path(args.run_dir)
            rrd = path / "run.rrd" if path.is_dir() else path
            if not rrd.exists():
                raise FileNotFoundError(f"no recording at {rrd} (give a run folder holding run.rrd)")
            if args.web:
                from ptrack.io.viz import run_child, web_viewer_command

                cmd, url = web_viewer_command(rrd, args.bind)  # checks that rrd is a recording
                print(url, flush=True)
                print(f"ptrack: serving {rrd} to the web viewer at {url} (Ctrl-C stops)", file=sys.stderr, flush=True)
                return run_child(cmd, env={**os.environ, "RUST_LOG": "warn"})
            return open_viewer(rrd) or 0
    except (InputError, FileNotFoundError, IsADirectoryError, NotADirectoryError) as e:
        print(f"ptrack: error: {e}", file=sys.stderr)
        return 2
    except EstimationError as e:
        print(f"ptrack: error: {e}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # the reader of stdout has gone (`| head -0`): no traceback, no flush error at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except Terminated as e:
        name = "" if e.signum == getattr(signal, "SIGTERM", None) else f" ({signal.Signals(e.signum).name})"
        print(f"ptrack: terminated{name}", file=sys.stderr)
        return 128 + e.signum
    except KeyboardInterrupt:
        print("ptrack: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
