"""The network thread's two queues: urgent jobs first, each queue in submission order, errors where read."""

import threading

import pytest

from runtime.dense.worker import PriorityWorker


def test_urgent_jobs_overtake_queued_later_work_and_each_queue_keeps_its_order():
    w = PriorityWorker("test")
    gate, started, order = threading.Event(), threading.Event(), []
    w.submit(lambda: (started.set(), gate.wait()))  # holds the thread while the queues fill
    assert started.wait(10)
    jobs = [
        w.submit(order.append, "later 1", urgent=False),
        w.submit(order.append, "urgent 1"),
        w.submit(order.append, "later 2", urgent=False),
        w.submit(order.append, "urgent 2"),
    ]
    assert w.pending() == (2, 2)
    gate.set()
    for j in jobs:
        j.result(timeout=10)
    assert order == ["urgent 1", "urgent 2", "later 1", "later 2"]
    w.shutdown()


def test_a_job_error_is_raised_where_its_result_is_read_and_the_thread_goes_on():
    w = PriorityWorker("test")
    bad = w.submit(lambda: 1 / 0)
    good = w.submit(lambda: 7, urgent=False)
    with pytest.raises(ZeroDivisionError):
        bad.result(timeout=10)
    assert good.result(timeout=10) == 7
    w.shutdown()


def test_shutdown_runs_every_submitted_job_then_refuses_more():
    w = PriorityWorker("test")
    gate, done = threading.Event(), []
    w.submit(gate.wait)
    for i in range(5):
        w.submit(done.append, i, urgent=i % 2 == 0)
    gate.set()
    w.shutdown(wait=True)
    assert sorted(done) == list(range(5)) and done == [0, 2, 4, 1, 3]
    with pytest.raises(RuntimeError, match="after shutdown"):
        w.submit(done.append, 9)
