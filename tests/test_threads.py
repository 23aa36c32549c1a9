"""Tests for ptrack.threads: the thread budget, the two-thread split and the two processes."""

from __future__ import annotations

import os
import threading
import time

import pytest
import torch

from ptrack import threads as th


def test_thread_budget_and_two_threads():
    """one_thread keeps the count it replaced as the budget parallel_halves reads (CPU only); on_two_threads
    returns both results in order, the first computed on the worker thread."""
    before = torch.get_num_threads()
    try:
        for budget in (1, 2):
            torch.set_num_threads(budget)
            with th.one_thread():
                assert torch.get_num_threads() == 1
                assert th.parallel_halves(torch.device("cpu")) == (budget >= 2)
                assert not th.parallel_halves(torch.device("meta"))
            assert torch.get_num_threads() == budget
    finally:
        torch.set_num_threads(before)
    names = th.on_two_threads(lambda x: (x, threading.current_thread().name), (1,), (2,))
    assert [n[0] for n in names] == [1, 2]
    assert names[0][1].startswith("ptrack-banded") and names[1][1] == threading.current_thread().name


def test_two_processes(tmp_path):
    """in_two_processes returns (first(), second()) with first() computed in a forked child; the child's exception
    is raised here with its type; a child that dies without an answer has first() run here instead; an
    exception in second() kills the child before it is raised. parallel_processes: a budget of 2 on the CPU, inside
    `one_thread` only."""
    here = os.getpid()
    assert th.in_two_processes(os.getpid, lambda: "second")[1] == "second"
    assert th.in_two_processes(os.getpid, os.getpid)[0] not in (here, None)

    def fails():
        raise ValueError("bad frame 7")

    with pytest.raises(ValueError, match="bad frame 7"):
        th.in_two_processes(fails, lambda: None)
    assert th.in_two_processes(lambda: os._exit(3) if os.getpid() != here else "ran here", lambda: 0) == ("ran here", 0)

    marker, finished = tmp_path / "child", tmp_path / "finished"

    def slow():
        marker.write_text(str(os.getpid()))
        time.sleep(20)
        finished.write_text("the child was waited for, not killed")

    def second():
        while not marker.exists() or not marker.read_text():
            time.sleep(0.01)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        th.in_two_processes(slow, second)
    with pytest.raises(ProcessLookupError):  # killed and reaped: no such process left
        os.kill(int(marker.read_text()), 0)
    assert not finished.exists()
    before = torch.get_num_threads()
    try:
        for budget in (1, 2):
            torch.set_num_threads(budget)
            with th.one_thread():
                assert th.parallel_processes(torch.device("cpu")) == (budget >= 2 and hasattr(os, "fork"))
                assert not th.parallel_processes(torch.device("meta"))
            assert not th.parallel_processes(torch.device("cpu"))  # outside one_thread: torch's pool may run
    finally:
        torch.set_num_threads(before)
