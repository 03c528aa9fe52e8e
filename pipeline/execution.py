"""The execution layer: every command that runs many simulations submits them here.

Built on Dask distributed: by default a local cluster of one single-threaded worker
process per core (``workers`` to size it), or an existing cluster (``scheduler``: the
address of a ``dask scheduler``, local or on an HPC system through dask-jobqueue). Runs
are independent tasks; a worker lost mid-run has its task rescheduled on another.
"""

from __future__ import annotations

import logging
import os
import threading
import uuid
from collections.abc import Callable, Sequence
from typing import Any

from chipstack.core.errors import InputError
from chipstack.core.keys import MAX_WORKERS
from chipstack.core.schema import printable

__all__ = ["Executor", "CONNECT_TIMEOUT_S"]

log = logging.getLogger(__name__)
CONNECT_TIMEOUT_S = 3.0  # a Dask handshake takes milliseconds on a LAN, under a second on a WAN


def _connect(address: str):
    """A client of the scheduler at ``address``, or a one-line error within the deadline.

    The connection runs in a daemon thread with a hard deadline: a service that accepts
    the connection but never speaks Dask would otherwise hang the handshake.
    """
    from distributed import Client

    outcome: dict[str, object] = {}

    def connect() -> None:
        try:
            outcome["client"] = Client(address, timeout=f"{CONNECT_TIMEOUT_S}s")
        except BaseException as exc:  # reported below, whatever the library raised
            outcome["error"] = exc

    thread = threading.Thread(target=connect, daemon=True)
    thread.start()
    thread.join(CONNECT_TIMEOUT_S + 1.0)
    if "client" in outcome:
        return outcome["client"]
    error = outcome.get("error")
    reason = (
        f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
        if error is not None
        else f"no Dask handshake within {CONNECT_TIMEOUT_S + 1.0:g} s"
    )
    raise InputError(f"--scheduler {printable(address)}: cannot reach the scheduler ({reason})")


class Executor:
    """``with Executor(workers=2) as ex: ex.run(task, args, on_result, on_error)``."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None) -> None:
        if workers is not None and not 1 <= workers <= MAX_WORKERS:
            raise InputError(f"--workers: must be between 1 and {MAX_WORKERS}, got {workers}")
        if workers is not None and scheduler is not None:
            raise InputError("--workers: not with --scheduler (the cluster has its workers)")
        self.workers = workers
        self.scheduler = scheduler
        self._client = None
        self._cluster = None

    def __enter__(self) -> Executor:
        # A scheduler is reached at once (a wrong address fails before any work); a local
        # cluster starts on the first task, so a command whose every result is cached
        # (a second diagnosis of a tabled design) never pays its two seconds.
        if self.scheduler is not None:
            self._client = _connect(self.scheduler)
        return self

    def _started(self):
        """The client, the local cluster started first if it is not yet."""
        if self._client is None:
            from distributed import Client, LocalCluster

            log.info("starting a local Dask cluster of %s workers", self.workers or "all")
            n = self.workers or os.cpu_count() or 1
            self._cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",  # any free port: never clashes with another cluster
                scheduler_kwargs={"dashboard": False},
                silence_logs=logging.CRITICAL,
            )
            self._client = Client(self._cluster)
        return self._client

    def __exit__(self, *exc: object) -> None:
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._client = self._cluster = None

    @property
    def n_workers(self) -> int:
        """Workers of the cluster (a local cluster is started to count them)."""
        return len(self._started().scheduler_info()["workers"])

    def run(
        self,
        task: Callable[..., Any],
        arguments: Sequence[tuple],
        on_result: Callable[[int, Any], None],
        on_error: Callable[[int, BaseException], None],
    ) -> None:
        """Run ``task(*arguments[k])`` for every k; report each result or error as it comes.

        Results arrive in completion order; ``on_result`` is called in this process, so it
        can write files as they arrive.
        """
        from distributed import as_completed

        client = self._started()
        futures = {
            client.submit(task, *args, pure=False, key=f"run-{k}-{uuid.uuid4().hex}"): k
            for k, args in enumerate(arguments)
        }
        for future in as_completed(futures):
            k = futures[future]
            if future.status == "error":
                on_error(k, future.exception())
            else:
                on_result(k, future.result())
            future.release()

    def map(self, function: Callable[..., Any], calls: Sequence[dict]) -> list:
        """``[function(**kwargs) for kwargs in calls]`` on the cluster, in order; the first
        task error is raised here."""
        # Run in the order given (a caller may order its calls longest first): equal
        # priorities leave the order of calls submitted together to the scheduler.
        client = self._started()
        futures = [
            client.submit(
                _call_with_kwargs,
                function,
                kwargs,
                pure=False,
                key=f"call-{k}-{uuid.uuid4().hex}",
                priority=len(calls) - k,
            )
            for k, kwargs in enumerate(calls)
        ]
        try:
            return client.gather(futures)
        finally:
            for future in futures:
                future.release()


def _call_with_kwargs(function: Callable[..., Any], kwargs: dict) -> Any:
    return function(**kwargs)
