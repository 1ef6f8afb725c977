"""The container setup without a Docker engine (there is none on CI): docker-compose.yml's
``api`` and ``worker`` services run as local processes with their exact commands and
environments, and the Dockerfile and compose file are checked for what they promise (non-root
image, /healthz healthcheck, ``hmcc serve`` by default, workers without ports).

What runs locally differs from the containers only by these substitutions, and nothing else:

* ``REDIS_URL``: host ``redis`` (the compose service) -> ``127.0.0.1``, port ``6379`` -> the
  port of the private ``redis-server`` of :func:`procs.redis_server` (scheme and db kept),
  which runs with the compose Redis's persistence (``aof=True``);
* the api command: ``--host 0.0.0.0`` -> ``--host 127.0.0.1`` and ``--port 8000`` -> a free
  port, since several test runs may share the machine;
* ``hmcc`` -> the virtualenv's ``hmcc`` script, and ``python`` in healthchecks -> this
  interpreter;
* the image's healthcheck gets ``HMCC_PORT`` = that free port (in the container it is unset
  and the check uses its default, 8000).
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Mapping
from contextlib import ExitStack
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import httpx
import pytest
import yaml

from tests.support import procs

pytestmark = pytest.mark.procs

COMPOSE_FILE = procs.ROOT / "docker-compose.yml"
DOCKERFILE = procs.ROOT / "Dockerfile"
#: The port the API listens on inside its container (compose and the Dockerfile use it).
CONTAINER_PORT = "8000"
DEFAULT_CMD = ["hmcc", "serve", "--host", "0.0.0.0", "--port", CONTAINER_PORT]


# -- reading the files ---------------------------------------------------------------------


def dockerfile_final_stage(text: str) -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` of the last stage (the image that runs), continuation
    lines joined and comments dropped."""
    stages: list[list[tuple[str, str]]] = []
    logical = ""
    for line in text.splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        if stripped.endswith("\\"):
            logical += stripped[:-1] + " "
            continue
        keyword, _, args = (logical + stripped).partition(" ")
        logical = ""
        if keyword.upper() == "FROM":
            stages.append([])
        if stages:
            stages[-1].append((keyword.upper(), args.strip()))
    assert stages, "the Dockerfile has no FROM"
    return stages[-1]


def instruction(stage: list[tuple[str, str]], keyword: str) -> str:
    """The arguments of the stage's last ``keyword`` (the one that takes effect)."""
    found = [args for kw, args in stage if kw == keyword]
    assert found, f"the final Dockerfile stage has no {keyword}"
    return found[-1]


def exec_form(args: str) -> list[str]:
    """A JSON (exec form) argument list; shell form is refused (no shell-word guessing)."""
    argv = json.loads(args)
    assert isinstance(argv, list) and all(isinstance(a, str) for a in argv), args
    return argv


def healthcheck_argv(args: str) -> list[str]:
    """The command of ``HEALTHCHECK [--option=value ...] CMD [...]``."""
    _, sep, command = args.partition("CMD ")
    assert sep, f"HEALTHCHECK without an exec-form CMD: {args}"
    return exec_form(command)


@pytest.fixture(scope="module")
def image() -> list[tuple[str, str]]:
    return dockerfile_final_stage(DOCKERFILE.read_text())


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return dict(yaml.safe_load(COMPOSE_FILE.read_text()))


