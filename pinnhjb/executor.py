"""Independent runs (case x seed x n) of a sweep, in this process, in local worker processes, or on a Dask cluster.

    from pinnhjb.executor import map_runs

    results = map_runs(train_one, tasks, workers=4)                        # 4 local processes
    results = map_runs(train_one, tasks, scheduler="tcp://10.0.0.5:8786")  # a Dask distributed cluster

``train_one`` must be a module-level function (it is pickled by reference) and every task picklable; a system
built from closures is not, so a task names its system and the function builds it. Results come back in task
order, whatever order the runs finish in.

Where the runs go:

* ``workers`` None or 1, no ``scheduler``: one after the other in this process (serial).
* ``workers=N``: N local processes (``ProcessPoolExecutor``, ``spawn`` start method, so no forked torch state).
* ``scheduler``: the workers of a Dask distributed cluster (``distributed.Client(scheduler).get_executor()``),
  started for instance with ``dask scheduler`` on one machine and ``dask worker tcp://HOST:8786 --nworkers N
  --nthreads 1`` on each of the others. The cluster decides how many runs go at once, so ``workers`` and
  ``scheduler`` together are refused as ambiguous. A run that writes files writes them on its worker: give it a
  path on a filesystem every worker sees.

Each worker sets torch's intra-op thread count to ``threads`` (default 1) before a run, so N workers use N cores
rather than N times all of them. The same seed gives the same weights bit for bit in a worker and in a serial
run *only at the same thread count*: a serial run keeps this process's count unless ``threads`` is given, so
compare a parallel run against a serial one made with ``threads=1`` (or the workers' count).
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import pickle
import re
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import torch

__all__ = ["check", "executor", "map_runs", "SCHEDULER_SCHEMES"]

#: The Dask address schemes a ``scheduler`` may use (``inproc://`` only reaches a cluster in this process).
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss", "ucx", "inproc")

_HOST_PORT = re.compile(r"^(?:\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(\d{1,5})$")
_INSTALL = "pip install distributed==2026.8.0 dask==2026.8.0"


def check(workers: int | None = None, scheduler: str | None = None, threads: int | None = None) -> str:
    """Check where runs would go, before any work; returns ``"serial"``, ``"processes"`` or ``"dask"``.

    * ``workers``: local worker processes, an integer >= 1; None or 1: serial.
    * ``scheduler``: a Dask scheduler's address, ``tcp://HOST:PORT`` (or ``tls://``, ``ws://``, ``wss://``,
      ``ucx://``, ``inproc://``); refused together with ``workers``.
    * ``threads``: torch threads per run, an integer >= 1; None: 1 in a worker, this process's count serially.

    A ValueError (a TypeError for a wrong type) says what is wrong; an ImportError names the pip command when a
    scheduler is given and ``distributed`` is not installed.
    """
    for name, value in (("workers", workers), ("threads", threads)):
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypeError(f"{name} must be an integer >= 1 or None; got {value!r}")
        if value < 1:
            raise ValueError(f"{name} must be an integer >= 1; got {value}")
    if scheduler is None:
        return "serial" if workers in (None, 1) else "processes"
    if workers is not None:
        raise ValueError(
            f"give either workers={workers} (local processes) or scheduler={scheduler!r} (a Dask cluster, whose "
            "workers decide how many runs go at once: `dask worker ADDRESS --nworkers N`), not both"
        )
    if not isinstance(scheduler, str):
        raise TypeError(f"scheduler must be an address string such as 'tcp://HOST:8786'; got {scheduler!r}")
    scheme, sep, rest = scheduler.partition("://")
    if not sep:
        hint = f"; did you mean 'tcp://{scheduler}'?" if _HOST_PORT.match(scheduler) else ""
        raise ValueError(
            f"scheduler {scheduler!r} is not a Dask address: expected tcp://HOST:PORT "
            f"(schemes: {', '.join(SCHEDULER_SCHEMES)}){hint}"
        )
    if scheme not in SCHEDULER_SCHEMES:
        raise ValueError(f"scheduler {scheduler!r}: unknown scheme {scheme!r}; known: {', '.join(SCHEDULER_SCHEMES)}")
    if scheme != "inproc":
        match = _HOST_PORT.match(rest)
        if not match or not 0 < int(match.group(1)) < 65536:
            raise ValueError(
                f"scheduler {scheduler!r}: expected {scheme}://HOST:PORT with a port 1..65535 "
                "(`dask scheduler` prints its address, by default on port 8786)"
            )
    elif not rest:
        raise ValueError(f"scheduler {scheduler!r}: an inproc:// address needs its path")
    try:
        import distributed  # noqa: F401
    except ImportError as exc:
        raise ImportError(
            f"scheduler {scheduler!r} needs the Dask distributed package, which is not installed: `{_INSTALL}` "
            "(the versions of requirements.txt)"
        ) from exc
    return "dask"


def _set_threads(threads: int) -> None:
    """A worker's initializer: torch's intra-op thread count."""
    torch.set_num_threads(threads)


def _call_with_threads(threads: int, fn: Callable, args: tuple, kwargs: dict) -> Any:
    """Run ``fn(*args, **kwargs)`` on a Dask worker at ``threads`` torch threads (its processes are long-lived)."""
    torch.set_num_threads(threads)
    return fn(*args, **kwargs)


class _Serial(cf.Executor):
    """Runs each submitted call at once, in this process; its future is already done."""

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:  # handed to the caller through the future, as a pool does
            future.set_exception(exc)
        return future


class _Dask(cf.Executor):
    """A Dask client's executor whose calls run at a fixed torch thread count."""

    def __init__(self, inner: cf.Executor, threads: int):
        self.inner, self.threads = inner, threads

    def submit(self, fn, /, *args, **kwargs):
        return self.inner.submit(_call_with_threads, self.threads, fn, args, kwargs)

    def shutdown(self, wait=True, *, cancel_futures=False):
        self.inner.shutdown(wait=wait and not cancel_futures)


