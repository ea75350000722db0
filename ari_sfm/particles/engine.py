"""Frames of a long experiment in partitions, on Dask or in this process.

Frames are independent: an experiment is cut into partitions (frame ranges),
each partition is one task (``client.submit``), and each result is written as
``OUT/parts/<name>.parquet`` (atomically) as soon as it arrives. A partition
whose file exists is skipped, so a killed run resumes where it stopped;
``OUT/parts/run.json`` records the settings, and partitions of a run with other
settings are refused. The same code runs on a LocalCluster (``workers``),
on an existing scheduler (``scheduler``: ``tcp://HOST:PORT``, e.g. a SLURM
cluster started with dask-jobqueue) or, with ``workers=0``, in this process.
"""
from __future__ import annotations

import logging
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.io import read_structured, write_json_atomic

log = logging.getLogger(__name__)

PARTS = "parts"
SCHEDULER_TIMEOUT_S = 20.0  # connecting to --scheduler


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
    """A frame range [first, last] and the task arguments of those frames."""

    first: int
    last: int
    args: tuple

    @property
    def name(self) -> str:
        return f"frames_{self.first:05d}-{self.last:05d}"


def split_frames(frames: Sequence[int], per_partition: int) -> list[list[int]]:
    """Consecutive chunks of ``per_partition`` frames (sorted)."""
    frames = sorted(int(f) for f in frames)
    return [frames[k:k + per_partition] for k in range(0, len(frames), per_partition)]


def check_run_settings(out: Path, settings: dict[str, Any]) -> None:
    """Record the settings of this run in OUT/parts/run.json, or refuse partitions of another run."""
    parts = out / PARTS
    record = parts / "run.json"
    if record.is_file():
        old = read_structured(record)
        if old != settings:
            diff = sorted(k for k in set(old) | set(settings) if old.get(k) != settings.get(k))
            raise AriSfmError(out, f"holds partitions of another run ({', '.join(diff)} differ): "
                                   f"choose another -o or delete {parts}")
    else:
        stale = list(parts.glob("*.parquet")) if parts.is_dir() else []
        if stale:
            raise AriSfmError(out, f"{parts} holds partitions but no run.json: delete it or choose another -o")
        write_json_atomic(record, settings)


def local_worker_environ() -> dict[str, Any]:
    """Dask's worker environment without ``MALLOC_TRIM_THRESHOLD_``: distributed sets it (65536) to hand
    memory back to the OS, which also fixes glibc's mmap threshold, so every large numpy temporary is
    mmapped and faulted in again: the matching took ~1.5x the CPU of the same code in-process."""
    import dask

    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", default={}) or {})
    environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    return environ


@contextmanager
def dask_client(workers: int, scheduler: str | None) -> Iterator[Any]:
    """A dask.distributed Client: on ``scheduler`` if given, else a LocalCluster of ``workers``
    single-threaded processes; None (run in this process) when ``workers`` is 0 and no scheduler."""
    if scheduler is None and workers == 0:
        yield None
        return
    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{SCHEDULER_TIMEOUT_S}s")
        except (OSError, TimeoutError) as exc:
            raise AriSfmError("--scheduler", f"cannot reach the Dask scheduler {scheduler} ({exc})") from None
        try:
            yield client
        finally:
            client.close()
        return
    with dask.config.set({"distributed.nanny.pre-spawn-environ": local_worker_environ()}):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


def run_partitions(task: Callable[..., dict[str, np.ndarray]], partitions: Sequence[Partition], out: Path,
                   client: Any, on_done: Callable[[Partition, bool], None] | None = None) -> list[Path]:
    """Run ``task(*partition.args)`` for every partition without a file yet; write each result
    (a mapping of equal-length columns) to OUT/parts/<name>.parquet. Returns every partition's file,
    in partition order. ``on_done(partition, skipped)`` after each one."""
    from ari_sfm.io.particles import write_parquet_atomic

    parts = out / PARTS
    parts.mkdir(parents=True, exist_ok=True)
    paths = [parts / f"{p.name}.parquet" for p in partitions]
    todo = []
    for p, path in zip(partitions, paths):
        if path.is_file():
            log.info("partition %s already written: skipped", p.name)
            if on_done:
                on_done(p, True)
        else:
            todo.append((p, path))
    if client is None:
        for p, path in todo:
            write_parquet_atomic(path, _result(lambda: task(*p.args)))
            if on_done:
                on_done(p, False)
        return paths
    from dask.distributed import as_completed

    futures = {client.submit(task, *p.args, pure=False): (p, path) for p, path in todo}
    for future in as_completed(futures):
        p, path = futures[future]
        write_parquet_atomic(path, _result(future.result))
        if on_done:
            on_done(p, False)
    return paths


def _result(get: Callable[[], Any]) -> Any:
    try:
        return get()
    except PartitionError as exc:
        raise AriSfmError(exc.path, exc.message) from None


def merge_partitions(paths: Sequence[Path]) -> Any:
    """One pyarrow table of the partitions' files, in order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    tables = [pq.read_table(p) for p in paths]
    return pa.concat_tables(tables) if tables else None
