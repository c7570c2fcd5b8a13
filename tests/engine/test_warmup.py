"""``spine_engine.warmup.warm_up``: the worker's main process calls it before the pool forks, so that
no pool process loads (or compiles) the engine's kernels on its first job."""

from __future__ import annotations

import json
import subprocess
import sys

KERNELS = {
    "spine_engine.rotations": ["_exp_kernel", "_log_kernel"],
    "spine_engine.fit.problem": ["_assemble_normal"],
    "spine_engine.fit.cameras": ["_project_kernel"],
    "spine_engine.fit.pose_rows": ["_tilt_kernel"],
    "spine_engine.fit.rod_rows": ["_jr_inverse_kernel", "_local_jacobian_kernel", "_normal_blocks_kernel"],
    "spine_engine.fit.uncertainty": ["_axial_rotation_rows", "_centreline_angle_rows", "weighted_gram"],
}
"""The numba kernels every ``register()`` without boundary calls from Python (the helpers they
inline, e.g. ``rod_rows._hat_entry``, get no signature of their own)."""

PROBE = """
import importlib, json, sys
kernels = json.loads(sys.argv[1])
def loaded():
    return {f"{m}.{k}": len(getattr(importlib.import_module(m), k).signatures) for m, ks in kernels.items() for k in ks}
before = loaded()
from spine_engine.warmup import warm_up
seconds = warm_up()
print(json.dumps({"before": before, "after": loaded(), "seconds": seconds}))
"""


def test_warm_up_loads_the_kernels_a_job_uses() -> None:
    """In a fresh interpreter (this one has run fits already): no kernel has a signature before,
    every one has after."""
    run = subprocess.run(
        [sys.executable, "-c", PROBE, json.dumps(KERNELS)], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 0, run.stderr[-3000:]
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert set(report["before"].values()) == {0}
    assert all(n >= 1 for n in report["after"].values()), report["after"]
    assert report["seconds"] > 0
