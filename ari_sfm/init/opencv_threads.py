"""OpenCV's threads in the analytic start: one for its own work (bit-identical results across
processes, :func:`one_cv2_thread`); a camera's independent per-view calls are shared with a helper
thread by :func:`ari_sfm.helper_thread.shared_map`."""
from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import cv2

_cv2_lock = threading.Lock()
_cv2_depth = 0  # open one_cv2_thread() contexts (nested or in other threads)
_cv2_saved = 1  # the caller's cv2.getNumThreads() when the first one opened


@contextmanager
def one_cv2_thread() -> Iterator[None]:
    """Run OpenCV on one thread inside, restoring the caller's thread count after.

    On one thread the initialisation, hence calibrate(), is bit-identical across runs. The
    setting is process-wide: nested and concurrent contexts share it, and the
    last to close restores it (detection, outside any context, keeps its threads).
    Usable as a decorator: ``@one_cv2_thread()``.

    Yields:
        Nothing; OpenCV runs on one thread until the context closes.
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
