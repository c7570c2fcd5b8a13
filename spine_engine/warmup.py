"""Load the engine's compiled kernels before the first job.

The numba kernels (``fit.rod_rows``, ``fit.problem``, ``rotations``) are compiled once into their
on-disk cache by ``make install`` and loaded from it by the first ``register()`` of a process
(about 0.4 s on this project's VM, 3–4 s on a cold cache). ``warm_up`` pays that before any job:
the worker calls it in its main process before the pool forks, so every pool process inherits
the loaded kernels.
"""

from __future__ import annotations

import time

from .levels import LEVELS
from .models import LATERAL_ORIENTATION, PA_ORIENTATION
from .projection import image_axes, project
from .reconstruction import register_model
from .synthetic import generate_spine
from .validation import validate_payload

MAGNIFICATION = 1.125
"""PA and lateral magnification of the warm-up films (any plausible value exercises the same code)."""


def warm_up() -> float:
    """Two ``register()`` calls on one synthetic spine (``synthetic.generate_spine(0)``) filmed by
    weak perspective, p = s·(e_c·r, e_r·r), s = ``MAGNIFICATION``, on a PA and a lateral view:
    without boundary (the clinic's path: cameras estimated, uncertainty, measures) and with T1 and
    L5 given exactly (the paper's path). Returns the seconds they took."""
    start = time.perf_counter()
    spine = generate_spine(0)
    views: dict[str, object] = {}
    for name, orientation in (("pa", PA_ORIENTATION), ("lateral", LATERAL_ORIENTATION)):
        e_c, e_r = image_axes(orientation)
        points = project(spine.positions, e_c, e_r, MAGNIFICATION, (200.0, 50.0))
        views[name] = {
            "units": "mm",
            "patient_orientation": list(orientation),
            "landmarks": [{"level": level, "point": p.tolist()} for level, p in zip(LEVELS, points, strict=True)],
        }
    boundary = {
        level: {"position": spine.positions[i].tolist(), "directors": spine.rotations[i].T.tolist()}
        for level, i in (("T1", 0), ("L5", len(LEVELS) - 1))
    }
    register_model(validate_payload(views))
    register_model(validate_payload({**views, "boundary": boundary}))
    return time.perf_counter() - start
