"""hmcc_schema: the JSON contract of hmcc-match and its conversion to the core's arrays.

* :mod:`~hmcc_schema.models`: pydantic models of the request bodies (the OpenAPI document's
  schemas, and the error reports);
* :func:`parse_pair` / :func:`parse_batch`: a body -> :class:`hmcc.flight.Flight`, validated
  once, keypoints and matches straight into numpy arrays; :func:`parse_pairs`: a pairs
  request (the pairs worth matching among a flight's images);
* :func:`validation_issues`: what is wrong, as ``[{field, reason}]``;
* :func:`reference_to_pair`: the ``shared/fixtures`` pair files in the public format.
"""

from __future__ import annotations

from .issues import FieldIssue, clip, validation_issues
from .models import MAX_KEYPOINTS, MAX_MATCHES, BatchRequest, PairRequest, PairsRequest
from .parse import PAIR_IMAGES, PairsQuery, parse_batch, parse_pair, parse_pairs
from .reference_pairs import is_reference_pair, reference_to_pair

__all__ = [
    "MAX_KEYPOINTS",
    "MAX_MATCHES",
    "PAIR_IMAGES",
    "BatchRequest",
    "FieldIssue",
    "PairRequest",
    "PairsQuery",
    "PairsRequest",
    "clip",
    "is_reference_pair",
    "parse_batch",
    "parse_pair",
    "parse_pairs",
    "reference_to_pair",
    "validation_issues",
]
