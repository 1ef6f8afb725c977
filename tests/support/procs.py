"""Real processes for integration tests: a redis-server of our own on a free port (so a test
can kill and restart it), ``hmcc serve`` and ``hmcc worker`` as subprocesses."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(predicate, timeout: float = 20.0, interval: float = 0.05) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if predicate():
                return True
        except Exception:
            pass
        time.sleep(interval)
    return False


class RedisServer:
    """``redis-server`` on a free port; ``stop()`` (SIGKILL) and ``start()`` for fault tests.

    No persistence by default. With ``aof``, an append-only file fsynced every second (as
    docker-compose.yml runs it) in ``dir``, which a restart keeps: a server killed and started
    again comes back with what it had written up to about a second before."""

    def __init__(self, *, aof: bool = False) -> None:
        if shutil.which("redis-server") is None:
            raise RuntimeError("redis-server is not installed; the service tests need it")
        self.aof = aof
        self.port = free_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.dir = tempfile.mkdtemp(prefix="hmcc-redis-")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        aof = ["--appendonly", "yes", "--appendfsync", "everysec"] if self.aof else []
        self.proc = subprocess.Popen(
            [
                "redis-server",
                "--port",
                str(self.port),
                "--bind",
                "127.0.0.1",
                "--save",
                "",
                *(aof or ["--appendonly", "no"]),
                "--dir",
                self.dir,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        import redis

        client = redis.Redis.from_url(self.url)
        # An AOF is replayed before the server answers (PING says LOADING until then).
        if not wait_until(lambda: client.ping(), 30):
            raise RuntimeError("redis-server did not start")
        client.close()

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            self.proc = None


@contextmanager
def redis_server(*, aof: bool = False) -> Iterator[RedisServer]:
    server = RedisServer(aof=aof)
    server.start()
    try:
        yield server
    finally:
        server.stop()
        shutil.rmtree(server.dir, ignore_errors=True)


class Proc:
    """A subprocess whose output goes to a file (read it with ``log()`` when a test fails)."""

    def __init__(self, args: list[str], env: dict[str, str], name: str) -> None:
        self.log_path = Path(tempfile.mkstemp(prefix=f"hmcc-{name}-", suffix=".log")[1])
        self._log = self.log_path.open("wb")
        self.proc = subprocess.Popen(
            args,
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            start_new_session=True,
        )

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def send_signal(self, sig: int) -> None:
        """Signal the process alone, not its children (as ``docker stop`` signals PID 1)."""
        self.proc.send_signal(sig)

    def kill(self, sig: int = signal.SIGKILL) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, sig)
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()
        self._log.close()


def service_env(**settings: str) -> dict[str, str]:
    """The current environment minus any HMCC_*/REDIS_URL, plus ``settings``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HMCC_") and k != "REDIS_URL"}
    env.update(settings)
    return env


def start_api(env: dict[str, str], port: int | None = None) -> tuple[Proc, str]:
    port = port or free_port()
    proc = Proc([str(BIN / "hmcc"), "serve", "--port", str(port)], env, "api")
    url = f"http://127.0.0.1:{port}"
    if not wait_until(lambda: httpx.get(f"{url}/healthz").status_code == 200, 30):
        proc.stop()
        raise RuntimeError(f"hmcc serve did not start:\n{proc.log()}")
    return proc, url


def start_worker(env: dict[str, str], name: str = "worker") -> Proc:
    return Proc([str(BIN / "hmcc"), "worker", "--name", f"{name}-{free_port()}"], env, name)


def wait_for_workers(url: str, n: int, timeout: float = 30.0) -> None:
    """Until the service at ``url`` counts ``n`` live workers (``/readyz``); RuntimeError after
    ``timeout`` s."""

    def ready() -> bool:
        doc = httpx.get(f"{url}/readyz", timeout=5, trust_env=False).json()
        return bool(doc.get("workers") == n)

    if not wait_until(ready, timeout):
        raise RuntimeError(f"{n} worker(s) did not register with the service")


@contextmanager
def running(*procs: Proc) -> Iterator[None]:
    try:
        yield
    finally:
        for p in procs:
            p.stop()


def compute_children(pid: int) -> set[int]:
    """The pids of the compute children of process ``pid`` (``hmcc serve`` or ``hmcc worker``):
    its children started by multiprocessing's spawn, not its resource tracker."""
    found = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid and b"spawn_main" in cmdline:
            found.add(int(entry.name))
    return found
