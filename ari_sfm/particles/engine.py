"""Frames of a long experiment in partitions, on Dask or in this process.

Frames are independent: an experiment is cut into partitions (frame ranges),
each partition is one task (``client.submit``), and each result is written as
``OUT/parts/<name>.parquet`` (atomically) as soon as it arrives. Partitions are
made as they are submitted (a bounded number in flight), so memory does not grow
with the number of frames. A partition whose file exists, made from the same
inputs (its ``inputs`` key, kept in the file: e.g. the images' sizes and times),
is skipped (one that cannot be read is made again), so a killed run resumes where
it stopped; ``OUT/parts/run.json`` records the settings, and partitions of a run
with other settings are refused.
The same code runs on a LocalCluster (``workers``), on an existing scheduler
(``scheduler``: ``tcp://HOST:PORT``, e.g. a SLURM cluster started with
dask-jobqueue) or, with ``workers=0``, in this process.

A cluster never makes a run hang: an address that does not answer as a Dask
scheduler is refused within SCHEDULER_TIMEOUT_S, a run with no worker connected
for ``worker_timeout_s`` stops with one error (a worker joining before that: it
goes on, and says so), a task whose workers keep dying stops it too.
"""
from __future__ import annotations

import functools
import logging
import math
import socket
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io import read_structured, write_json_atomic

log = logging.getLogger(__name__)

PARTS = "parts"
SCHEDULER_TIMEOUT_S = 20.0  # connecting to --scheduler, and its first answer
WORKER_TIMEOUT_S = 120.0  # a run with no Dask worker connected for this long stops
worker_timeout: ContextVar[float] = ContextVar("worker_timeout", default=WORKER_TIMEOUT_S)  # what dask_client
# waits when not told (the CLI's --worker-timeout sets it, for every command on Dask)
WATCH_INTERVAL_S = 1.0  # how often the cluster's workers are counted
WARN_AFTER_S = 5.0  # no worker for this long: said once (a LocalCluster's nanny restarts one within seconds)
IN_FLIGHT_PER_THREAD = 2  # partitions submitted ahead, per worker thread (at least MIN_IN_FLIGHT)
MIN_IN_FLIGHT = 4
INPUTS_KEY = b"ari_sfm.inputs"  # a partition file's schema metadata: the key of the inputs it was made from


class PartitionError(Exception):
    """A task's problem with one of its files (picklable across Dask; the client raises it as AriSfmError)."""

    def __init__(self, path: str | Path, message: str) -> None:
        super().__init__(str(path), message)
        self.path = str(path)
        self.message = message

    def __reduce__(self):
        return (PartitionError, (self.path, self.message))


@dataclass(frozen=True)
class Partition:
    """A frame range and its task.

    Attributes:
        first: First frame of the range.
        last: Last frame of the range (inclusive).
        args: The task's arguments for those frames.
        inputs: The key of the inputs they are read from ("" when run.json's settings say it all).
    """

    first: int
    last: int
    args: tuple
    inputs: str = ""

    @property
    def name(self) -> str:
        """The partition's file name without suffix, ``frames_<first>-<last>``."""
        return f"frames_{self.first:05d}-{self.last:05d}"


def split_frames(frames: Iterable[int], per_partition: int) -> list[list[int]]:
    """Cut frames into consecutive chunks.

    Args:
        frames: Frame numbers.
        per_partition: Frames per chunk.

    Returns:
        Chunks of ``per_partition`` frames (the last may be shorter), sorted.
    """
    frames = sorted(int(f) for f in frames)
    return [frames[k:k + per_partition] for k in range(0, len(frames), per_partition)]


def frame_ranges(first: int, last: int, per_partition: int) -> Iterator[list[int]]:
    """The frames first..last in consecutive chunks, made one at a time.

    Args:
        first: First frame.
        last: Last frame (inclusive).
        per_partition: Frames per chunk.

    Yields:
        Chunks of ``per_partition`` frames (the last may be shorter).
    """
    for start in range(first, last + 1, per_partition):
        yield list(range(start, min(start + per_partition, last + 1)))


