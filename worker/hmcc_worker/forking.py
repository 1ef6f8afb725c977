"""The fork server a compute pool's forked children come from (Python's own,
:mod:`multiprocessing.forkserver`, one a process): its context, and starting and stopping it on
its own, before any pool.

The server imports :data:`PRELOAD` before it forks a child: the main module (where a task's
functions may live) and :mod:`hmcc_worker.forkserver`, which imports and warms the core (some
2 s on 2 cores). ``hmcc flight`` starts it first thing (:func:`start`), so that the warm-up
runs beside the command's own imports and reading of its file rather than after them; a pool
made later with ``forked`` (:class:`~hmcc_worker.pool.ComputePool`) forks from that same
server. This module imports the standard library only, so that starting the server costs the
command nothing before its own imports."""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver
import os
import signal

__all__ = ["PRELOAD", "context", "running_pid", "start", "stop"]

#: What the fork server imports before it forks a child. Python 3.11's server skips the main
#: module (it looks for a key its own preparation data names otherwise), so each child runs the
#: main module itself, with the command line of the process that made the pool: a command's
#: module code must not start anything in a child (:func:`hmcc_cli.flight_args.start_early`).
PRELOAD = ["__main__", "hmcc_worker.forkserver"]


def context() -> multiprocessing.context.BaseContext | None:
    """The fork server's context, its preload set; None where the platform has none."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return None
    forkserver = multiprocessing.get_context("forkserver")
    forkserver.set_forkserver_preload(PRELOAD)
    return forkserver


def start() -> bool:
    """Start this process's fork server now, without waiting for its warm-up (a no-op when it
    runs already); False where the platform has none."""
    if context() is None:
        return False
    multiprocessing.forkserver.ensure_running()
    return True


def running_pid() -> int | None:
    """The pid of this process's fork server, None when it has not started."""
    # the stdlib's server's state (Python 3.11 to 3.14), read only
    pid = getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None)
    return pid if isinstance(pid, int) else None


def stop() -> None:
    """Stop this process's fork server, at once, if it runs and no pool uses it (one started
    early for a flight that is then verified in this process). Python's own stop waits until
    the server has finished importing (the whole warm-up), so it is killed first: it has no
    children yet, and nothing it does is kept."""
    pid = running_pid()
    if pid is None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    # closes the server's pipe and socket and waits for it (the stdlib's own, private)
    multiprocessing.forkserver._forkserver._stop()  # type: ignore[attr-defined]
