"""Render a run's rerun recording to a PNG, the way the viewer opens it (its blueprint included).

    python scripts/screenshot.py RUN_DIR OUT.png [--time S] [--size 1600x1000] [--colors N] [--timeout 120]

RUN_DIR is a run folder (its `run.rrd` is read) or an .rrd file. The script starts the rerun
viewer headless (`rerun --headless --window-size WxH --port P`, P a free port), opens the recording
in it, pauses the `time` timeline at S seconds (default: the middle of the recording), and saves a
screenshot of the whole viewer window (`--colors N`: reduced to an N-colour palette, a third of the
bytes at 256, for images kept in the repository). It talks to the viewer through the SDK's
`rerun.experimental.ViewerClient` rather than `rerun --screenshot-to`, which cannot place the time
cursor. Needs a Vulkan driver: on a machine without a GPU, Mesa's software one
(`apt-get install mesa-vulkan-drivers`); no X server is needed.

Exit status: 0 written, 2 bad arguments (missing recording), 1 the viewer failed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ptrack.io.viz import end_group


def free_port() -> int:
    """A TCP port nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def recording_path(run: Path) -> Path:
    """RUN_DIR/run.rrd, or RUN_DIR itself if it is a file; FileNotFoundError if missing."""
    path = run / "run.rrd" if run.is_dir() else run
    if not path.is_file():
        raise FileNotFoundError(f"no rerun recording at {path}")
    return path


def connect(port: int, viewer: subprocess.Popen, timeout: float):
    """A ViewerClient on the headless viewer at `port`, once it answers (RuntimeError if it exits)."""
    from rerun.experimental import ViewerClient

    deadline = time.monotonic() + timeout
    while True:
        if viewer.poll() is not None:
            raise RuntimeError(f"the rerun viewer exited with status {viewer.returncode}")
        try:
            client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
            client.get_state()
            return client
        except Exception:  # not listening yet
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def screenshot(
    rrd: Path, out: Path, at_s: float | None = None, size: str = "1600x1000", timeout: float = 120.0, colors: int = 0
) -> Path:
    """Render `rrd` in a headless viewer of `size` (logical points) at `time` = `at_s` seconds (None:
    the middle) and write the PNG to `out`, with a palette of `colors` colours if > 0. Returns `out`."""
    exe = shutil.which("rerun")
    if exe is None:
        raise RuntimeError("the `rerun` executable is not on PATH (pip install rerun-sdk)")
    port = free_port()
    env = dict(os.environ)
    runtime = tempfile.mkdtemp(prefix="ptrack-rerun-")  # the viewer wants an XDG runtime folder
    env.setdefault("XDG_RUNTIME_DIR", runtime)
    with tempfile.TemporaryFile() as log:
        # its own process group: `rerun` may be a launcher (pip's rerun-sdk) that starts the viewer
        # binary as a child, which must be stopped too
        viewer = subprocess.Popen(
            [
                exe,
                "--headless",
                "--port",
                str(port),
                "--window-size",
                size,
                "--hide-welcome-screen",
                "--memory-limit",
                "2GB",
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        try:
            client = connect(port, viewer, timeout)
            client.open(str(rrd.resolve()))
            deadline = time.monotonic() + timeout
            while True:  # until the recording and its timelines are loaded
                state = client.get_state()
                recordings = [r for r in state.recordings if r.store_id == state.active_recording]
                if recordings and not state.loading and any(t.name == "time" for t in recordings[0].timelines):
                    break
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{rrd} did not load in {timeout:.0f} s (state: {state})")
                time.sleep(0.2)
            line = next(t for t in recordings[0].timelines if t.name == "time")
            if at_s is None:
                at_ns = (line.start + line.end) // 2
            else:
                at_ns = min(max(round(at_s * 1e9), line.start), line.end)
            client.set_time("time", duration=at_ns / 1e9, play_state="paused")
            time.sleep(1.0)  # let the views settle on the new time (plots, 3D bounds)
            client.take_screenshot()  # the first paint after a seek can lag behind; keep the second
            png = client.take_screenshot()
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_bytes(png)
            if colors:
                from PIL import Image

                with Image.open(out) as image:
                    image.convert("RGB").quantize(colors).save(out, optimize=True)
        except BaseException:
            log.seek(0)
            sys.stderr.write(log.read().decode(errors="replace")[-4000:])
            raise
        finally:
            end_group(viewer, 10.0)  # the launcher and the viewer it started
            shutil.rmtree(runtime, ignore_errors=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="run folder (with run.rrd) or .rrd file")
    parser.add_argument("out", type=Path, help="PNG to write")
    parser.add_argument("--time", type=float, default=None, help="seconds on the `time` timeline (default: middle)")
    parser.add_argument("--size", default="1600x1000", help="viewer window size in logical points, WxH")
    parser.add_argument("--colors", type=int, default=0, help="reduce to a palette of N colours (0: keep all)")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the viewer")
    args = parser.parse_args(argv)
    try:
        rrd = recording_path(args.run)
    except FileNotFoundError as e:
        print(f"screenshot: error: {e}", file=sys.stderr)
        return 2
    try:
        screenshot(rrd, args.out, args.time, args.size, args.timeout, args.colors)
    except Exception as e:  # the viewer's own output is on stderr already
        print(f"screenshot: error: {e}", file=sys.stderr)
        return 1
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
