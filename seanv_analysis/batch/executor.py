"""Map a function over per-run tasks: serially, on local processes, or on a
dask.distributed cluster, with the same results whichever ran them.

Tasks get small picklable arguments (run folder paths, option dicts), never
DataFrames. A failing task never aborts the others: its error is collected
(one line) in :class:`TaskResult` and the rest go on. Results come back in
the order of the inputs, whatever order the workers finished in
(completion is followed with ``as_completed``, which also drives the
progress bar).

Executors
---------
``serial``
    in this process (``workers=1``), simplest to debug;
``process``
    :class:`concurrent.futures.ProcessPoolExecutor` with ``workers`` local
    processes (default: the CPU count);
``dask``
    a ``dask.distributed.Client``: one passed in (``client=``) or connected
    to ``scheduler='tcp://host:port'``. The cluster is never closed here:
    only the client connection this module opened is.
"""
from __future__ import annotations

import multiprocessing as mp
import os
import re
import sys
import threading
import time
import traceback
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from ..errors import ConfigError, SeanvError

__all__ = ["TaskResult", "Executor", "make_executor", "one_line_error"]


@dataclass
class TaskResult:
    """Outcome of one task: its input ``item``, the ``value`` it returned, or
    ``error`` (one line) when it raised."""

    item: Any
    value: Any = None
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


def one_line_error(exc: BaseException) -> str:
    """One-line message of an exception (type name added when it is not one of ours)."""
    text = " ".join(str(exc).split())
    if isinstance(exc, SeanvError):
        return text
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class _SingleThreadBLAS:
    """Run a task with one BLAS thread, as dask workers do (they set
    OMP_NUM_THREADS=1): multi-threaded BLAS sums in another order, so results
    would differ in the last bits between executors (threadpoolctl)."""

    def __enter__(self) -> "_SingleThreadBLAS":
        from threadpoolctl import threadpool_limits

        self._limits = threadpool_limits(limits=1, user_api="blas")
        return self

    def __exit__(self, *exc: Any) -> None:
        self._limits.restore_original_limits()


def _call(func: Callable, item: Any, kwargs: dict[str, Any], limit_blas: bool = True
          ) -> tuple[bool, Any]:
    """Run one task; exceptions become (False, one-line message) so that they
    cross process boundaries as plain strings. ``limit_blas``: one BLAS
    thread for this call (False where the caller already set it once: a
    threadpoolctl round costs ~2 ms, as much as a small task)."""
    try:
        if limit_blas:
            with _SingleThreadBLAS():
                return True, func(item, **kwargs)
        return True, func(item, **kwargs)
    except SeanvError as exc:
        return False, one_line_error(exc)
    except Exception as exc:  # a bug in a stage must not abort the batch
        tb = traceback.extract_tb(exc.__traceback__)
        where = f" (at {os.path.basename(tb[-1].filename)}:{tb[-1].lineno})" if tb else ""
        return False, one_line_error(exc) + where


#: most tasks a process-pool worker is handed at once (:func:`_chunks`)
CHUNK_MAX = 16


