"""hmcc_worker: the job side of the service.

* :mod:`.protocol`: every name the API and the workers share (Redis keys, job functions,
  statuses, error codes);
* :mod:`.payload`: a flight as bytes for the queue (no pickle);
* :mod:`.pool`: the supervised child processes that verify pairs (crash isolation);
* :mod:`.outcomes`: each pair's result or error, encoded once;
* :mod:`.jobs`, :mod:`.rq_worker`, :mod:`.rq_compat`: the RQ worker and its job;
* :mod:`.metrics`, :mod:`.logs`: per-stage durations and failures, JSON log lines.
"""
