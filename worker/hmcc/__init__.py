"""hmcc: geometric verification of UAV feature matches with rough POS (HMCC-RANSAC).

The core is pure numpy/scipy/OpenCV with no I/O. Typical use::

    from hmcc import PairRequest, verify_request
    result = verify_request(PairRequest.model_validate(pair_dict))
"""

from __future__ import annotations

__version__ = "0.1.0"