def _chunks(n: int, workers: int) -> list[range]:
    """Indices 0..n-1 in consecutive chunks, one process-pool task each.

    A task costs the pool ~0.5 ms of the parent's time (future, queues,
    pickling), as much as summarising a short run: a long list of small
    tasks goes in chunks of up to ``CHUNK_MAX``, about 8 per worker or more,
    so the workers still share the work evenly; up to 16 items per worker
    (a few runs' closed-loop re-runs, figures) stay one task each."""
    size = max(1, min(CHUNK_MAX, n // (8 * max(workers, 1))))
    return [range(a, min(a + size, n)) for a in range(0, n, size)]


def _call_chunk(func: Callable, items: Sequence[Any], kwargs: dict[str, Any]
                ) -> list[tuple[bool, Any]]:
    """:func:`_call` on each item in turn (in a worker that already runs
    with one BLAS thread)."""
    return [_call(func, item, kwargs, False) for item in items]


def _call_chunk_alone(func: Callable, items: Sequence[Any], kwargs: dict[str, Any]
                      ) -> tuple[bool, list[tuple[bool, Any]]]:
    """A Dask task: :func:`_call_chunk` with one BLAS thread, as ``(True,
    outcomes)`` (the shape :meth:`Executor._dask_collect` reads)."""
    with _SingleThreadBLAS():
        return True, _call_chunk(func, items, kwargs)


def _bar(total: int, desc: str, quiet: bool):
    """The bar of a batch: drawn where the package's bars are
    (:func:`seanv_analysis.log.progress`: a terminal, logging configured) and
    not ``quiet``."""
    from ..log import progress

    return progress(total=total, desc=desc, disable=quiet)


class Executor:
    """Runs batches of tasks on one back end; create with :func:`make_executor`.

    Use as a context manager: a process pool or a client it opened is shut
    down on exit (a cluster is never shut down).
    """

    kind: str = "serial"

    def __init__(self, kind: str = "serial", *, workers: int = 1, client: Any = None,
                 own_client: bool = False, asked: int | None = None):
        self.kind = kind
        self.workers = workers
        #: the workers asked for when more than the processors (capped to ``workers``)
        self.asked = asked
        self.client = client
        self._own_client = own_client
        self._pool: ProcessPoolExecutor | None = None
        self._background: ProcessPoolExecutor | None = None   # :meth:`start`'s worker
        self._feed: _OneAtATime | None = None                  # and its queue
        self._importing: threading.Thread | None = None        # :meth:`import_beside`'s
        self._threads: int | None = None                       # a Dask cluster's threads

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        self.close(wait=exc_type is None)

    def close(self, *, wait: bool = True) -> None:
        """Shut down the process pool / the client connection this executor opened.

        ``wait=False`` (on an error, Ctrl-C or SIGTERM) returns at once:
        pending tasks are cancelled and the pool's workers are killed (what
        they had finished is in the cache, written atomically; a later run
        computes the rest)."""
        if wait:      # interrupted: the thread's imports die with the process
            self._imported()
        if self._feed is not None:
            self._feed.cancel_all()
            self._feed = None
        for name in ("_pool", "_background"):
            pool = getattr(self, name)
            if pool is None:
                continue
            if wait:
                pool.shutdown(wait=True, cancel_futures=True)
            else:
                _stop_pool(pool)   # interrupted: queued runs are not waited for
            setattr(self, name, None)
        if self.client is not None and self._own_client:
            self.client.close()  # the connection only; the cluster keeps running
            self.client = None

    def _imported(self) -> None:
        """Wait for :meth:`import_beside`'s thread, if any."""
        if self._importing is not None:
            self._importing.join()

    def describe(self) -> str:
        """One line: 'serial', 'process pool (2 workers)', 'dask tcp://...'."""
        if self.kind == "serial":
            return "serial (1 process)"
        if self.kind == "process" or self.asked:
            capped = (f"; {self.asked} asked, capped at the processors this process may use"
                      if self.asked else "")
            return (f"process pool ({self.workers} workers{capped})" if self.kind == "process"
                    else f"serial (1 process{capped})")
        addr = getattr(getattr(self.client, "scheduler", None), "address", None) or "?"
        return f"dask.distributed ({addr})"

    def _process_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:
            self._pool = _new_pool(self.workers, fork=True, initializer=_worker_init)
        return self._pool

    @property
    def slots(self) -> int:
        """How many tasks run at once: the pool's workers, a Dask cluster's
        worker threads, 1 in this process (``Context.task_slots``: a data-set
        stage sends its independent parts to the executor where there are
        more than one)."""
        if self.kind == "dask":
            return self._dask_threads()
        return self.workers if self.kind == "process" else 1

    def _dask_threads(self) -> int:
        """The Dask cluster's worker threads (tasks it runs at once; 1 when
        it cannot say), asked once."""
        if self._threads is None:
            try:
                self._threads = max(1, sum(self.client.nthreads().values()))
            except Exception:   # a scheduler that does not answer: the tasks will say
                return 1
        return self._threads

    @staticmethod
    def _dask_collect(futures: list, done: Callable[[int, bool, Any], None]) -> None:
        """Hand each dask future's outcome to ``done`` as it completes."""
        from dask.distributed import as_completed as dask_as_completed

        index = {f.key: i for i, f in enumerate(futures)}
        for fut in dask_as_completed(futures):
            i = index[fut.key]
            try:
                done(i, *fut.result())
            except Exception as exc:  # worker lost, task cancelled
                done(i, False, one_line_error(exc))
            fut.release()

    def map(self, func: Callable, items: Sequence[Any], *, kwargs: dict[str, Any] | None = None,
            desc: str = "", quiet: bool = False,
            on_result: Callable[[TaskResult], None] | None = None) -> list[TaskResult]:
        """Apply ``func(item, **kwargs)`` to every item; results in input order.

        Parameters
        ----------
        func : a module-level (picklable) function
        items : small picklable inputs (paths, tuples)
        kwargs : keyword arguments common to every call (picklable)
        desc : progress bar label (the stage name)
        quiet : no progress bar
        on_result : called in this process as each task completes (any order),
            e.g. to save a resume index

        Returns
        -------
        list of TaskResult, one per item, in the order of ``items``.
        """
        kwargs = dict(kwargs or {})
        items = list(items)
        out: list[TaskResult | None] = [None] * len(items)
        if not items:
            return []
        with _bar(len(items), desc, quiet) as bar:
            def done(i: int, ok: bool, value: Any) -> None:
                res = TaskResult(items[i], value if ok else None, None if ok else str(value))
                out[i] = res
                bar.update(1)
                if on_result is not None:
                    on_result(res)

            if self.kind == "serial":
                with _SingleThreadBLAS():
                    for i, item in enumerate(items):
                        done(i, *_call(func, item, kwargs, False))
            elif self.kind == "process":
                pool = self._process_pool()  # its workers run with one BLAS thread
                futures = {pool.submit(_call_chunk, func, [items[i] for i in chunk], kwargs): chunk
                           for chunk in _chunks(len(items), self.workers)}
                for fut in as_completed(futures):
                    chunk = futures[fut]
                    try:
                        outcomes = fut.result()
                    except Exception as exc:  # worker died (killed, out of memory)
                        outcomes = [(False, one_line_error(exc))] * len(chunk)
                    for i, outcome in zip(chunk, outcomes):
                        done(i, *outcome)
            elif self.kind == "dask":
                # in chunks, as on the process pool: a Dask task costs this
                # process and the scheduler about a millisecond (the paper's
                # 242 runs read one a task: ingest 3.5-5.1 s against 1.1-1.4 s
                # on 2 local workers). pure=False: equal arguments still both run
                chunks = _chunks(len(items), self._dask_threads())
                futures = [self.client.submit(_call_chunk_alone, func,
                                              [items[i] for i in chunk], kwargs, pure=False)
                           for chunk in chunks]

                def chunk_done(k: int, ok: bool, value: Any) -> None:
                    # a chunk's outcomes, or the one error of its lost worker for each item
                    for i, outcome in zip(chunks[k], value if ok else
                                          [(False, value)] * len(chunks[k])):
                        done(i, *outcome)

                try:
                    self._dask_collect(futures, chunk_done)
                except BaseException:   # Ctrl-C, SIGTERM: best effort, the cluster stays
                    _cancel_quietly(self.client, futures)
                    raise
            else:  # pragma: no cover - guarded by make_executor
                raise ConfigError(f"executor: unknown kind {self.kind!r}")
        return [r for r in out if r is not None]

    def tasks(self, func: Callable, items: Sequence[Any], *,
              kwargs: dict[str, Any] | None = None, desc: str = "",
              quiet: bool = True) -> list[tuple[bool, Any]]:
        """:meth:`map` as a :class:`~seanv_analysis.stages.TaskMapper`:
        ``[(ok, value or one-line error)]`` in the order of ``items`` (the
        independent tasks of a data-set stage, such as its figures)."""
        return [(r.ok, r.value if r.ok else r.error)
                for r in self.map(func, items, kwargs=kwargs, desc=desc, quiet=quiet)]

    @property
    def can_start(self) -> bool:
        """Whether :meth:`start` runs tasks beside this process: a local
        process pool of two workers or more, or a Dask cluster where this
        machine has a second processor (the data-set stages run here, in
        this process, whichever back end the per-run work goes to)."""
        if self.kind == "process":
            return self.workers > 1
        return self.kind == "dask" and usable_cpus() > 1

    def start(self, func: Callable, items: Sequence[Any], *,
              kwargs: dict[str, Any] | None = None) -> "Started":
        """Submit ``func(item, **kwargs)`` for each item to a background
        worker and return at once (:class:`Started`: cancel those not begun,
        then wait for the others).

        The background worker is one process of its own at a lower CPU
        priority (nice +:data:`BACKGROUND_NICE`): it works on what the
        command's process and the pool's workers leave idle (the figures whose
        inputs exist while the analysis runs:
        :func:`seanv_analysis.stages.figures.start_ahead`) and never holds up
        a task of theirs in the pool's queue. Only where :attr:`can_start`."""
        if not self.can_start:
            raise ConfigError(f"executor: {self.describe()} starts no background task")
        feed = self._background_feed()
        return Started([feed.submit(func, item, dict(kwargs or {})) for item in items])

    def _background_feed(self) -> "_OneAtATime":
        if self._feed is None:
            self._feed = _OneAtATime(self._background_pool())
        return self._feed

    def _background_pool(self) -> ProcessPoolExecutor:
        if self._background is None:
            self._imported()         # never a fork while a thread imports
            # forked as the pool's workers are; spawned beside a Dask client
            # (its event loop's threads do not survive a fork)
            self._background = _new_pool(1, fork=self.kind == "process",
                                         initializer=_background_init)
        return self._background

    def preload(self, modules: Sequence[str]) -> None:
        """Import ``modules`` here before a forked pool's workers start, so
        that they inherit them rather than each importing them again (the
        modules the data-set stages' tasks run in and the figures' inputs,
        which this process imports anyway when it runs those stages:
        identify's costs a worker 0.7 s, the discovery result's 0.5 s).
        Nothing for the serial and Dask back ends, or once the workers run."""
        if self.kind != "process" or self._pool is not None:
            return
        import importlib

        for name in modules:
            importlib.import_module(name)

    def import_beside(self, modules: Sequence[str]) -> Callable[[], None]:
        """Import ``modules`` in this process on a thread while a process
        pool's workers run their first tasks (what this process imports when
        the data-set stages begin: scipy.optimize and pyarrow.parquet for the
        flow fit, 0.5-0.8 s it would otherwise spend after the runs are read,
        its cores busy with other work meanwhile). The pool's workers are
        forked first (a forked pool starts them all at its first task), and
        the thread is waited for before another fork (:meth:`start`'s
        background worker) and when the executor closes. Returns the wait;
        call it before the stages run. Nothing (a wait that returns at once)
        for the serial and Dask back ends, without ``modules`` or once called."""
        if self.kind != "process" or not modules or self._importing is not None:
            return _nothing
        self._process_pool().submit(_nothing)      # every worker forked now
        self._importing = threading.Thread(target=_import_all, args=(tuple(modules),),
                                           name="seanv-import-beside", daemon=True)
        self._importing.start()
        return self._importing.join

    def warm(self, func: Callable[[], Any]) -> None:
        """Start a process pool's workers now and run ``func()`` once on each
        worker, without waiting (e.g. import matplotlib and lay out a first
        figure while the main process analyses, so the figures drawn there
        later pay none of it). Nothing for the serial and Dask back ends; a
        warm-up that fails is ignored (the task that needs it pays)."""
        if self.kind != "process":
            return
        pool = self._process_pool()
        for _ in range(self.workers):
            pool.submit(func)         # not awaited: the pool keeps its own queue


def _nothing() -> None:
    """A task and a wait that do nothing (module level: sent to workers)."""


def _import_all(modules: Sequence[str]) -> None:
    """Import each of ``modules``; one that fails is left to the code that
    needs it (it raises there, with its own context)."""
    import importlib

    for name in modules:
        try:
            importlib.import_module(name)
        except Exception:   # pragma: no cover - a missing optional module
            pass


def _new_pool(workers: int, *, fork: bool, initializer: Callable[..., None]
              ) -> ProcessPoolExecutor:
    """A process pool of ``workers``, forked where ``fork`` and Linux allow
    it (else spawned); ``initializer(parent pid, kernel_watch)`` starts each
    worker. A forked pool starts every worker at the first submit, on that
    thread: the kernel's parent-death signal is safe when it is the main
    thread (it fires when the forking thread ends)."""
    fork = fork and "fork" in mp.get_all_start_methods() and sys.platform.startswith("linux")
    ctx = mp.get_context("fork" if fork else "spawn")
    kernel_watch = threading.current_thread() is threading.main_thread() and fork
    return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=initializer,
                               initargs=(os.getpid(), kernel_watch))


class _OneAtATime:
    """A one-process pool fed one task at a time: a pool hands its worker's
    queue tasks ahead of the one it runs, and those cannot be cancelled any
    more; here every task not running waits in this process, where it can."""

    def __init__(self, pool: ProcessPoolExecutor):
        self._pool = pool
        self._waiting: deque = deque()
        # re-entrant: a task that ends before its callback is added calls
        # it at once, on the thread that holds the lock
        self._lock = threading.RLock()
        self._busy = False

    def submit(self, func: Callable, item: Any, kwargs: dict[str, Any]) -> Future:
        fut: Future = Future()
        with self._lock:
            self._waiting.append((fut, func, item, kwargs))
            self._next()
        return fut

    def cancel_all(self) -> None:
        with self._lock:
            for fut, *_ in self._waiting:
                fut.cancel()
            self._waiting.clear()

    def _next(self) -> None:
        """Hand the worker the next task not cancelled (with the lock held)."""
        while not self._busy and self._waiting:
            fut, func, item, kwargs = self._waiting.popleft()
            if not fut.set_running_or_notify_cancel():
                continue        # cancelled while it waited
            self._busy = True
            try:
                inner = self._pool.submit(_call, func, item, kwargs)
            except Exception as exc:   # the pool is shut down or broken
                self._busy = False
                fut.set_exception(exc)
                continue
            inner.add_done_callback(lambda done, fut=fut: self._done(fut, done))

    def _done(self, fut: Future, inner: Future) -> None:
        try:
            fut.set_result(inner.result())
        except BaseException as exc:   # the process died, or the pool was shut down
            fut.set_exception(exc)
        with self._lock:
            self._busy = False
            self._next()


class Started:
    """Tasks :meth:`Executor.start` submitted to its background worker."""

    def __init__(self, futures: list):
        self._futures = futures

    def cancel_waiting(self) -> None:
        """Cancel the tasks that have not begun (the caller does them
        itself); the one running goes on."""
        for fut in self._futures:
            fut.cancel()

    def begun(self) -> list[bool]:
        """For each task, in order: it ran or runs (it was not cancelled)."""
        return [not fut.cancelled() for fut in self._futures]

    def results(self) -> list:
        """Wait for the tasks: ``(ok, value or one-line error)`` each, in
        order; None for a task cancelled."""
        out: list = []
        for fut in self._futures:
            if fut.cancelled():
                out.append(None)
                continue
            try:
                out.append(tuple(fut.result()))
            except Exception as exc:  # the process died
                out.append((False, one_line_error(exc)))
        return out


def _cancel_quietly(client: Any, futures: list) -> None:
    """Cancel dask futures not yet done (best effort: a lost connection is ignored)."""
    try:
        client.cancel([f for f in futures if not f.done()])
    except Exception:
        pass


def _kill_workers(pool: ProcessPoolExecutor) -> None:
    """SIGKILL the pool's worker processes (they hold no state worth saving:
    each finished result is already in the cache)."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        try:
            proc.kill()
        except (OSError, AttributeError, ValueError):
            pass


#: longest wait for the pool's manager thread once its workers are killed [s]
#: (it ends in milliseconds: killed workers make the pool "broken" at once)
MANAGER_JOIN_S = 5.0


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Stop a pool at once (Ctrl-C, SIGTERM, an error): kill its workers,
    cancel the queued tasks and wait for its manager thread to end.

    The wait matters at interpreter exit: ``shutdown(wait=False)`` leaves
    the manager thread running, and concurrent.futures' exit hook
    (``_python_exit``, run by ``threading._shutdown``) writes to the
    thread's wake-up pipe without the pool's lock, after checking that it
    is open, while the manager thread, which found the killed workers,
    closes that pipe. Under load the close falls between the check and the
    write: a traceback "OSError: [Errno 9] Bad file descriptor" (or "handle
    is closed") after the command's one-line message (CPython gh-125451:
    newer releases guard ``_ThreadWakeup`` with a lock; 3.11 does not).
    Once the manager thread has ended the pipe is closed and the exit hook
    skips it."""
    manager = getattr(pool, "_executor_manager_thread", None)
    _kill_workers(pool)
    pool.shutdown(wait=False, cancel_futures=True)
    if manager is not None and manager is not threading.current_thread():
        manager.join(MANAGER_JOIN_S)


#: how often a worker checks that its parent is alive [s]
PARENT_CHECK_S = 0.5


def _watch_parent(parent_pid: int, period_s: float = PARENT_CHECK_S) -> None:
    """Exit this worker as soon as ``parent_pid`` is no longer its parent
    (the parent was killed, even with SIGKILL, which it cannot catch):
    a worker never outlives the command that started it."""
    while True:
        if os.getppid() != parent_pid:
            os._exit(1)
        time.sleep(period_s)


def _worker_init(parent_pid: int | None = None, kernel_watch: bool = False) -> None:
    """Worker process set-up, once per process: the worker ends when its
    parent dies, through the kernel (``kernel_watch``:
    :func:`~.process_setup.die_with_parent`, Linux, a forked pool started by
    the main thread) and a watchdog thread (:func:`_watch_parent`), one BLAS thread
    (as dask workers have, so results match across executors) and one Arrow
    thread (the processes are the parallelism; nested thread pools only
    contend: measured on 2 cores, 200 runs, 1.87 s vs 2.68 s with
    multi-threaded Arrow)."""
    from threadpoolctl import threadpool_limits

    from .process_setup import die_with_parent, return_large_blocks_to_os

    if parent_pid is not None and kernel_watch:
        die_with_parent(parent_pid)
    if parent_pid is not None:
        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True,
                         name="seanv-parent-watch").start()
    # Ctrl-C reaches the whole process group: the parent handles it (and kills
    # the workers); a worker ends quietly on SIGTERM, not through the
    # parent's handler it inherited by fork
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)

    return_large_blocks_to_os()  # as the CLI process does
    threadpool_limits(limits=1, user_api="blas")
    try:
        import pyarrow as pa

        pa.set_cpu_count(1)
        pa.set_io_thread_count(1)
    except Exception:  # pragma: no cover - pyarrow always present
        pass