def check_workers(workers: Any) -> int:
    """Check a count of LocalCluster processes.

    Args:
        workers: The ``--workers`` value: an integer >= 0 (0: this process).

    Returns:
        ``workers`` as an int.

    Raises:
        AriSfmError: Not a whole number >= 0.
    """
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)):
        raise AriSfmError("--workers", f"must be a whole number >= 0 (got {workers!r})")
    if workers < 0:
        raise AriSfmError("--workers", f"must be >= 0: Dask worker processes, 0 for this process (got {workers})")
    return int(workers)


def check_run_settings(out: Path, settings: dict[str, Any]) -> None:
    """Record the settings of this run in OUT/parts/run.json, or refuse partitions of another run.

    A record without partitions, left by a run that failed before making one, is replaced.

    Args:
        out: The output folder (OUT).
        settings: The run's settings (JSON-serialisable).

    Raises:
        AriSfmError: OUT holds partitions of a run with other settings, or partitions without run.json.
    """
    parts = out / PARTS
    record = parts / "run.json"
    if record.is_file():
        old = read_structured(record)
        if old != settings and not any(parts.glob("*.parquet")):  # an earlier run that made no partition (it
            write_json_atomic(record, settings)  # failed before): nothing of it to mix with this run's
        elif old != settings:
            diff = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
            raise AriSfmError(out, f"holds partitions of another run ({', '.join(diff)} differ): "
                                   f"choose another -o or delete {parts}")
    else:
        stale = list(parts.glob("*.parquet")) if parts.is_dir() else []
        if stale:
            raise AriSfmError(out, f"{parts} holds partitions but no run.json: delete it or choose another -o")
        write_json_atomic(record, settings)


def local_worker_environ() -> dict[str, Any]:
    """Dask's worker environment without ``MALLOC_TRIM_THRESHOLD_`` (which distributed sets).

    Returns:
        The environment for LocalCluster's workers (``distributed.nanny.pre-spawn-environ``).
    """
    import dask

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    return environ


def check_scheduler_answers(address: str, timeout_s: float) -> None:
    """Refuse an address that is no Dask scheduler before dask.distributed connects to it.

    A scheduler speaks first: an 8-byte frame length, then its handshake. A server that accepts the
    connection and says nothing (an HTTP server, the dashboard's port) is refused after ``timeout_s``.
    Only ``tcp://`` addresses are checked.

    Args:
        address: The scheduler's address, ``tcp://HOST:PORT``.
        timeout_s: How long to wait for the connection and for the first 8 bytes (s).

    Raises:
        AriSfmError: A malformed address, or one that cannot be reached or does not answer as a scheduler.
    """
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme != "tcp":  # tls://, ucx://: dask's own connection timeout only
            return
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise AriSfmError("--scheduler", f"not a Dask scheduler address tcp://HOST:PORT ({address!r}: {exc})") from None
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise AriSfmError("--scheduler", f"cannot reach the Dask scheduler {address} "
                                         f"({exc.strerror or exc or 'timed out'})") from None
    with sock:
        head = b""
        deadline = time.monotonic() + timeout_s
        try:
            while len(head) < 8:
                sock.settimeout(max(deadline - time.monotonic(), 1e-3))
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    break
                head += chunk
        except TimeoutError:
            raise AriSfmError("--scheduler", f"{address} accepts connections but is not a Dask scheduler: it sent "
                                             f"nothing in {timeout_s:g} s (an HTTP server, the dashboard's port?)"
                              ) from None
        except OSError as exc:
            raise AriSfmError("--scheduler", f"cannot reach the Dask scheduler {address} ({exc.strerror or exc})"
                              ) from None
    if len(head) < 8:
        raise AriSfmError("--scheduler", f"{address} closed the connection: not a Dask scheduler")
    if not any(0 < int.from_bytes(head, order) <= 1 << 24 for order in ("little", "big")):
        raise AriSfmError("--scheduler", f"{address} is not a Dask scheduler (it answered {head!r})")


