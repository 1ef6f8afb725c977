"""Where the real UAV fixtures live: ``$HMCC_SHARED`` or the ``shared/`` beside the checkout.

CI clones the repository with ``shared/`` beside it; a missing directory fails loudly rather
than skipping, so a green run always means the real data was exercised.
"""

from __future__ import annotations

import os
from pathlib import Path

SHARED = Path(os.environ.get("HMCC_SHARED", Path(__file__).resolve().parents[3] / "shared"))
BRIGHTON = SHARED / "fixtures" / "brighton-beach"

if not BRIGHTON.is_dir():
    raise RuntimeError(f"fixtures not found at {BRIGHTON}; set HMCC_SHARED to the shared/ folder")
