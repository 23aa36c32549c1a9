"""Tests for ptrack.threads: the thread budget and the two-thread split."""

from __future__ import annotations

import threading

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
