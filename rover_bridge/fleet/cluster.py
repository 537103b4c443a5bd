"""The fleet's parallel map on Dask: one task per log, only LogReports travel back.

By default a LocalCluster of worker processes on this machine (one thread each: a replay is pure Python,
so threads would share one core); with a scheduler address, an existing Dask cluster, used as it is (its
workers need rover-bridge installed and the logs at the same paths). The results come back in the order
of the logs, whatever order the tasks finish in, so a report does not depend on the number of workers.
Dask is an optional extra: without it `require_dask` says what to install.
"""

from __future__ import annotations

import importlib
import logging
import sys
import time
from collections.abc import Sequence
from types import TracebackType
from typing import Any

from rover_bridge.app.log_frames import log_kind
from rover_bridge.errors import ConfigError
from rover_bridge.fleet.analysis import LogReport, analyse_log
from rover_bridge.fleet.jobs import LogJob
from rover_bridge.params import Profile

# From a clone (the package is not on the index), the editable form; from elsewhere, the path to the clone.
INSTALL = "pip install -e '.[fleet]' in the clone (or pip install '/path/to/rover-bridge[fleet]')"


def require_dask() -> None:
    """ConfigError saying what to install when Dask's distributed scheduler is missing."""
    try:
        import dask  # noqa: F401
        import distributed  # noqa: F401
    except ImportError as exc:
        raise ConfigError([f"fleet runs on Dask, which is not installed ({exc}): {INSTALL} "
                           "(dask[distributed], and pyarrow for Parquet tables)"]) from exc


def analyse_job(job: LogJob, profile: Profile, use_truncated: bool) -> LogReport:
    """One task: never raises (a log that breaks something is a skipped log with the reason)."""
    from pathlib import Path

    # The estimator's warnings (slip, a clock jump) are the per-log table's business here, not the terminal's.
    logging.getLogger("rover_bridge").setLevel(logging.ERROR)
    try:
        return analyse_log(job.path, profile, job.folder, use_truncated)
    except Exception as exc:  # a damaged log can make any library raise anything: it must not stop the run
        return LogReport(job.path, job.folder, 0, log_kind(Path(job.path)), "skipped",
                         reason=f"error while reading: {type(exc).__name__}: {exc}")


def warm_up() -> None:
    """What every worker imports before its first log (part of the start-up, not of the first log's time)."""
    importlib.import_module("filterpy.kalman")  # with scipy: half a second
    from rover_bridge.app.composition import BridgeCore

    BridgeCore(Profile())


class DaskMap:
    """`with DaskMap(scheduler, workers) as m: reports = m.run(jobs, profile)` (see the module docstring)."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None, progress: bool = True) -> None:
        require_dask()
        self.scheduler = scheduler
        self.workers = workers
        self.progress = progress
        self._cluster: Any = None
        self._client: Any = None
        self.started_s = 0.0  # how long the cluster took to start (or the connection to be made)

    def __enter__(self) -> DaskMap:
        t0 = time.perf_counter()
        dist = _distributed()  # it sets up its own INFO logging: quiet unless the command runs with -v
        if logging.getLogger().getEffectiveLevel() > logging.INFO:
            logging.getLogger("distributed").setLevel(logging.ERROR)
        if self.scheduler:
            self._client = dist.Client(self.scheduler)
        else:
            self._cluster = dist.LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                         dashboard_address=":0", silence_logs=logging.ERROR)  # any free port
            self._client = dist.Client(self._cluster)
        try:
            self._client.run(warm_up)
        except Exception as exc:  # e.g. a cluster whose workers do not have rover-bridge installed
            self.__exit__(None, None, None)
            raise ConfigError([f"the Dask workers cannot run rover-bridge ({type(exc).__name__}: {exc}): install "
                               f"it on them ({INSTALL})"]) from exc
        self.started_s = time.perf_counter() - t0
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()

    def worker_cpu_s(self) -> float:
        """CPU seconds the workers' processes have used so far (what a benchmark divides by the logs)."""
        return float(sum(self._client.run(time.process_time).values()))

    @property
    def worker_count(self) -> int:
        return len(self._client.scheduler_info()["workers"]) if self._client is not None else 0

    def run(self, jobs: Sequence[LogJob], profile: Profile, use_truncated: bool = False) -> list[LogReport]:
        client = self._client
        profile_future = client.scatter(profile, broadcast=True)
        futures = client.map(analyse_job, list(jobs), profile=profile_future, use_truncated=use_truncated,
                             pure=False)  # random keys: never another client's results on a shared cluster
        index = {f.key: i for i, f in enumerate(futures)}
        out: list[LogReport | None] = [None] * len(jobs)
        t0 = time.perf_counter()
        for done, future in enumerate(_distributed().as_completed(futures), 1):
            i = index[future.key]
            try:
                out[i] = future.result()
            except Exception as exc:  # the task never ran to the end (a worker died): that log, not the run
                job = jobs[i]
                out[i] = LogReport(job.path, job.folder, 0, "", "skipped",
                                   reason=f"task failed: {type(exc).__name__}: {exc}")
            if self.progress:
                _bar(done, len(jobs), time.perf_counter() - t0)
        if self.progress and jobs and sys.stderr.isatty():
            print(file=sys.stderr)
        return [r for r in out if r is not None]


def _distributed() -> Any:
    """dask.distributed, imported by name: its API is only partly typed, and it is an optional extra."""
    return importlib.import_module("distributed")


def _bar(done: int, total: int, elapsed_s: float) -> None:
    """A bar redrawn in place on a terminal; elsewhere (a log file) a line at every tenth of the logs."""
    tty = sys.stderr.isatty()
    if not tty and done != total and done * 10 // total == (done - 1) * 10 // total:
        return
    width = 30
    filled = round(width * done / total)
    eta = elapsed_s / done * (total - done)
    print(f"{chr(13) if tty else ''}[{'#' * filled}{'.' * (width - filled)}] {done}/{total} logs, {elapsed_s:.0f} s, "
          f"about {eta:.0f} s left ", end="" if tty else "\n", file=sys.stderr, flush=True)
