"""Where pairs are verified: child processes a supervisor restarts, so no pair can take down
the process that accepted it.

OpenCV is native code: an input can make it segfault, and a segfault is not an exception. So the
core never runs in the API process nor in the RQ worker's own process: both hand flights to a
:class:`ComputePool` (pebble's ``ProcessPool``, spawned children that ignore SIGINT/SIGTERM so a
stopping worker can finish its job; ``hmcc flight``'s are forked from a fork server that imported
and warmed the core once, see :func:`_context`). When a child dies, pebble replaces it and fails
only the task it was running; :meth:`ComputePool.run` then runs that chunk's pairs one by one, so
the pair that killed the child is reported ``worker_crashed`` and every other pair still gets its
result. A chunk that outlives its timeout is run pair by pair the same way, each pair with the same
timeout (the child is killed, not asked to stop: native code cannot be interrupted).

A child that dies while the pool is idle breaks pebble's pool for good; :class:`ComputePool`
replaces the broken pool with a new one (see its docstring), so a child's death, busy or idle,
costs at most the pair that caused it.

The children compute in parallel without the GIL; the submitting process only moves bytes.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor, as_completed, wait
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from pebble import ProcessPool
from pebble.common import ProcessExpired
from pebble.pool.base_pool import PoolStatus

from hmcc.flight import Flight

from . import forking
from .metrics import process_cpu_s
from .outcomes import PairOutcome, crashed, timed_out, verify_flight

__all__ = [
    "CHILD_LOST",
    "FAULT_CHILD_START_FAILS",
    "ComputePool",
    "ComputePoolDead",
    "describe",
    "forkserver_cpu_s",
    "prepare_process",
    "task_pairs",
    "task_plan",
]

_T = TypeVar("_T")

#: What :meth:`ComputePool.call` raises when the child died or ran past the timeout.
CHILD_LOST = (ProcessExpired, FutureTimeout)

log = logging.getLogger("hmcc.worker")

#: What a child runs on a flight: the outcomes of its pairs, in order: one a pair
#: (:func:`~hmcc_worker.outcomes.verify_flight`), or runs of consecutive pairs of one status
#: (:func:`~hmcc_worker.outcomes.verify_flight_lines`: a run's body, its pairs' lines).
FlightFunction = Callable[[Flight], list[PairOutcome]]
#: The outcome of a pair (the flight of that one pair) whose child was lost, in the form of a
#: :data:`FlightFunction`'s (made in the process that hands the tasks out).
LostFunction = Callable[[Flight, PairOutcome], PairOutcome]


#: Fault injection for the tests of a pool that cannot be rebuilt: while the file this
#: variable names exists, a child's start fails (it exits before it takes a task), as a child
#: that cannot import or warm the core would. Unset in production.
FAULT_CHILD_START_FAILS = "HMCC_FAULT_CHILD_START_FAILS"

#: Attempts at a new pool, each warmed within :data:`_WARM_S`, before the pool is dead.
_REBUILD_ATTEMPTS = 3
_WARM_S = 120.0
#: How often the watchdog looks for a broken pool (an idle child's death breaks it).
_WATCH_S = 0.25


class ComputePoolDead(RuntimeError):
    """The pool's children cannot be started again: this process cannot verify anything."""


class _PoolBroken(Exception):
    """The pebble pool a task was handed to broke (not the task's own child death)."""


#: Whether :func:`prepare_process` ran in this process (or in the fork server it was forked
#: from: a forked child skips the warm-up's 0.1 CPU s).
_prepared = False


def prepare_process() -> None:
    """One OpenCV thread and one BLAS thread per child (the children are the parallelism), a
    warm core: run by each child at its start, and once by the fork server the children are
    forked from (:mod:`hmcc_worker.forkserver`), so that they start warm (once a process).

    BLAS: numpy, scipy and OpenCV each bring an OpenBLAS with a thread per core, and the
    core's least-squares products (a few thousand rows by 9) are large enough for OpenBLAS to
    share them out. Its threads spin while they wait for work, on the cores the other children
    need. The limit is set after the warm-up, whose imports load SciPy's OpenBLAS."""
    global _prepared
    if _prepared:
        return
    import cv2
    from threadpoolctl import threadpool_limits

    from .warm import warm_up

    cv2.setNumThreads(1)
    warm_up()
    threadpool_limits(1)
    _prepared = True


