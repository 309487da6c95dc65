"""The distributed engine of a tolerance study: Dask, the firmware shipped once, drives in batches.

:func:`open_client` connects to a Dask scheduler (``--scheduler tcp://HOST:PORT``)
or starts a ``LocalCluster`` of single-threaded worker processes on this
machine.  The firmware a study runs travels as a :class:`FirmwarePackage`
(the generated firmware folder's files, or the HEX with its ``board.json``;
the profile; the firmware's parameter table), scattered to every worker once
(``Client.scatter(..., broadcast=True)``); a worker writes it into its own
scratch folder the first time a task needs it (:func:`prepare`), and builds the
twin's library there once (the build is cached by content,
``picdrive_hil.build``); every later task of that worker runs on it.

The client builds the twin's library before the first task (a firmware that
does not compile fails the study before any sample runs), so workers on the
same machine find it in the shared cache and build nothing.
"""
from __future__ import annotations

import atexit
import hashlib
import os
import pickle
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import PicdriveError

__all__ = ["FirmwarePackage", "open_client", "prepare", "run_task", "SCHEDULER_TIMEOUT_S"]

#: the name of the folder a package is written into, on the client and on every worker
PACKAGE_FOLDER = "firmware"

#: how long a scheduler given with --scheduler has to answer, and to show a worker, s
SCHEDULER_TIMEOUT_S = 10.0


@dataclass
class FirmwarePackage:
    """What a worker needs to run a study's drives: shipped once per worker.

    ``files``: relative path -> bytes of the firmware folder (software twin) or of the HEX
    (``firmware.hex``) and its ``board.json`` (processor twin); ``profile`` the nominal profile
    (its tolerances); ``table`` the firmware's parameter table; ``plan`` the scenario."""

    files: dict[str, bytes]
    profile: object
    table: object
    plan: dict
    processor: bool
    digest: str = field(default="")

    def __post_init__(self):
        if not self.digest:
            h = hashlib.sha256()
            for k in sorted(self.files):
                h.update(k.encode() + b"\0" + hashlib.sha256(self.files[k]).digest())
            h.update(pickle.dumps((self.profile.sha256, self.plan, self.processor)))
            self.digest = h.hexdigest()


# per worker process: package digest -> (folder, hex path or None)
_PREPARED: dict[str, tuple[Path, Path | None]] = {}


def prepare(pkg: FirmwarePackage) -> tuple[Path, Path | None]:
    """The package's files in a folder of this process (written once per process), and the HEX path
    for the processor twin."""
    got = _PREPARED.get(pkg.digest)
    if got is not None and got[0].is_dir():
        return got
    # in the Dask worker's own scratch folder (removed with the worker, however it ends), else a temporary one
    try:
        from distributed import get_worker
        base = get_worker().local_directory
    except (ImportError, ValueError):
        base = None
    top = Path(tempfile.mkdtemp(prefix=f"picdrive-robustness-{pkg.digest[:12]}-", dir=base))
    atexit.register(shutil.rmtree, top, True)
    # the same folder name as the client's: the twin's build cache keys on the include folders' names
    d = top / PACKAGE_FOLDER
    for rel, data in pkg.files.items():
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    got = (d, d / "firmware.hex" if pkg.processor else None)
    _PREPARED[pkg.digest] = got
    return got


def run_task(pkg: FirmwarePackage, indices: list[int], seeds: list[int]) -> list[dict]:
    """A batch of drives on this worker (:func:`picdrive.robustness.sample.run_sample` each), their rows."""
    from .sample import run_sample
    folder, hex_file = prepare(pkg)
    return [run_sample(pkg.profile, folder, pkg.table, pkg.plan, k, s, hex_file=hex_file)
            for k, s in zip(indices, seeds)]


def batch_size(n_samples: int, n_workers: int) -> int:
    """Drives per task: one while a study is small, up to :data:`MAX_BATCH` so that each worker still
    gets at least 8 tasks (the client's and the scheduler's work per task, about 5 to 15 ms of the
    client's CPU, is shared by the batch)."""
    return max(1, min(MAX_BATCH, n_samples // (8 * max(1, n_workers))))


#: the most drives one task runs
MAX_BATCH = 16


def _worker_env() -> None:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def open_client(scheduler: str | None, workers: int | None, *, timeout_s: float = SCHEDULER_TIMEOUT_S):
    """A ``distributed.Client``: on ``scheduler`` (``tcp://HOST:PORT``), or on a new ``LocalCluster`` of
    ``workers`` single-threaded processes (default: this machine's cores).  Returns ``(client,
    cluster or None)``; close both when done.  Raises PicdriveError when the scheduler does not
    answer or shows no worker within ``timeout_s`` seconds."""
    import logging

    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise PicdriveError("picdrive robustness runs on Dask distributed, which is not installed: "
                            "pip install 'dask[distributed]'") from None
    _worker_env()
    if scheduler is not None:
        if not scheduler.startswith(("tcp://", "tls://", "inproc://", "ws://", "wss://")) or ":" not in scheduler[6:]:
            raise PicdriveError(f"--scheduler {scheduler!r}: expected a Dask scheduler address tcp://HOST:PORT "
                                "(the one 'dask scheduler' prints, port 8786 by default)")
        try:
            client = Client(scheduler, timeout=f"{timeout_s:g}s", set_as_default=False)
        except (OSError, TimeoutError) as e:
            raise PicdriveError(f"--scheduler {scheduler}: no Dask scheduler answers there within "
                                f"{timeout_s:g} s ({type(e).__name__}); start one with 'dask scheduler' "
                                "and workers with 'dask worker ADDRESS' (docs/robustness.md), or leave "
                                "--scheduler out for a local cluster") from None
        try:
            client.wait_for_workers(1, timeout=timeout_s)
        except (OSError, TimeoutError):
            client.close()
            raise PicdriveError(f"--scheduler {scheduler}: the scheduler answers but has no worker after "
                                f"{timeout_s:g} s; start one with 'dask worker {scheduler} --nthreads 1'") \
                from None
        return client, None
    n = workers or os.cpu_count() or 1
    import signal
    import threading
    # Ctrl-C reaches the whole process group: the workers ignore it (a process started with SIGINT
    # ignored keeps it so), the client stops the study and closes them
    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        import dask
        # the workers' statistical profiler samples the running task's stack every 10 ms and the system
        # monitors poll psutil every 0.5 s: off / every 2 s (no dashboard shows them); about 1 % of each
        # worker's core (the workers take the configuration in force when they start)
        with dask.config.set({"distributed.worker.profile.enabled": False,
                              "distributed.admin.system-monitor.interval": "2s"}):
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR)
    finally:
        if main:
            signal.signal(signal.SIGINT, old)
    client = Client(cluster, set_as_default=False)
    return client, cluster