@pytest.fixture(scope="module")
def services(compose: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return dict(compose["services"])


# -- the substitutions (see the module docstring) --------------------------------------------


def local_redis_url(url: str, port: int) -> str:
    """``redis://redis:6379/<db>`` -> ``redis://127.0.0.1:<port>/<db>``."""
    parts = urlsplit(url)
    assert (parts.hostname, parts.port) == ("redis", 6379), f"unexpected REDIS_URL {url}"
    return urlunsplit(parts._replace(netloc=f"127.0.0.1:{port}"))


def local_env(service: Mapping[str, Any], redis_port: int, **extra: str) -> dict[str, str]:
    """The service's ``environment`` (REDIS_URL made local) over this process's environment
    minus any HMCC_*/REDIS_URL of the caller."""
    env = {key: str(value) for key, value in service["environment"].items()}
    env["REDIS_URL"] = local_redis_url(env["REDIS_URL"], redis_port)
    return procs.service_env(**env, **extra)


def local_argv(argv: list[str], options: Mapping[str, tuple[str, str]] | None = None) -> list[str]:
    """``argv`` with the program resolved to the venv and each ``--option expected`` turned
    into ``--option replacement`` (each must be there, with exactly the expected value)."""
    programs = {"hmcc": str(procs.BIN / "hmcc"), "python": sys.executable}
    assert argv and argv[0] in programs, f"unexpected program in {argv}"
    out = [programs[argv[0]], *argv[1:]]
    for option, (expected, replacement) in (options or {}).items():
        assert option in out, f"{option} missing from {argv}"
        at = out.index(option) + 1
        assert out[at] == expected, f"{option} {out[at]} in {argv}, expected {expected}"
        out[at] = replacement
    return out


def expect_check(argv: list[str], env: dict[str, str], healthy: bool, context: str = "") -> None:
    """Run a healthcheck command as Docker does (exit status 0 = healthy) and assert the
    verdict, so each check is shown to tell a working service from a missing one."""
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=30)
    assert (done.returncode == 0) == healthy, (
        f"{argv[-1]!r} exited {done.returncode}, expected {'0' if healthy else 'non-zero'}\n"
        f"{done.stderr}\n{context}"
    )


def logs(named: Mapping[str, procs.Proc]) -> str:
    """Every process's exit status (None: running) and output, for assertion messages."""
    return "\n".join(
        f"--- {name} (exit status {p.proc.poll()}) ---\n{p.log()}" for name, p in named.items()
    )


# -- static checks ---------------------------------------------------------------------------


def test_image_runs_the_api_as_non_root_with_a_healthz_check(
    image: list[tuple[str, str]],
) -> None:
    """What the image promises: ``hmcc serve`` on 8000 by default, as a non-root
    user, a /healthz healthcheck, the project without test/dev extras."""
    user = instruction(image, "USER").split(":")[0]
    assert user not in {"root", "0"}, f"the image runs as {user}"
    assert exec_form(instruction(image, "CMD")) == DEFAULT_CMD
    assert CONTAINER_PORT in instruction(image, "EXPOSE").split()
    check = healthcheck_argv(instruction(image, "HEALTHCHECK"))
    assert check[0] == "python" and "/healthz" in check[-1] and CONTAINER_PORT in check[-1]
    installs = [args for kw, args in image if kw == "RUN" and "pip install" in args]
    assert all("[" not in args for args in installs), f"extras installed: {installs}"


def test_compose_services_match_the_image(
    compose: dict[str, Any], services: dict[str, dict[str, Any]], image: list[tuple[str, str]]
) -> None:
    """The api runs the image's default command and check; workers publish nothing and come
    two by default; both wait for a healthy Redis that keeps an append-only file (fsynced
    every second) on a named volume, so accepted jobs survive its restart."""
    api, worker, redis = services["api"], services["worker"], services["redis"]
    assert api["command"] == exec_form(instruction(image, "CMD"))
    assert api["ports"] == [f"{CONTAINER_PORT}:{CONTAINER_PORT}"]
    assert "test" not in api["healthcheck"], "the api should inherit the image's /healthz check"
    assert worker["command"] == ["hmcc", "worker"]
    assert "ports" not in worker and "expose" not in worker
    assert worker["deploy"]["replicas"] == 2
    for service in (api, worker):
        assert service["depends_on"]["redis"]["condition"] == "service_healthy"
    assert redis["healthcheck"]["test"] == ["CMD", "redis-cli", "ping"]
    flags = redis["command"]
    persistence = {
        f: flags[flags.index(f) + 1]
        for f in ("--save", "--appendonly", "--appendfsync")
        if f in flags
    }
    assert persistence == {"--save": "", "--appendonly": "yes", "--appendfsync": "everysec"}, (
        f"redis persistence: {flags}"
    )
    volume, _, mount = redis["volumes"][0].partition(":")
    assert mount == "/data" and volume in compose["volumes"], redis["volumes"]


