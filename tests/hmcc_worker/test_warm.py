"""``warm_up`` compiles (or loads from the cache) every kernel a request needs, before the first
request: checked in a fresh interpreter, where nothing else has compiled them."""

from __future__ import annotations

import subprocess
import sys

import pytest

KERNELS = (
    "plus_kernels.fit_candidates",
    "plus_kernels.refine",
    "plus_kernels.motion_field",
    "plus_kernels.leave_one_out",
    "plus_kernels.ray_gate",
    "plus_kernels.posed_model",
    "projection._ground_heights",
    "projection._ground_from_heights",
    "seven_point._ransac",
    "gc_filter._vote_every_pair",
    "relative_pose._cheirality",
)

CHECK = f"""
from hmcc import gc_filter, plus_kernels, projection, relative_pose, seven_point
kernels = {{name: eval(name) for name in {KERNELS!r}}}
assert not [n for n, k in kernels.items() if k.signatures], "compiled before warm_up"
from hmcc_worker.warm import warm_up
warm_up()
missing = [n for n, k in kernels.items() if not k.signatures]
assert not missing, missing
"""


@pytest.mark.procs  # a fresh interpreter
def test_warm_up_loads_the_compiled_kernels() -> None:
    done = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
