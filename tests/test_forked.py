"""lrfcal.runtime.forked: tasks on every core without pickling their inputs, and the fallbacks that run a task here."""

from __future__ import annotations

import multiprocessing
import os
import time

import pytest

from lrfcal.runtime.forked import Ahead, call_forked, cores

PARENT = os.getpid()


def _pid() -> int:
    return os.getpid()


def _dies_in_a_child() -> str:
    if os.getpid() != PARENT:
        os._exit(3)  # a child that dies (as out of memory would): the task must run again in the parent
    return "here"


FORKS = cores() >= 2 and "fork" in multiprocessing.get_all_start_methods()
NO_FORKS = "one core or no fork: every task runs in the process (the fallback tested below)"


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_tasks_run_in_forked_children_that_read_the_parents_data() -> None:
    big = list(range(100_000))  # read by the children without being pickled

    def total() -> int:
        return sum(big)

    out = call_forked({"first": _pid, "second": _pid, "sum": total})
    assert list(out) == ["first", "second", "sum"]
    assert out["first"] == os.getpid() and out["second"] != os.getpid()
    assert out["sum"] == sum(big)


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_a_task_whose_child_dies_runs_here() -> None:
    assert call_forked({"first": _pid, "dies": _dies_in_a_child}) == {"first": os.getpid(), "dies": "here"}


def _in_a_daemon(_: int) -> list[bool]:
    out = call_forked({"a": _pid, "b": _pid})
    return [v == os.getpid() for v in out.values()]


def test_a_daemonic_process_runs_every_task_itself() -> None:
    """A pool's worker may not have children: its tasks run in it."""
    with multiprocessing.get_context("fork").Pool(1) as pool:
        assert pool.map(_in_a_daemon, [0]) == [[True, True]]


PREPARED: list[int] = []


def _prepare() -> None:
    PREPARED.append(os.getpid())


def _where_prepared(x: int) -> tuple[int, int, bool]:
    return x + 1, os.getpid(), os.getpid() in PREPARED


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_ahead_prepares_in_a_child_and_runs_the_call_there() -> None:
    PREPARED.clear()
    with Ahead(_prepare) as ahead:
        value, pid, prepared = ahead.call(_where_prepared, 41)
    assert value == 42 and pid != os.getpid() and prepared  # run in the child, after its prepare()
    assert PREPARED == []  # nothing prepared here


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_ahead_runs_the_call_here_when_the_child_dies_or_it_does_not_pickle() -> None:
    PREPARED.clear()
    with Ahead(_prepare) as ahead:
        assert ahead.call(_dies_in_a_child) == "here"
    assert [os.getpid()] == PREPARED  # prepared here before the call ran here
    t0 = time.perf_counter()
    with Ahead(_prepare) as ahead:
        assert ahead.call(lambda x: 2 * x, 21) == 42  # a lambda does not pickle
    assert time.perf_counter() - t0 < 0.9  # the child ended with the pipe, not by the exit's 1 s timeout


def test_ahead_left_by_an_error_ends_its_child_at_once() -> None:
    t0 = time.perf_counter()
    with pytest.raises(KeyError), Ahead(lambda: time.sleep(5.0)):
        raise KeyError("refused")
    assert time.perf_counter() - t0 < 2.0
    assert not multiprocessing.active_children()


def _sum_and_none(values: object, nothing: object) -> tuple[int, object, int]:
    return sum(values), nothing, os.getpid()  # type: ignore[call-overload]


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_ahead_sends_what_the_child_inherited_by_reference_while_this_process_goes_on() -> None:
    from lrfcal.runtime.forked import _dumps

    big = list(range(200_000))
    with Ahead(_prepare, inherit=(big,)) as ahead:
        ahead.start(_sum_and_none, big, None)
        assert ahead.started
        here = sum(range(10))  # this process goes on while the child runs the call
        total, nothing, pid = ahead.result()
    assert (total, nothing, here) == (sum(big), None, 45) and pid != os.getpid()
    sent = _dumps((_sum_and_none, (big, None)), {id(big): big})
    assert len(sent) < 200  # a reference, not the 200 000 numbers; None is not taken for the inherited object
    assert len(_dumps((_sum_and_none, (list(big), None)), {id(big): big})) > 100_000  # an equal copy travels whole


def _slow_pid(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_ahead_runs_several_calls_in_the_order_sent_and_the_rest_here_after_a_death() -> None:
    """The report's figures: intensity.png sent on the association, the others on the fit, taken in that order."""
    PREPARED.clear()
    with Ahead(_prepare) as ahead:
        ahead.start(_slow_pid, 0.2)
        ahead.start(_where_prepared, 1)
        first, (value, pid, prepared) = ahead.result(), ahead.result()
        assert not ahead.started
    assert first == pid != os.getpid() and (value, prepared) == (2, True)  # both in the one child, in order
    with Ahead(_prepare) as ahead:
        ahead.start(_dies_in_a_child)
        ahead.start(_where_prepared, 2)
        assert ahead.result() == "here"
        value, pid, prepared = ahead.result()  # the child is gone: the later call runs here, prepared once
    assert (value, pid, prepared) == (3, os.getpid(), True) and [os.getpid()] == PREPARED
    with Ahead(_prepare) as ahead:
        ahead.start(_slow_pid, 0.1)
        with pytest.raises(RuntimeError):
            ahead.call(_pid)  # a call whose result would be taken out of order


def test_ahead_left_with_a_call_running_ends_its_child_at_once() -> None:
    """A calibration refused after intensity.png was sent: the drawing child is not waited for."""
    t0 = time.perf_counter()
    with pytest.raises(KeyError), Ahead(_prepare) as ahead:
        ahead.start(_slow_pid, 5.0)
        raise KeyError("refused")
    assert time.perf_counter() - t0 < 2.0
    assert not multiprocessing.active_children()


def _niceness() -> int:
    return os.nice(0)


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_ahead_nice_child_and_ready_calls() -> None:
    """Ahead(nice=) raises its child's niceness, not this process's; ready() is False while the oldest call runs in
    the child and True once it has finished (lrfcal.pipeline.search.proposal_ahead keeps the finished starts)."""
    here = os.nice(0)
    with Ahead(_prepare, nice=5) as ahead:
        ahead.start(_slow_pid, 1.0)
        ahead.start(_niceness)
        assert not ahead.ready()
        deadline = time.monotonic() + 30.0
        while not ahead.ready() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert ahead.ready()
        assert ahead.result() != os.getpid()
        assert ahead.result() == min(19, here + 5)
        assert not ahead.ready()  # no call left
    assert os.nice(0) == here


@pytest.mark.skipif(not FORKS, reason=NO_FORKS)
def test_ahead_start_returns_while_the_child_prepares_even_for_a_call_larger_than_the_pipe() -> None:
    """The figures' child is sent intensity.png's candidate mask (1.6 MB) while it still imports matplotlib: start()
    must not wait for the child to read it (a sender thread writes it), and the calls arrive in order."""
    big = b"x" * 4_000_000  # far beyond a pipe's buffer (64 KiB-1 MiB)
    with Ahead(lambda: time.sleep(1.5)) as ahead:
        t0 = time.perf_counter()
        ahead.start(len, big)
        ahead.start(len, big[:10])
        sent_in = time.perf_counter() - t0
        assert (ahead.result(), ahead.result()) == (4_000_000, 10)
    assert sent_in < 0.75  # before: the 1.5 s of the child's prepare()