# -- the services, run ----------------------------------------------------------------------


def simulated_pair() -> bytes:
    """A POST /v1/verifications body: ``hmcc simulate`` (200 true matches plus outliers)."""
    done = subprocess.run(
        [str(procs.BIN / "hmcc"), "simulate", "--n-inliers", "200"],
        capture_output=True,
        check=True,
        timeout=60,
    )
    return done.stdout


def test_compose_services_verify_a_pair(
    services: dict[str, dict[str, Any]], image: list[tuple[str, str]]
) -> None:
    """The api and ``deploy.replicas`` workers, as compose starts them, verify a pair; the
    image's healthcheck and the workers' pass on them and fail without them."""
    api_svc, worker_svc = services["api"], services["worker"]
    replicas = int(worker_svc["deploy"]["replicas"])
    kind, *worker_test = worker_svc["healthcheck"]["test"]
    assert kind == "CMD", f"worker healthcheck should be exec form: {kind}"
    worker_check = local_argv(worker_test)
    api_check = local_argv(healthcheck_argv(instruction(image, "HEALTHCHECK")))
    pair = simulated_pair()
    port = procs.free_port()
    url = f"http://127.0.0.1:{port}"

    with procs.redis_server(aof=True) as redis, ExitStack() as stack:
        api_env = local_env(api_svc, redis.port)
        worker_env = local_env(worker_svc, redis.port)
        api_check_env = {**api_env, "HMCC_PORT": str(port)}
        expect_check(api_check, api_check_env, healthy=False, context="no API running yet")
        expect_check(worker_check, worker_env, healthy=False, context="no worker running yet")

        named: dict[str, procs.Proc] = {}

        def start(name: str, argv: list[str], env: dict[str, str]) -> None:
            named[name] = procs.Proc(argv, env, name)
            stack.callback(named[name].stop)

        start(
            "api",
            local_argv(
                api_svc["command"],
                {
                    "--host": ("0.0.0.0", "127.0.0.1"),
                    "--port": (CONTAINER_PORT, str(port)),
                },
            ),
            api_env,
        )
        for k in range(replicas):
            start(f"worker{k}", local_argv(worker_svc["command"]), worker_env)

        readiness: dict[str, Any] = {}

        def settled() -> bool:
            if any(p.proc.poll() is not None for p in named.values()):
                return True  # one exited: stop waiting, the assertion shows its log
            readiness.update(httpx.get(f"{url}/readyz", timeout=5).json())
            return readiness.get("ready") is True and readiness["workers"] == replicas

        procs.wait_until(settled, timeout=90, interval=0.25)
        assert readiness.get("workers") == replicas and all(
            p.proc.poll() is None for p in named.values()
        ), f"not ready with {replicas} workers: {readiness}\n{logs(named)}"
        expect_check(api_check, api_check_env, healthy=True, context=logs(named))
        expect_check(worker_check, worker_env, healthy=True, context=logs(named))

        response = httpx.post(
            f"{url}/v1/verifications",
            params={"wait": 30},
            content=pair,
            headers={"Content-Type": "application/json"},
            timeout=60,
        )
        body = response.json()
        assert response.status_code == 200 and body["status"] == "finished", (
            f"{response.status_code} {body}\n{logs(named)}"
        )
        assert body["result"]["inliers"], f"no inliers: {body}\n{logs(named)}"
