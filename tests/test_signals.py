"""Processes that outlive a kill: `kill PID` (SIGTERM) of `ptrack evaluate --jobs 2`, `ptrack replay --web`
and `ptrack run` ends the command as Ctrl-C does (`ptrack: terminated`, status 143): no worker or server is
left, nothing is written afterwards, no hidden `.partial` folder stays. A run's claim on its out_dir (the
locked `.NAME.partial` sibling, taken before any work) makes a second run into it refuse at once, and what
a SIGKILLed run left is removed by the next run into the same folder, never a live run's.

The commands run as subprocesses of `python -m ptrack.cli` with this checkout first on PYTHONPATH; their
processes are found through /proc (no dependency). Waits are generous (the machine may be slow and shared);
nothing is timed."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from ptrack.cli import main

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads processes from /proc; POSIX signals"
)

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo.yaml"
EVAL = REPO / "configs" / "eval_frame.yaml"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
FAST = ["data.stop=48", "data.stride=4", "frame.iterations=15", "frame.first_iterations=60", "progress=false"]
QUICK = [*FAST, "frame.iterations=3", "frame.first_iterations=5"]
LONG = ["progress=false", "frame.iterations=400", "frame.first_iterations=400"]  # minutes: killed before it ends
OUTPUTS = ["config.yaml", "metrics.json", "plots", "result.bvh", "result.npz", "run.rrd", "skeleton.urdf"]
WAIT_S = 300  # for a process to reach a state (slow, shared machines); never an assertion on speed


def _start(args: list[str], log: Path, **kw) -> subprocess.Popen:
    """`python -m ptrack.cli ARGS` with this checkout's ptrack, stderr into `log`."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    with log.open("w") as err:
        return subprocess.Popen([sys.executable, "-m", "ptrack.cli", *args], cwd=REPO, env=env, stderr=err, **kw)


def _wait_for(what: str, done: Callable[[], bool], proc: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + WAIT_S
    while not done():
        if proc.poll() is not None:
            pytest.fail(f"the command ended ({proc.returncode}) before {what}: {log.read_text()}")
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} after {WAIT_S} s: {log.read_text()}")
        time.sleep(0.05)