class WorkerWatch:
    """Counts a client's workers every WATCH_INTERVAL_S (a daemon thread).

    With none connected for ``timeout_s`` it cancels the client's tasks, so that whatever waits on them
    (``as_completed``, ``gather``) returns, and keeps the reason in ``failure``. A worker back before then:
    it says so.
    """

    def __init__(self, client: Any, address: str, timeout_s: float) -> None:
        self.client = client
        self.address = address
        self.timeout_s = timeout_s
        self.failure: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ari-sfm-worker-watch", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop watching (waits up to 10 s for the thread)."""
        self._stop.set()
        self._thread.join(timeout=10.0)

    def _count(self) -> int | None:
        """Worker threads connected to the scheduler; None when it does not answer."""
        try:
            return int(sum(self.client.nthreads(callback_timeout=max(5.0, WATCH_INTERVAL_S)).values()))
        except Exception:  # noqa: BLE001 - a scheduler gone, a closed client: counted as no worker
            return None

    def _run(self) -> None:
        missing_since = None
        warned = False
        while not self._stop.wait(WATCH_INTERVAL_S):
            n = self._count()
            if self._stop.is_set():
                return
            now = time.monotonic()
            if n:
                if warned:
                    log.warning("a Dask worker is connected to %s again: going on", self.address)
                missing_since, warned = None, False
                continue
            missing_since = now if missing_since is None else missing_since
            waited = now - missing_since
            if not warned and waited >= min(WARN_AFTER_S, self.timeout_s / 2):
                log.warning("%s: waiting up to %g s (--worker-timeout)", self._what(n), self.timeout_s)
                warned = True
            if waited >= self.timeout_s:
                self.failure = (f"{self._what(n)} for {self.timeout_s:g} s (killed, never started, or out of "
                                "memory): start Dask workers and run the command again, or raise --worker-timeout")
                self._cancel_all()
                return

    def _what(self, n: int | None) -> str:
        return (f"no Dask worker connected to {self.address}" if n == 0 else
                f"the Dask scheduler {self.address} does not answer")

    def _cancel_all(self) -> None:
        from distributed import Future

        async def pending_keys() -> list:
            return list(self.client.futures)

        try:
            keys = self.client.sync(pending_keys, callback_timeout=10.0)
            self.client.cancel([Future(k, self.client) for k in keys], reason="no-workers", msg=self.failure)
        except Exception:  # noqa: BLE001 - a client already closed has cancelled its tasks itself
            pass


@contextmanager
def dask_client(workers: int, scheduler: str | None, worker_timeout_s: float | None = None) -> Iterator[Any]:
    """A dask.distributed Client for the block (a context manager).

    While it is open a :class:`WorkerWatch` stops the run after ``worker_timeout_s`` without a worker. A
    cluster's failures (no worker, a task that killed its workers, the scheduler gone) leave the block as
    one AriSfmError naming ``--scheduler`` or ``--workers``.

    Args:
        workers: LocalCluster single-threaded processes (0: this process).
        scheduler: An existing scheduler's address (``tcp://HOST:PORT``), used instead of ``workers``.
        worker_timeout_s: How long to wait with no worker (s); None for the ``worker_timeout`` context
            variable (WORKER_TIMEOUT_S unless the CLI set it).

    Yields:
        The client on ``scheduler`` if given, else on a LocalCluster; None (run in this process) when
        ``workers`` is 0 and there is no scheduler.

    Raises:
        AriSfmError: Bad ``workers`` or ``worker_timeout_s``, a scheduler that cannot be reached, or a
            cluster's failure inside the block.
    """
    workers = check_workers(workers)
    worker_timeout_s = worker_timeout.get() if worker_timeout_s is None else worker_timeout_s
    if not (isinstance(worker_timeout_s, (int, float)) and math.isfinite(worker_timeout_s) and worker_timeout_s > 0):
        raise AriSfmError("--worker-timeout", f"must be a number of seconds > 0 (got {worker_timeout_s!r})")
    if scheduler is None and workers == 0:
        yield None
        return
    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        if not isinstance(scheduler, str) or not scheduler.strip():
            raise AriSfmError("--scheduler", f"not a Dask scheduler address tcp://HOST:PORT ({scheduler!r})")
        check_scheduler_answers(scheduler, SCHEDULER_TIMEOUT_S)
        try:
            client = Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise AriSfmError("--scheduler", f"cannot reach the Dask scheduler {scheduler} ({exc})") from None
        except Exception as exc:  # noqa: BLE001 - e.g. tls:// without Dask's TLS settings, ucx:// without UCX
            hint = ("; tls:// needs Dask's TLS settings (distributed.comm.tls in its configuration)"
                    if scheduler.strip().lower().startswith("tls://") else "")
            raise AriSfmError("--scheduler", f"cannot connect to the Dask scheduler {scheduler} "
                                             f"({type(exc).__name__}: {_first_line(exc)}){hint}") from None
        cluster, where, address = None, "--scheduler", scheduler
    else:
        with dask.config.set({"distributed.nanny.pre-spawn-environ": local_worker_environ()}):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
        where, address = "--workers", cluster.scheduler_address
    watch = WorkerWatch(client, address, worker_timeout_s)
    failed = True
    try:
        yield client
        failed = False
    except BaseException as exc:
        error = cluster_error(exc, watch, where, address)
        if error is None:
            raise
        raise error from None
    finally:
        watch.stop()
        with _distributed_silenced(failed):  # its errors closing a client cut short: the run's one error says it
            client.close()
            if cluster is not None:
                cluster.close()


