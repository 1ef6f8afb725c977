"""Imported once by the compute pool's fork server (:mod:`hmcc_worker.pool`), before it forks
any child: the imports and the warm-up every child would otherwise pay again (numba, SciPy,
OpenCV, numba's cached loops: some 2 CPU seconds a child), paid once in the server. A child
forked from it starts warm; it still runs :func:`~hmcc_worker.pool.prepare_process` (then
nearly free), so a server that could not warm up leaves each child to fail or succeed at its
own start as a spawned child would."""

from __future__ import annotations

import logging

from .pool import prepare_process

try:
    prepare_process()
except Exception:  # noqa: BLE001  (an error here would stop the server: the children say why)
    logging.getLogger("hmcc.worker").exception("the fork server could not warm the core")
