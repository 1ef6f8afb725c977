"""What the image files say of their capture: the EXIF camera and time."""

from __future__ import annotations

from datetime import datetime

import pytest

from hmcc_colmap.capture import read_capture
from tests.support.shared_data import BRIGHTON, SHARED

CALITERRA = SHARED / "fixtures" / "caliterra" / "images"


def test_brighton_capture() -> None:
    """EXIF FocalLengthIn35mmFilm (no sensor size): 20 mm x 2000 px / 36 mm;
    DateTimeOriginal."""
    c = read_capture(BRIGHTON / "images" / "DJI_0018.JPG")
    assert c.camera == {"width": 2000, "height": 1125, "focal": pytest.approx(2000 * 20 / 36)}
    assert c.time == datetime(2016, 6, 23, 16, 31, 59)
    # Caliterra: FocalLength 4.5 mm over a 4000 px / 16393 px-per-inch sensor, stored 1600 px
    k = read_capture(CALITERRA / "IMG_9354.jpg")
    assert k.camera is not None and k.camera["focal"] == pytest.approx(
        4.5 * 1600 / (4000 / 16393.44262295082 * 25.4)
    )