@contextmanager
def _distributed_silenced(silenced: bool) -> Iterator[None]:
    """dask.distributed's loggers quiet while a client cut short closes (it logs the cancellation of its
    reconnection to a lost scheduler as an ERROR with a traceback)."""
    if not silenced:
        yield
        return
    names = [n for n in list(logging.root.manager.loggerDict) if n == "distributed" or n.startswith("distributed.")]
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _first_line(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def cluster_error(exc: BaseException, watch: WorkerWatch, where: str, address: str) -> AriSfmError | None:
    """The one-line error of a cluster's failure.

    Args:
        exc: The exception that left the client's block.
        watch: The block's worker watch (its ``failure``, if any, is the reason).
        where: The option to name in the error, ``--scheduler`` or ``--workers``.
        address: The scheduler's address.

    Returns:
        The error, or None for any other exception (an interrupt, a file's).
    """
    from distributed import KilledWorker
    from distributed.comm.core import CommClosedError
    from distributed.utils import CancelledError

    if isinstance(exc, (KeyboardInterrupt, SystemExit, AriSfmError)):
        return None
    if not isinstance(exc, (Exception, CancelledError)):  # the CLI's SIGTERM, GeneratorExit
        return None
    if watch.failure is not None:
        return AriSfmError(where, watch.failure)
    if isinstance(exc, KilledWorker):
        return AriSfmError(where, f"a task killed every Dask worker that ran it ({exc.allowed_failures + 1} times; "
                                  f"out of memory?): run the command again with fewer frames per partition, or "
                                  f"give the workers more memory")
    if isinstance(exc, (CancelledError, CommClosedError)):
        reason = getattr(exc, "reason", None) or (str(exc).splitlines()[0] if str(exc) else "its tasks were cancelled")
        return AriSfmError(where, f"lost the Dask scheduler {address} ({reason}): run the command again")
    return None


def run_partitions(task: Callable[..., dict[str, np.ndarray]], partitions: Iterable[Partition], out: Path,
                   client: Any, on_done: Callable[[Partition, bool], None] | None = None) -> list[Path]:
    """Run a task for every partition without an up-to-date file yet, writing each result as it arrives.

    Each result (a mapping of equal-length columns) is written to OUT/parts/<name>.parquet with the
    partition's ``inputs`` key. ``partitions`` is consumed lazily: at most IN_FLIGHT_PER_THREAD per worker
    thread are submitted ahead.

    Args:
        task: Called as ``task(*partition.args)``; returns the partition's columns.
        partitions: The partitions, in order.
        out: The output folder (OUT).
        client: A dask.distributed Client, or None to run in this process.
        on_done: Called as ``on_done(partition, skipped)`` after each partition; None for nothing.

    Returns:
        Every partition's file, in partition order.

    Raises:
        AriSfmError: A task's problem with one of its files (:class:`PartitionError`).
    """
    parts = out / PARTS
    parts.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []

    def todo() -> Iterator[tuple[Partition, Path]]:
        for p in partitions:
            path = parts / f"{p.name}.parquet"
            paths.append(path)
            if _up_to_date(path, p.inputs):
                log.info("partition %s already written: skipped", p.name)
                if on_done:
                    on_done(p, True)
            else:
                yield p, path

    if client is None:
        for p, path in todo():
            _write_partition(path, _result(functools.partial(task, *p.args)), p.inputs)
            if on_done:
                on_done(p, False)
        return paths
    from dask.distributed import as_completed

    pending = todo()
    futures: dict[Any, tuple[Partition, Path]] = {}
    threads = 0

    def submit() -> list:
        """Submit partitions up to the bound of tasks in flight; the new futures."""
        nonlocal threads
        threads = _threads(client, threads)
        new = []
        while len(futures) < max(MIN_IN_FLIGHT, IN_FLIGHT_PER_THREAD * threads):
            item = next(pending, None)
            if item is None:
                break
            future = client.submit(task, *item[0].args, pure=False)
            futures[future] = item
            new.append(future)
        return new

    queue = as_completed(submit())
    while futures:
        future = next(queue)
        p, path = futures.pop(future)
        _write_partition(path, _result(future.result), p.inputs)
        future.release()
        if on_done:
            on_done(p, False)
        queue.update(submit())
    return paths


def _threads(client: Any, default: int) -> int:
    """The cluster's worker threads now (``default`` when the scheduler does not answer at once)."""
    try:
        return int(sum(client.nthreads(callback_timeout=5.0).values()))
    except Exception:  # noqa: BLE001 - the WorkerWatch deals with a scheduler gone
        return default


def _up_to_date(path: Path, inputs: str) -> bool:
    """The partition's file exists and was made from the same inputs (else it is made again)."""
    if not path.is_file():
        return False
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        metadata = pq.read_schema(path).metadata or {}
    except (pa.ArrowException, OSError):
        log.warning("partition %s cannot be read: made again", path.name)
        return False
    if metadata.get(INPUTS_KEY, b"").decode() != inputs:
        log.warning("partition %s was made from other inputs (changed images?): made again", path.name)
        return False
    try:  # every page (a file damaged past its footer reads its schema): made again, not merged
        pq.read_table(path)
    except (pa.ArrowException, OSError) as exc:
        log.warning("partition %s is damaged (%s): made again", path.name, _first_line(exc))
        return False
    return True


def _write_partition(path: Path, columns: dict[str, Any], inputs: str) -> None:
    from ari_sfm.io.particles import write_parquet_atomic

    write_parquet_atomic(path, columns, metadata={INPUTS_KEY: inputs.encode()})


def _result(get: Callable[[], Any]) -> Any:
    try:
        return get()
    except PartitionError as exc:
        raise AriSfmError(exc.path, exc.message) from None


def merge_partitions(paths: Sequence[Path], dest: Path, each: Callable[[Any], None] | None = None) -> int:
    """Write the partitions' files, in order, as one parquet table (atomically), one partition in memory at a time.

    Args:
        paths: The partitions' files, in order.
        dest: The table to write.
        each: Called with each partition's table (pyarrow); None for nothing.

    Returns:
        The number of rows written.

    Raises:
        AriSfmError: A partition's file cannot be read.
    """
    from ari_sfm.io.particles import write_tables_atomic

    def tables() -> Iterator[Any]:
        import pyarrow as pa
        import pyarrow.parquet as pq

        for path in paths:
            try:
                table = pq.read_table(path).replace_schema_metadata(None)
            except (pa.ArrowException, OSError) as exc:
                raise AriSfmError(path, f"cannot be read ({_first_line(exc)}): a damaged partition; run the command "
                                        "again: it is made again, the others are kept") from None
            if each is not None:
                each(table)
            yield table

    return write_tables_atomic(dest, tables())