@contextmanager
def executor(workers: int | None = None, scheduler: str | None = None, threads: int | None = None) -> Iterator:
    """A ``concurrent.futures.Executor`` for independent runs, closed (and its workers stopped) on exit.

    * ``workers``: local worker processes (``spawn``); None or 1: serial, in this process.
    * ``scheduler``: a Dask scheduler's address, ``tcp://HOST:PORT``: run on that cluster's workers.
    * ``threads``: torch threads per run; None: 1 in a worker, this process's own count serially (restored on
      exit when given).

    Arguments are checked (:func:`check`) before anything starts.
    """
    kind = check(workers, scheduler, threads)
    if kind == "serial":
        before = torch.get_num_threads()
        if threads is not None:
            torch.set_num_threads(threads)
        try:
            yield _Serial()
        finally:
            torch.set_num_threads(before)
        return
    threads = 1 if threads is None else threads
    if kind == "processes":
        pool = cf.ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=_set_threads,
            initargs=(threads,),
        )
        try:
            yield pool
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        return
    from distributed import Client

    with Client(scheduler, set_as_default=False) as client:
        pool = _Dask(client.get_executor(pure=False), threads)  # pure=False: equal tasks are still run, each
        try:
            yield pool
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def _label(task: Any, limit: int = 120) -> str:
    text = repr(task)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def map_runs(
    fn: Callable[[Any], Any],
    tasks: Sequence,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    threads: int | None = None,
    progress: bool = True,
    desc: str = "runs",
    label: Callable[[Any], str] | None = None,
    pool: cf.Executor | None = None,
) -> list:
    """``[fn(task) for task in tasks]``, each call an independent run, in task order; serial, in local processes or
    on a Dask cluster.

    * ``fn``: a module-level function of one task (pickled by reference).
    * ``tasks``: the tasks, each picklable.
    * ``workers``: local worker processes; None or 1: serial, in this process.
    * ``scheduler``: a Dask scheduler's address, ``tcp://HOST:PORT``; refused together with ``workers``.
    * ``threads``: torch threads per run; None: 1 in a worker, this process's own count serially. Weights are
      bit-identical to a serial run's only at the same thread count.
    * ``progress``: a progress bar of finished runs.
    * ``desc``: the progress bar's label.
    * ``label``: a task's name in an error message; None: its repr.
    * ``pool``: an executor already opened by :func:`executor` (then ``workers``, ``scheduler`` and ``threads``
      must be left out).

    A run that raises stops the sweep: runs not yet started are cancelled, runs already going are waited for, and
    the failing run's own exception is raised with a note naming its task (index and label) and saying how many
    runs finished; their results are on the exception as ``exc.finished``, ``{task index: result}``. The first
    failure by task order among those that happened is the one raised.
    """
    tasks = list(tasks)
    if pool is not None:
        if (workers, scheduler, threads) != (None, None, None):
            raise ValueError("map_runs: give either pool or workers/scheduler/threads, not both")
        return _map(pool, fn, tasks, progress, desc, label or _label)
    with executor(workers, scheduler, threads) as ex:
        return _map(ex, fn, tasks, progress, desc, label or _label)


def _map(ex: cf.Executor, fn, tasks: list, progress: bool, desc: str, label) -> list:
    from tqdm.auto import tqdm

    if isinstance(ex, cf.ProcessPoolExecutor):  # a lambda or a nested function would fail in every worker
        try:
            pickle.dumps(fn)
        except (pickle.PicklingError, AttributeError, TypeError) as exc:
            raise TypeError(
                f"map_runs: {fn!r} cannot be sent to a worker process: use a module-level function"
            ) from exc

    results: dict[int, Any] = {}
    failed: dict[int, BaseException] = {}
    futures: dict[cf.Future, int] = {}
    with tqdm(total=len(tasks), desc=desc, disable=not progress, dynamic_ncols=True) as bar:
        for i, task in enumerate(tasks):
            future = ex.submit(fn, task)
            futures[future] = i
            if isinstance(ex, _Serial):  # done already: show it, and stop at the first failure as a loop would
                bar.update(1)
                if future.exception() is not None:
                    break
        for future in cf.as_completed(futures):
            i = futures[future]
            if future.cancelled():
                continue
            exc = future.exception()
            if exc is None:
                results[i] = future.result()
                if not isinstance(ex, _Serial):
                    bar.update(1)
                continue
            if not failed:  # cancel what has not started; what is running finishes (as_completed waits for it)
                for other in futures:
                    other.cancel()
            failed[i] = exc
    if not failed:
        return [results[i] for i in range(len(tasks))]
    first = min(failed)
    exc = failed[first]
    others = f"; {len(failed) - 1} other run(s) failed too" if len(failed) > 1 else ""
    note = (
        f"in run {first + 1} of {len(tasks)} ({label(tasks[first])}); {len(results)} run(s) finished and "
        f"{len(tasks) - len(results) - len(failed)} did not run{others}"
    )
    if hasattr(exc, "add_note"):  # Python >= 3.11
        exc.add_note(note)
    try:
        exc.finished = dict(sorted(results.items()))
    except AttributeError:  # an exception type that takes no attributes
        pass
    raise exc