#: how much lower the CPU priority of :meth:`Executor.start`'s background
#: worker is (Linux ``nice``: at +10 it gets about a tenth of a core its
#: neighbours want, all of one they leave idle)
BACKGROUND_NICE = 10


def _background_init(parent_pid: int | None = None, kernel_watch: bool = False) -> None:
    """:func:`_worker_init`, then a lower CPU priority (:data:`BACKGROUND_NICE`)."""
    _worker_init(parent_pid, kernel_watch)
    try:
        os.nice(BACKGROUND_NICE)
    except (OSError, AttributeError):  # pragma: no cover - not permitted, or no nice
        pass


def make_executor(*, workers: int | None = None, scheduler: str | None = None,
                  client: Any = None) -> Executor:
    """Pick the back end.

    Parameters
    ----------
    workers : number of local processes; 1 runs serially in this process;
        None: the CPU count (serial on a single-CPU machine); more than the
        processors this process may use (at least 2) is capped to them, and
        :meth:`Executor.describe` says so
    scheduler : address of a running dask scheduler (``tcp://host:port``);
        also read from ``DASK_SCHEDULER_ADDRESS`` when neither this nor
        ``client`` is given and ``workers`` is None
    client : an existing ``dask.distributed.Client`` (never closed here)

    Raises
    ------
    ConfigError
        ``workers`` < 1, dask not installed, a scheduler address that is not
        one, or the scheduler cannot be reached.
    """
    if workers is not None and workers < 1:
        raise ConfigError(f"workers: {workers}; expected 1 or more")
    if client is not None:
        return Executor("dask", workers=workers or 0, client=client, own_client=False)
    if scheduler is None and workers is None:
        scheduler = os.environ.get("DASK_SCHEDULER_ADDRESS") or None
    if scheduler:
        _check_address(scheduler)
        try:
            from dask.distributed import Client
        except ImportError:
            raise ConfigError("scheduler: dask.distributed is not installed; "
                              "pip install 'seanv-analysis[dask]'") from None
        t0 = time.monotonic()
        try:
            c = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise ConfigError(f"scheduler: cannot connect to {scheduler} after "
                              f"{time.monotonic() - t0:.0f} s ({one_line_error(exc)}); is "
                              "`dask scheduler` running there?") from None
        except (ValueError, TypeError) as exc:   # dask's own parse of the address
            raise ConfigError(f"scheduler: {scheduler!r} is not a dask scheduler address "
                              f"({one_line_error(exc)}); expected tcp://HOST:PORT") from None
        return Executor("dask", workers=0, client=c, own_client=True)
    cpus = usable_cpus()
    n = workers if workers is not None else cpus
    limit = max(cpus, 2)   # more processes than processors only wait on each other (2: a pool)
    asked = n if n > limit else None
    n = min(n, limit)
    if n == 1:
        return Executor("serial", workers=1, asked=asked)
    return Executor("process", workers=n, asked=asked)


def usable_cpus() -> int:
    """The processors this process may run on (its affinity; else the CPU count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


_ADDRESS = re.compile(r"(?P<scheme>[a-z]+)://(?P<host>\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+)"
                      r"(?::(?P<port>\d{1,5}))?/?")


def _check_address(address: str) -> None:
    """A dask scheduler address, ``tcp://HOST:PORT`` (or tls://, ws://, wss://,
    ucx://, inproc://): refused in one line before a connection is tried."""
    m = _ADDRESS.fullmatch(address.strip()) if isinstance(address, str) else None
    schemes = ("tcp", "tls", "ws", "wss", "ucx", "inproc")
    if m is None or m["scheme"] not in schemes or \
            (m["port"] is not None and not 0 < int(m["port"]) < 65536) or \
            (m["port"] is None and m["scheme"] in ("tcp", "tls")):
        raise ConfigError(f"scheduler: {address!r} is not a dask scheduler address; expected "
                          f"SCHEME://HOST:PORT with SCHEME one of {', '.join(schemes)} and a port "
                          "1..65535 (e.g. tcp://127.0.0.1:8786)")