def _stat(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command name (state first, ppid second), or None if gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()


def _descendants(pid: int) -> dict[int, str]:
    """Every live process below `pid`: {pid: its start time (to tell a reused pid)}."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            fields = _stat(int(entry.name))
            if fields is not None and fields[0] != "Z":
                parents[int(entry.name)] = (int(fields[1]), fields[19])
    found: dict[int, str] = {}
    todo = [pid]
    while todo:
        p = todo.pop()
        for child, (ppid, start) in parents.items():
            if ppid == p and child not in found:
                found[child] = start
                todo.append(child)
    return found


def _alive(pids: dict[int, str]) -> list[int]:
    """Those of `pids` still running (a zombie or a new process under a reused pid is not)."""
    left = []
    for pid, start in pids.items():
        fields = _stat(pid)
        if fields is not None and fields[0] != "Z" and fields[19] == start:
            left.append(pid)
    return left


def _all_gone(pids: dict[int, str]) -> list[int]:
    """Wait (generously) for every one of `pids` to end; -> those still running."""
    deadline = time.monotonic() + 60
    while _alive(pids) and time.monotonic() < deadline:
        time.sleep(0.1)
    return _alive(pids)


def _kill_left(pids: dict[int, str]) -> None:
    """After a failed test: end what it started (by pid) so no process outlives it."""
    for pid in _alive(pids):
        os.kill(pid, signal.SIGKILL)


def _hidden(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob(".*"))


def _terminated(proc: subprocess.Popen, log: Path) -> str:
    """SIGTERM `proc`; assert it ends as Ctrl-C would (status 143, last line `ptrack: terminated`, no traceback)."""
    os.kill(proc.pid, signal.SIGTERM)
    proc.wait(timeout=WAIT_S)
    err = log.read_text()
    assert proc.returncode == 143, err
    assert err.rstrip().splitlines()[-1] == "ptrack: terminated" and "Traceback" not in err, err
    return err


def test_sigterm_stops_every_evaluate_worker(tmp_path):
    """`kill PID` of `evaluate --jobs 2` while its workers run: status 143, every worker (and multiprocessing's
    helper) ends, no run folder is written afterwards, nothing half-written is left."""
    out, log = tmp_path / "eval", tmp_path / "stderr.txt"
    args = ["evaluate", str(EVAL), *QUICK, "--clips", str(AMC), "--seeds", "0-9", "--jobs", "2", "--out", str(out)]
    proc = _start(args, log)
    children: dict[int, str] = {}
    try:
        _wait_for("worker inside a run", lambda: any((out / "10_02").glob(".*.partial")), proc, log)
        children = _descendants(proc.pid)
        assert len(children) >= 2  # the two workers
        _terminated(proc, log)
        assert _all_gone(children) == []
        runs = sorted(p.name for p in (out / "10_02").iterdir())
        time.sleep(3)  # a worker left running would write its next folder
        assert sorted(p.name for p in (out / "10_02").iterdir()) == runs
        assert len(runs) < 10 and _hidden(out) == []
        for run in runs:
            assert sorted(p.name for p in (out / "10_02" / run).iterdir()) == OUTPUTS
        assert not (out / "results.md").exists()
    finally:
        proc.kill()
        _kill_left(children)


def _recording(path: Path) -> Path:
    import rerun as rr

    rec = rr.RecordingStream("ptrack-test")
    rec.save(path)
    rec.log("points", rr.Points3D([[0.0, 0.0, 0.0]]))
    rec.disconnect()
    return path


def _ports(url: str) -> list[int]:
    """The two ports in `ptrack replay --web`'s address: the viewer's and rerun's gRPC server's."""
    from urllib.parse import unquote

    web = int(url.split("://", 1)[1].split("?")[0].rsplit(":", 1)[1])
    grpc = int(unquote(url).rsplit(":", 1)[1].split("/")[0])
    return [web, grpc]


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_sigterm_stops_the_replay_web_server(tmp_path):
    """`kill PID` of `replay --web` while it serves: status 143, rerun's launcher and server end, both ports
    are free again."""
    rrd, log = _recording(tmp_path / "run.rrd"), tmp_path / "stderr.txt"
    proc = _start(["replay", str(rrd), "--web"], log, stdout=subprocess.PIPE, text=True)
    children: dict[int, str] = {}
    try:
        assert proc.stdout is not None
        ports = _ports(proc.stdout.readline().strip())
        _wait_for("server listening", lambda: all(_listening(p) for p in ports), proc, log)
        children = _descendants(proc.pid)
        assert len(children) >= 2  # `python -m rerun` and the rerun binary it starts
        _terminated(proc, log)
        assert _all_gone(children) == []
        for port in ports:
            with socket.socket() as s:
                s.bind(("127.0.0.1", port))  # free again
    finally:
        proc.kill()
        _kill_left(children)


def test_sigterm_during_a_run_leaves_nothing(tmp_path):
    """`kill PID` of `ptrack run` while it computes: status 143, nothing at out_dir, no hidden folder beside it."""
    out, log = tmp_path / "runs" / "demo", tmp_path / "stderr.txt"
    proc = _start(["run", str(DEMO), *LONG, f"out_dir={out}"], log)
    try:
        _wait_for("claim on out_dir", lambda: (out.parent / ".demo.partial").is_dir(), proc, log)
        _terminated(proc, log)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["stderr.txt"]  # not even the parent it made
    finally:
        proc.kill()


def _one_error(capsys, argv: list[str]) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: ") and "Traceback" not in err, err
    return lines[0]


def test_a_second_run_into_the_same_out_dir_refuses_at_once(tmp_path, capsys):
    """While one run computes into out_dir (held still by SIGSTOP, so the order is sure), another into the same
    out_dir refuses before any work with one line naming the first's pid; the first then ends as usual, with
    exactly its files at out_dir."""
    out, log = tmp_path / "demo", tmp_path / "stderr.txt"
    first = _start(["run", str(DEMO), *FAST, f"out_dir={out}"], log, stdout=subprocess.PIPE, text=True)
    try:
        _wait_for("claim on out_dir", lambda: (tmp_path / ".demo.partial").is_dir(), first, log)
        os.kill(first.pid, signal.SIGSTOP)
        try:
            line = _one_error(capsys, ["run", str(DEMO), *QUICK, f"out_dir={out}"])
        finally:
            os.kill(first.pid, signal.SIGCONT)
        assert f"out_dir {out} is being written by another run (pid {first.pid})" in line
        stdout, _ = first.communicate(timeout=WAIT_S)
        assert first.returncode == 0, log.read_text()
        assert stdout.strip() == str(out)
        assert sorted(p.name for p in out.iterdir()) == OUTPUTS
        assert json.loads((out / "metrics.json").read_text())["frames"] == 12
        assert sorted(p.name for p in tmp_path.iterdir()) == ["demo", "stderr.txt"]
    finally:
        first.kill()


def test_a_later_run_removes_what_a_killed_run_left_but_not_a_live_runs_claim(tmp_path, capsys):
    """A run SIGKILLed while it computes leaves its `.NAME.partial` (nothing can clean up after SIGKILL); the
    next run into the same folder removes it, and leaves alone the claim of a run still alive."""
    logs = tmp_path / "logs"
    logs.mkdir()
    # the live run claims first: a run removes stale claims when it takes its own, so one started after the
    # kill would already clean up what the later run is to clean up
    live = _start(["run", str(DEMO), *LONG, f"out_dir={tmp_path / 'live'}"], logs / "live.txt")
    killed = None
    try:
        _wait_for("claim", lambda: (tmp_path / ".live.partial").is_dir(), live, logs / "live.txt")
        os.kill(live.pid, signal.SIGSTOP)  # alive, though not computing while the others run
        killed = _start(["run", str(DEMO), *LONG, f"out_dir={tmp_path / 'killed'}"], logs / "killed.txt")
        _wait_for("claim", lambda: (tmp_path / ".killed.partial").is_dir(), killed, logs / "killed.txt")
        killed.kill()
        killed.wait(timeout=WAIT_S)
        assert (tmp_path / ".killed.partial").is_dir()  # what SIGKILL left
        assert main(["run", str(DEMO), *QUICK, f"out_dir={tmp_path / 'later'}", "--quiet"]) == 0
        assert sorted(p.name for p in tmp_path.iterdir()) == [".live.partial", "later", "logs"]
        assert live.poll() is None
    finally:
        if killed is not None:
            killed.kill()
        os.kill(live.pid, signal.SIGCONT)
        live.kill()
        live.wait(timeout=WAIT_S)


def test_an_ignored_hangup_stays_ignored_and_handlers_are_restored(monkeypatch):
    """Under `nohup` (SIGHUP ignored) the command does not start ending on a hangup; SIGTERM is handled; after
    `main` returns (in-process callers) both signals have their handlers back."""
    import ptrack.cli

    old_hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    old_term = signal.getsignal(signal.SIGTERM)
    try:
        seen = {}

        def handlers(args) -> int:
            seen.update(hup=signal.getsignal(signal.SIGHUP), term=signal.getsignal(signal.SIGTERM))
            return 0

        monkeypatch.setattr(ptrack.cli, "_main", handlers)
        assert main(["replay", "x.rrd"]) == 0
        assert seen["hup"] is signal.SIG_IGN and callable(seen["term"]) and seen["term"] is not old_term
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN and signal.getsignal(signal.SIGTERM) is old_term
    finally:
        signal.signal(signal.SIGHUP, old_hup)


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_sigterm_stops_every_batch_worker(tmp_path, executor):
    """`kill PID` of `ptrack batch --workers 2` (local worker processes, or a local Ray runtime) while items run:
    status 143, every process it started ends (Ray's too), nothing half-written is left, and status.csv still
    lists every item (the finished ones done, the others pending)."""
    if executor == "ray":
        pytest.importorskip("ray", reason="the ray extra is not installed")
    clips = tmp_path / "clips"
    clips.mkdir()
    (clips / "10.asf").write_bytes((REPO / "ptrack" / "data" / "10.asf").read_bytes())
    for k in range(6):
        (clips / f"10_0{k}.amc").write_bytes(AMC.read_bytes())
    out, log = tmp_path / "out", tmp_path / "stderr.txt"
    args = ["batch", str(EVAL), *QUICK, "--inputs", str(clips / "*.amc"), "--out", str(out), "--workers", "2"]
    proc = _start([*args, "--executor", executor], log)
    children: dict[int, str] = {}
    try:
        _wait_for("worker inside a run", lambda: any(out.glob(".*.partial")), proc, log)
        children = _descendants(proc.pid)
        assert len(children) >= 2  # the two workers (and with Ray its runtime's processes)
        _terminated(proc, log)
        assert _all_gone(children) == []
        assert _hidden(out) == []
        states = [line.split(",")[3] for line in (out / "status.csv").read_text().splitlines()[1:]]
        assert len(states) == 6 and set(states) <= {"done", "pending"} and "pending" in states
        assert not (out / "results.md").exists()
    finally:
        proc.kill()
        _kill_left(children)
