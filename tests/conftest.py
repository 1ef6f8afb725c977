"""Suite-wide set-up: compile the core once before any test starts a process of its own.

The numba loops of the core are cached on disk after their first compilation (about 40 s).
Compiling here, in the pytest process, fills that cache before the service tests start API
and worker processes, which then load it instead of all compiling at once.
"""

from __future__ import annotations

import pytest


def pytest_sessionstart(session: pytest.Session) -> None:
    from hmcc_worker.warm import warm_up

    warm_up()
