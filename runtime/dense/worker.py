"""One background thread with two queues: work the tracking thread waits for goes before work it does not.

The dense mapper's network thread runs two kinds of job. The tracking thread waits for some of them: a new
keyframe's network pass and the relinearisations of the code keyframes, which the next optimisation needs. It
never waits for the others: a leaving keyframe's map code, its depth metrics and its fusion into the map. With one
first-in-first-out queue an urgent job waited behind every later-work job queued before it, and the tracking thread
with it. :class:`PriorityWorker` runs the urgent queue first and each queue in the order it was submitted to, so a
job still sees every earlier job of its own queue done. A later-work job runs only when the urgent queue is empty,
so every urgent job submitted before it is done too. What a later-work job needs of an urgent job submitted after
it must therefore be taken at submission, by an urgent job of its own (the mapper's snapshot of the providers).

A job that waits on another job's result must wait only on jobs that run before it: jobs of its own queue
submitted earlier, or urgent jobs submitted earlier. Anything else would wait on a job queued behind it on the
same thread.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future

__all__ = ["PriorityWorker"]


class PriorityWorker:
    """A single worker thread with an urgent and a later queue, each first in, first out.

    >>> w = PriorityWorker("example")
    >>> w.submit(sum, [1, 2, 3]).result()
    6
    >>> w.shutdown()
    """

    def __init__(self, name: str) -> None:
        self._queues: tuple[deque, deque] = (deque(), deque())  # urgent, later
        self._cv = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable, *args, urgent: bool = True) -> Future:
        """Queue ``fn(*args)``; its result (or error) comes through the returned future."""
        job: Future = Future()
        with self._cv:
            if self._closing:
                raise RuntimeError("PriorityWorker: submit after shutdown")
            self._queues[0 if urgent else 1].append((job, fn, args))
            self._cv.notify()
        return job

    def pending(self) -> tuple[int, int]:
        """Jobs waiting (not running): ``(urgent, later)``."""
        with self._cv:
            return len(self._queues[0]), len(self._queues[1])

    def _loop(self) -> None:
        while True:
            with self._cv:
                while not (self._queues[0] or self._queues[1] or self._closing):
                    self._cv.wait()
                if not (self._queues[0] or self._queues[1]):
                    return  # closing, and every job done
                job, fn, args = (self._queues[0] or self._queues[1]).popleft()
            if not job.set_running_or_notify_cancel():
                continue
            try:
                job.set_result(fn(*args))
            except BaseException as e:  # noqa: BLE001 - raised where the result is read
                job.set_exception(e)

    def shutdown(self, wait: bool = True) -> None:
        """Run every job already submitted, then stop the thread (``wait``: return once it has)."""
        with self._cv:
            self._closing = True
            self._cv.notify()
        if wait:
            self._thread.join()
