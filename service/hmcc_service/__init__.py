"""hmcc_service: the HTTP API of hmcc-match (FastAPI), its queues, client and load test.

``create_app(settings)`` builds the app; ``hmcc serve`` runs it under uvicorn.
"""

from __future__ import annotations
