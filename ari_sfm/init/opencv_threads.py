"""OpenCV's threads in the analytic start: one for its own work (bit-identical results across
processes, :func:`one_cv2_thread`), and a kept helper thread sharing a camera's independent per-view
calls with the caller (:func:`opencv_map`)."""
from __future__ import annotations

import itertools
import os
import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TypeVar

import cv2

_cv2_lock = threading.Lock()
_cv2_depth = 0  # open one_cv2_thread() contexts (nested or in other threads)
_cv2_saved = 1  # the caller's cv2.getNumThreads() when the first one opened


@contextmanager
def one_cv2_thread() -> Iterator[None]:
    """Run OpenCV on one thread inside, restoring the caller's thread count after.

    cv2.calibrateCamera and cv2.solvePnP split work over threads, and their
    results then differ at 1e-15..1e-9 from process to process, enough to
    change how many steps the exact stage of calibrate() takes. On one thread
    the initialisation, hence calibrate(), is bit-identical across runs. The
    setting is process-wide: nested and concurrent contexts share it, and the
    last to close restores it (detection, outside any context, keeps its threads).
    Usable as a decorator: ``@one_cv2_thread()``.
    """
    global _cv2_depth, _cv2_saved
    with _cv2_lock:
        if _cv2_depth == 0:
            _cv2_saved = cv2.getNumThreads()
            if _cv2_saved != 1:
                cv2.setNumThreads(1)
        _cv2_depth += 1
    try:
        yield
    finally:
        with _cv2_lock:
            _cv2_depth -= 1
            if _cv2_depth == 0 and _cv2_saved != 1:
                cv2.setNumThreads(_cv2_saved)


_T = TypeVar("_T")
_R = TypeVar("_R")


class _HelperThread:
    """One kept daemon thread running :func:`opencv_map`'s second share (a thread's start costs
    ~0.15 ms; a ThreadPoolExecutor's threads are not daemons, and the command line leaves at once
    on Ctrl-C while a non-daemon thread lives: :func:`ari_sfm.cli_process._exit_interrupted`). A task the
    thread has not started when its caller is done is dropped, not waited for."""

    def __init__(self) -> None:
        self.tasks: queue.SimpleQueue = queue.SimpleQueue()
        self.lock = threading.Lock()
        threading.Thread(target=self._serve, name="ari-opencv", daemon=True).start()

    def _serve(self) -> None:
        while True:
            fn, state, done = self.tasks.get()
            with self.lock:
                if state["dropped"]:
                    continue
                state["started"] = True
            try:
                fn()  # (opencv_map's share catches its items' exceptions)
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


def _helper_thread() -> _HelperThread:
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


def opencv_map(fn: Callable[[_T], _R], items: Sequence[_T], threads: int = 1, min_items: int = 4) -> list[_R]:
    """``[fn(x) for x in items]``, with ``threads`` >= 2 and at least ``min_items`` items shared with
    another thread: for independent OpenCV calls (which release the GIL) inside :func:`one_cv2_thread`,
    so each call runs as it would alone and the results are those of the loop. Each thread takes the
    next item not yet taken (the second starts ~0.05 ms late; a fixed half each left the first waiting
    ~0.25 ms a call; a helper the machine does not schedule in time leaves its share to the caller).
    The first failing item in order raises, after every item has run."""
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

    wait = _helper_thread().run(run)
    try:
        run()
    finally:
        wait()
    if failed:
        raise failed[min(failed)]
    return results
