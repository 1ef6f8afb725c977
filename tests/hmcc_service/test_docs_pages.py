"""``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) work offline: every script, style sheet, icon
and document a page loads is this service's own URL, and each answers 200 (with an API key
set too: the documentation stays open)."""

from __future__ import annotations

import os
import re
from collections.abc import AsyncIterator

import httpx
import pytest
from fastapi import FastAPI
from pydantic import SecretStr

from hmcc_service.app import create_app
from hmcc_service.settings import Settings

pytestmark = pytest.mark.anyio

#: What a page makes the browser fetch: src=, href=, Swagger UI's ``url:`` and ReDoc's
#: ``spec-url=``.
_LOADS = re.compile(r"""(?:\bsrc|\bhref|\bspec-url)\s*=\s*["']([^"']*)["']|\burl:\s*'([^']*)'""")

#: The content type each asset must be answered with (a browser refuses a script sent as HTML).
_TYPES = {".js": "javascript", ".css": "text/css", ".png": "image/png", ".json": "json"}


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


@pytest.fixture
async def app(hermetic_env: None) -> AsyncIterator[FastAPI]:
    """The app with an API key set, whatever the environment says."""
    app = create_app(Settings(api_key=SecretStr("secret")))
    try:
        yield app
    finally:
        await app.state.queue.close()


def _client(app: FastAPI, root_path: str = "") -> httpx.AsyncClient:
    transport = httpx.ASGITransport(app=app, root_path=root_path)
    return httpx.AsyncClient(transport=transport, base_url="http://hmcc.test")


def _loaded(page: str) -> list[str]:
    return [a or b for a, b in _LOADS.findall(page)]


@pytest.mark.parametrize(("page", "expected"), [("/docs", 4), ("/redoc", 3)])
async def test_a_docs_page_loads_only_this_services_files(
    app: FastAPI, page: str, expected: int
) -> None:
    async with _client(app) as client:
        r = await client.get(page)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        urls = _loaded(r.text)
        # Swagger UI: its script, style sheet, icon and the document; ReDoc: no style sheet.
        assert len(urls) == expected, urls
        assert "/openapi.json" in urls
        for url in urls:
            assert url.startswith("/") and not url.startswith("//"), f"{page} loads {url}"
            asset = await client.get(url)
            assert asset.status_code == 200, url
            assert asset.content, url
            kind = _TYPES[os.path.splitext(url)[1]]
            assert kind in asset.headers["content-type"], (url, asset.headers["content-type"])
    assert "googleapis" not in r.text and "cdn" not in r.text.lower()


async def test_the_pages_follow_a_root_path(app: FastAPI) -> None:
    """Behind a proxy that mounts the service under a prefix, the pages name their files
    under it (the prefix is the proxy's to strip)."""
    async with _client(app, root_path="/hmcc") as behind:
        for page in ("/docs", "/redoc"):
            r = await behind.get(page)
            assert r.status_code == 200
            urls = _loaded(r.text)
            assert urls and all(url.startswith("/hmcc/") for url in urls), urls
