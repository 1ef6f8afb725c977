"""hmcc_worker: the job side of the service.

``jobs`` holds the functions a queue runs (JSON text in, JSON-ready dict out); ``rq_worker``
runs them from Redis with a warm, fork-free, allow-listed RQ worker; ``metrics`` aggregates
per-stage job durations where the API's ``/metrics`` can read them.
"""
