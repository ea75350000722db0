"""A kept helper thread that shares a list of independent, GIL-releasing calls (OpenCV's per-view
calls, compiled kernels) with the caller: :func:`shared_map`. The results are those of the loop, in its
order, whichever thread ran each item."""
from __future__ import annotations

import itertools
import os
import queue
import threading
from collections.abc import Callable, Sequence
from typing import TypeVar

_T = TypeVar("_T")
_R = TypeVar("_R")


class _HelperThread:
    """One kept daemon thread running :func:`shared_map`'s second share.

    A daemon, so that the command line leaves at once on Ctrl-C
    (:func:`ari_sfm.cli.process._exit_interrupted`). A task the thread has not started when its caller is done
    is dropped, not waited for.
    """

    def __init__(self) -> None:
        self.tasks: queue.SimpleQueue = queue.SimpleQueue()
        self.lock = threading.Lock()
        threading.Thread(target=self._serve, name="ari-helper", daemon=True).start()

    def _serve(self) -> None:
        while True:
            fn, state, done = self.tasks.get()
            with self.lock:
                if state["dropped"]:
                    continue
                state["started"] = True
            try:
                fn()  # (shared_map's share catches its items' exceptions)
            except BaseException:  # never ends the thread
                pass
            finally:
                done.set()

    def run(self, fn: Callable[[], None]) -> Callable[[], None]:
        """Queue ``fn``; returns the caller's wait: until ``fn`` has run, or at once if it had not started."""
        state, done = {"started": False, "dropped": False}, threading.Event()
        self.tasks.put((fn, state, done))

        def wait() -> None:
            with self.lock:
                if not state["started"]:
                    state["dropped"] = True
                    return
            done.wait()

        return wait


_helper: _HelperThread | None = None
_helper_lock = threading.Lock()


def helper_thread() -> _HelperThread:
    """The process's helper (started on first use; a forked child starts its own)."""
    global _helper
    with _helper_lock:
        if _helper is None:
            _helper = _HelperThread()
        return _helper


def _forget_helper() -> None:
    global _helper, _helper_lock
    _helper, _helper_lock = None, threading.Lock()  # (held by another thread at the fork: never released)


os.register_at_fork(after_in_child=_forget_helper)


def shared_map(fn: Callable[[_T], _R], items: Sequence[_T], threads: int = 1, min_items: int = 4) -> list[_R]:
    """``[fn(x) for x in items]``, shared with a second thread.

    For independent calls that release the GIL (OpenCV's inside
    :func:`~ari_sfm.init.opencv_threads.one_cv2_thread`, compiled kernels): each call runs as it would alone
    and the results are those of the loop, in its order. Each thread takes the next item not yet taken; a
    helper the machine does not schedule in time leaves its share to the caller.

    Args:
        fn: the call for one item.
        items: the items.
        threads: shared only with 2 or more (1: the plain loop).
        min_items: shared only with at least this many items.

    Returns:
        ``fn`` of each item, in the items' order.

    Raises:
        BaseException: the first failing item's exception in the items' order, after every item has run.
    """
    if threads < 2 or len(items) < min_items:
        return [fn(x) for x in items]
    taken = itertools.count()  # next() is atomic under the GIL
    results: list = [None] * len(items)
    failed: dict[int, BaseException] = {}

    def run() -> None:
        for i in iter(taken.__next__, None):
            if i >= len(items):
                return
            try:
                results[i] = fn(items[i])
            except BaseException as exc:  # raised in the caller, in order, after every item
                failed[i] = exc

    wait = helper_thread().run(run)
    try:
        run()
    finally:
        wait()
    if failed:
        raise failed[min(failed)]
    return results
