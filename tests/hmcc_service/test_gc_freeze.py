"""``hmcc serve``'s app leaves what its process holds once started out of the garbage
collector's work (:func:`gc.freeze`) and collects less often (:func:`gc.set_threshold`); an app
a library caller or a test makes does neither."""

from __future__ import annotations

import gc

import pytest
from fastapi.testclient import TestClient

from hmcc_service import app as app_module
from hmcc_service.settings import Settings

pytestmark = pytest.mark.procs  # the app's lifespan starts its compute children


@pytest.mark.parametrize("served", [False, True])
def test_only_the_served_app_freezes_what_the_process_holds(
    served: bool, monkeypatch: pytest.MonkeyPatch, hermetic_env: None
) -> None:
    monkeypatch.setattr(app_module, "get_settings", lambda: Settings(embedded_workers=1))
    monkeypatch.setattr(app_module, "configure_logging", lambda level: None)
    gc.unfreeze()
    thresholds = gc.get_threshold()
    try:
        app = app_module.app_from_env() if served else app_module.create_app(Settings())
        with TestClient(app) as client:
            assert client.get("/healthz").status_code == 200
            frozen = gc.get_freeze_count()
            first = gc.get_threshold()[0]
    finally:
        gc.unfreeze()
        gc.set_threshold(*thresholds)
    assert (frozen > 10_000) is served, frozen
    assert (first > thresholds[0]) is served, (first, thresholds)