def _start_child(environ: dict[str, str] | None) -> None:
    """In each child: stopping is the parent's decision (it waits for the job, then closes the
    pool); ``environ``, the environment of the process that made the pool, if given (a forked
    child has its fork server's, as of the server's start); :func:`prepare_process`."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if environ is not None and os.environ != environ:
        os.environ.clear()
        os.environ.update(environ)
    flag = os.environ.get(FAULT_CHILD_START_FAILS)
    if flag and os.path.exists(flag):
        raise RuntimeError(f"{FAULT_CHILD_START_FAILS}: {flag} exists, this child does not start")
    prepare_process()


def _context(forked: bool) -> multiprocessing.context.BaseContext:
    """Spawned children, or (``forked``, where there is a fork server) children forked from a
    fork server that imported and warmed the core once (:mod:`hmcc_worker.forkserver`).
    Forked, a child starts warm and ends without the interpreter's teardown (``os._exit``):
    on the 2-core machine a spawned child cost some 2.2 CPU s to start and 0.4 s to end, a
    forked one 0.1 s (the server's 2.3 s once). The server is this process's child; the
    pool's children are its own, so their CPU time is the server's
    (:func:`forkserver_cpu_s`)."""
    context = forking.context() if forked else None
    return context if context is not None else multiprocessing.get_context("spawn")


def _new_pool(processes: int, forked: bool) -> ProcessPool:
    return ProcessPool(
        max_workers=processes,
        context=_context(forked),
        initializer=_start_child,
        initargs=(dict(os.environ) if forked else None,),
    )


def forkserver_cpu_s() -> float:
    """CPU seconds of this process's fork server, its own and those of its children that
    ended (the children of a pool with ``forked``, once closed); 0 when there is none."""
    pid = forking.running_pid()
    cpu = None if pid is None else process_cpu_s(pid)
    return 0.0 if cpu is None else cpu[0] + cpu[1]


# pebble's state, read here only (pebble 5): whether a pool has failed for good, and its
# children. pebble fails the whole pool ("All workers expired", status ERROR) when a child
# ends abnormally while no task is running anywhere in the pool, taking that for an
# initializer that cannot succeed; it then stops scheduling, stops replacing children and
# never recovers.


def _pool_failed(pool: ProcessPool) -> bool:
    return bool(pool._context.status == PoolStatus.ERROR)


def _pool_children(pool: ProcessPool) -> set[int]:
    for _ in range(5):  # pebble's threads change the dict as children come and go
        try:
            workers = list(pool._pool_manager.worker_manager.workers.values())
        except RuntimeError:
            continue
        return {int(w.pid) for w in workers if w.pid is not None and w.is_alive()}
    return set()


def _discard(pool: ProcessPool) -> None:
    """Stop a pool and its children (running tasks are lost; their waiters are cancelled)."""
    pool.stop()
    pool.join()


def _warm(pool: ProcessPool, processes: int, timeout_s: float) -> set[int] | None:
    """Schedule short tasks until each child of ``pool`` has run one (a task runs only on a
    warm child: the warm-up is the initializer); their pids, or None if the pool broke (its
    children die at start) or ``timeout_s`` passed first."""
    pids: set[int] = set()
    deadline = time.monotonic() + timeout_s
    try:
        while len(pids) < processes:
            if time.monotonic() > deadline:
                return None
            tasks = [pool.schedule(_pid, args=(0.05,)) for _ in range(processes)]
            while wait(tasks, timeout=_WATCH_S).not_done:
                if _pool_failed(pool) or time.monotonic() > deadline:
                    return None
            pids |= {task.result() for task in tasks}
    except (RuntimeError, BrokenProcessPool, ProcessExpired, CancelledError):
        return None
    return pids


class ComputePool:
    """``processes`` children verifying flights; ``timeout_s`` bounds each task (None: no
    bound); ``forked``: children forked from a warm fork server rather than spawned (see
    :func:`_context`: for a pool that lives as long as one flight, ``hmcc flight``; a service's
    pool starts once, and its children are this process's own, as its metrics and tests
    expect). Thread-safe: the embedded queue runs one job per thread on one pool.

    The pool heals itself: pebble replaces a child that dies running a task, but a child that
    dies idle breaks pebble's pool for good (see :func:`_pool_failed`). So a watchdog thread
    (from :meth:`start`) and every task look for a broken pool and replace it with a new one,
    warmed, under the lock; a task lost to the broken pool is run again on the new one (it
    is reported lost only if it loses its pool twice). When :data:`_REBUILD_ATTEMPTS` new
    pools in a row cannot warm their children, the pool is :attr:`dead`: every task raises
    :class:`ComputePoolDead`, and the process should stop taking work."""

    def __init__(
        self, processes: int, timeout_s: float | None = None, forked: bool = False
    ) -> None:
        self.processes = processes
        self.timeout_s = timeout_s
        self.forked = forked
        self._pending: set[Future[Any]] = set()
        self._closed = False
        self._dead = False
        self._started = False
        self._lock = threading.Lock()
        self._pool = _new_pool(processes, forked)
        self._watchdog: threading.Thread | None = None
        self._quiet = threading.Event()

    @property
    def dead(self) -> bool:
        """True once the pool could not be rebuilt (its children die at start)."""
        return self._dead

    @property
    def started(self) -> bool:
        """True once :meth:`start` or a task started the children (pebble starts them with the
        first task otherwise)."""
        return self._started

    def live_children(self) -> set[int]:
        """The pids of the children alive now (none when the pool is dead)."""
        return set() if self._dead else _pool_children(self._pool)

    def start(self, timeout_s: float = 300.0) -> set[int]:
        """Start and warm every child now rather than with the first tasks, and the watchdog;
        returns the children's pids. A task runs only on a warm child (the warm-up is the
        children's initializer), so short tasks are scheduled until each child has run one
        (or ``timeout_s``). Raises :class:`ComputePoolDead` if the children cannot start."""
        with self._lock:
            self._started = True
            pids = _warm(self._pool, self.processes, timeout_s)
            if pids is None:
                log.error("the compute pool's children did not start; starting a new pool")
                self._rebuild()
                if self._dead:
                    raise ComputePoolDead("the compute pool's children cannot start")
                pids = self.live_children()
        if self._watchdog is None:
            self._watchdog = threading.Thread(
                target=self._watch, name="hmcc-pool-watchdog", daemon=True
            )
            self._watchdog.start()
        return pids

    def prestart(self) -> Future[list[int]]:
        """Start the children now without waiting for them (:meth:`start` waits, under the
        lock), so that their start and warm-up overlap the caller's own work (``hmcc flight``
        parsing its file); the first real tasks then find them warm or nearly. Handing a child
        its first task blocks until the fork server has imported and warmed the core (about
        1 s), so that is done in a thread: a short task for each child. The future returned
        holds the children's pids once each is warm (an empty list when the pool is closed,
        dead or broken: nothing is started then, and the first task heals a broken one; an
        exception when the pool broke or closed on the way)."""
        started: Future[list[int]] = Future()

        def start() -> None:
            try:
                with self._lock:
                    if self._closed or self._dead or _pool_failed(self._pool):
                        started.set_result([])
                        return
                    self._started = True
                    tasks = [self._pool.schedule(_pid, args=(0.0,)) for _ in range(self.processes)]
                started.set_result([task.result() for task in tasks])
            except BaseException as e:  # noqa: BLE001  (the caller reads it from the future)
                started.set_exception(e)

        threading.Thread(target=start, name="hmcc-pool-prestart", daemon=True).start()
        return started

    def _watch(self) -> None:
        """Heal a pool that broke while idle, so it is whole before the next task comes."""
        while not self._quiet.wait(_WATCH_S):
            pool = self._pool
            if not self._closed and not self._dead and _pool_failed(pool):
                log.warning("a compute child died while the pool was idle; rebuilding the pool")
                self._heal(pool)

    def _heal(self, broken: ProcessPool) -> None:
        with self._lock:
            if self._pool is broken and not self._closed and not self._dead:
                self._rebuild()

    def _rebuild(self) -> None:
        """Replace the pool (the lock held): up to :data:`_REBUILD_ATTEMPTS` new pools, each
        warmed; if none warms, the pool is dead."""
        _discard(self._pool)
        for attempt in range(1, _REBUILD_ATTEMPTS + 1):
            pool = _new_pool(self.processes, self.forked)
            pids = _warm(pool, self.processes, _WARM_S)
            if pids is not None:
                self._pool = pool
                log.warning("the compute pool was rebuilt: children %s", sorted(pids))
                return
            _discard(pool)
            log.error(
                "a new compute pool's children did not start (attempt %d of %d)",
                attempt,
                _REBUILD_ATTEMPTS,
            )
            self._pool = pool
        self._dead = True
        log.critical("the compute pool cannot be rebuilt: no pair can be verified here")

    def run(
        self, flight: Flight, fn: FlightFunction = verify_flight, lost: LostFunction | None = None
    ) -> list[PairOutcome]:
        """The outcome of every pair of ``flight``, in order, whatever the children do;
        ``fn`` verifies a flight in a child (a caller's :func:`verify_flight` that also does
        its own per-pair work there; it must pickle); ``lost(pair's flight, outcome)`` makes
        the outcome of a pair whose child was lost the same form as ``fn``'s (default: as
        it is)."""
        try:
            return self.call(fn, flight)
        except CHILD_LOST as e:
            return self.after_loss(flight, e, fn, lost)

    def after_loss(
        self,
        flight: Flight,
        e: BaseException,
        fn: FlightFunction = verify_flight,
        lost: LostFunction | None = None,
    ) -> list[PairOutcome]:
        """The outcomes of ``flight`` after a run of all its pairs lost its child (``e``, one
        of :data:`CHILD_LOST`): a single pair is that loss; more are run one at a time, so a
        pair that kills its child or runs past the timeout is that pair's outcome
        (``worker_crashed``, ``timeout``) and the others finish. ``lost`` as in :meth:`run`."""

        def loss(single: Flight, e: BaseException) -> PairOutcome:
            outcome = self._lost(e)
            return outcome if lost is None else lost(single, outcome)

        if len(flight.pairs) == 1:
            return [loss(flight, e)]
        log.warning(
            "a chunk of %d pairs %s; running its pairs one by one", len(flight.pairs), describe(e)
        )
        outcomes = []
        for i in range(len(flight.pairs)):
            single = flight.subset([i])
            try:
                outcomes.extend(self.call(fn, single))
            except CHILD_LOST as e:
                log.error("pair %d of a chunk %s", i, describe(e))
                outcomes.append(loss(single, e))
        return outcomes

    def call(self, fn: Callable[..., _T], *args: Any) -> _T:
        """``fn(*args)`` in a child, within the timeout; raises one of :data:`CHILD_LOST`
        if the child dies or runs out of time (``fn`` and its arguments must pickle), and
        :class:`ComputePoolDead` if the pool cannot be rebuilt. A task whose pool broke under
        it (another child died) is run again on the rebuilt pool, once."""
        for _ in range(2):
            pool, future = self._schedule(fn, args)
            try:
                return self._result(pool, future)
            except _PoolBroken:
                log.warning("the compute pool broke under a task; rebuilding it, running it again")
                self._heal(pool)
            finally:
                with self._lock:
                    self._pending.discard(future)
        raise ProcessExpired("the compute pool broke under this task twice", code=None)

    def map_flight(
        self,
        flight: Flight,
        chunk_pairs: int | None = None,
        fn: FlightFunction = verify_flight,
    ) -> Iterator[tuple[int, PairOutcome]]:
        """Verify every pair of ``flight`` on all children (see :meth:`map_tasks`); yields
        ``(pair index, outcome)`` as they finish (not in order)."""
        for indices, outcomes in self.map_tasks(flight, chunk_pairs, fn):
            yield from zip(indices, outcomes, strict=True)

    def map_tasks(
        self,
        flight: Flight,
        chunk_pairs: int | None = None,
        fn: FlightFunction = verify_flight,
        lost: LostFunction | None = None,
    ) -> Iterator[tuple[list[int], list[PairOutcome]]]:
        """Verify every pair of ``flight`` on all children, in the tasks of :func:`task_plan`
        (``chunk_pairs`` pairs each, if given); yields each task's ``(pair indices,
        outcomes)`` as it finishes (not in order). Two chunks per child are handed to the pool
        at once: a child that ends one finds the next waiting rather than waiting for this
        process to hand it over (which competes for the cores with the children: 4-10 ms a task
        on 2 cores, 2-4 ms now); no more, so a long flight does not sit in the queue. ``fn`` and
        ``lost`` as in :meth:`run`. A task pickles ``flight.subset(indices)``: a
        :class:`~hmcc_worker.shared_flight.SharedFlight` pickles as its indices only."""
        n = len(flight.pairs)
        plan = iter(task_plan(n, self.processes, chunk_pairs))
        with ThreadPoolExecutor(2 * self.processes, thread_name_prefix="hmcc-flight") as threads:
            running: dict[Future[list[PairOutcome]], list[int]] = {}

            def more() -> None:
                for indices in plan:
                    task = threads.submit(self.run, flight.subset(indices), fn, lost)
                    running[task] = indices
                    if len(running) >= 2 * self.processes:
                        return

            more()
            while running:
                done = next(as_completed(running))
                indices = running.pop(done)
                yield indices, done.result()
                more()

    def _schedule(
        self, fn: Callable[..., _T], args: tuple[Any, ...]
    ) -> tuple[ProcessPool, Future[_T]]:
        with self._lock:  # with close(): no future escapes the cancellation
            while True:
                if self._closed:
                    raise CancelledError("the compute pool is closed")
                if self._dead:
                    raise ComputePoolDead("the compute pool cannot be rebuilt")
                pool = self._pool
                if _pool_failed(pool):
                    self._rebuild()
                    continue
                self._started = True
                try:
                    future = pool.schedule(fn, args=args, timeout=self.timeout_s)
                except RuntimeError:
                    if _pool_failed(pool):  # it broke since the look above
                        continue
                    raise
                self._pending.add(future)
                return pool, future

    def _result(self, pool: ProcessPool, future: Future[_T]) -> _T:
        """The task's result; :class:`_PoolBroken` if ``pool`` broke first (pebble then fails
        its tasks with ``BrokenProcessPool``, or leaves one a surviving child took unanswered)."""
        # future.done(), not wait()'s done set: a future cancelled while it runs (close) is
        # done but never "notified", and wait() would leave it pending for ever.
        while not future.done():
            wait([future], timeout=_WATCH_S)
            if not future.done() and _pool_failed(pool):
                future.cancel()
                raise _PoolBroken
        try:
            return future.result()
        except BrokenProcessPool as e:
            raise _PoolBroken from e

    def _lost(self, e: BaseException) -> PairOutcome:
        if isinstance(e, ProcessExpired):
            return crashed(e.exitcode)
        return timed_out(self.timeout_s or 0.0)

    def close(self, wait: bool = True) -> None:
        """Stop taking tasks; with ``wait``, let the running ones finish first, else cancel
        them (whoever waits on them gets ``CancelledError``)."""
        self._quiet.set()
        with self._lock:
            self._closed = True
            if not wait:
                for future in self._pending:
                    future.cancel()
            pool = self._pool
        if self._dead:
            return  # its last pool is discarded already
        if wait:
            pool.close()
        else:
            pool.stop()
        pool.join()


#: At most this many pairs a task: each task pickles the images its pairs name, and a flight's
#: results come back task by task (progress, the caller's own work on them).
MAX_TASK_PAIRS = 256


def task_pairs(n: int, processes: int) -> int:
    """Pairs per task for a flight of ``n`` pairs on ``processes`` children: as few tasks as
    :data:`MAX_TASK_PAIRS` allows, in rounds of one a child (:func:`task_plan`).

    A task costs its hand-off (pickling, pebble's channel, the child's wait for its next task,
    the results' way back while this process competes for the cores): on the Brighton
    database (108 pairs, 2 children) six tasks of 18 took 12 ms longer than two of 54 (median
    of 40 paired runs), though the children ended 1-25 ms apart with six. The tail that more,
    smaller tasks would shorten is short anyway when a round's tasks are dealt alike."""
    if n <= 0:
        return 1
    rounds = math.ceil(n / (MAX_TASK_PAIRS * processes))
    return max(1, -(-n // (rounds * processes)))


def task_plan(n: int, processes: int, chunk_pairs: int | None = None) -> list[list[int]]:
    """The pairs of each task of a flight of ``n`` pairs on ``processes`` children, in the
    order they are handed out: ``chunk_pairs`` consecutive pairs each if given, else rounds
    of one task a child of :func:`task_pairs` pairs, a round's pairs dealt to its tasks in
    turn, there and back, so that they cost about the same when the flight comes heaviest
    first (two halves in order, the heaviest pairs in one, took 8 ms longer on the Brighton
    database)."""
    size = chunk_pairs or task_pairs(n, processes)
    if chunk_pairs is not None or processes <= 1:
        return [list(range(s, min(s + size, n))) for s in range(0, n, size)]
    plan: list[list[int]] = []
    for start in range(0, n, size * processes):
        tasks: list[list[int]] = [[] for _ in range(processes)]
        for k, index in enumerate(range(start, min(start + size * processes, n))):
            turn, lap = k % processes, (k // processes) % 2
            tasks[turn if lap == 0 else processes - 1 - turn].append(index)
        plan += [t for t in tasks if t]
    return plan


def _pid(sleep_s: float) -> int:
    """A child's pid, after a short sleep (so that the other children take the next tasks)."""
    time.sleep(sleep_s)
    return os.getpid()


def describe(e: BaseException) -> str:
    """What happened to a child, for the logs (``e`` one of :data:`CHILD_LOST`)."""
    if isinstance(e, ProcessExpired):
        return f"killed its process (exit code {e.exitcode})"
    return "ran past its timeout"
