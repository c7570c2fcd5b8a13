"""Same results, bit for bit? ``register()``'s outputs over a fixed set of payloads, written to a
file and compared with another run's (docs/performance.md: the engine's CPU cuts kept every output
float identical).

    python -m tools.engine_outputs dump before.json          # on the old code (an export first on PYTHONPATH)
    python -m tools.engine_outputs dump after.json
    python -m tools.engine_outputs compare before.json after.json [--tolerance 1e-12]

The payloads (438): the load bench's ``payload(0..29)``; the 24 VerSe dev spines of
``tests/data/verse_dev.csv`` with and without the T1/L5 boundary, PA alone and PA + lateral, 1 mm
landmark noise (seed 7), and with corners (every other level) or pedicles on the PA, with the
boundary on the PA alone, without it PA + lateral (seed 11); the same spines as ``spine bench perf``
sends them, in the paper's case and
in each clinic case (a)–(h) (``perf.clinic_payloads``: no boundary, perspective films, geometry
priors). ``compare`` walks both
results field by field (``fit.runtime_ms`` left out), prints the floats compared, the largest
relative difference and every other mismatch, and exits 1 when a non-float field differs or a float
differs by more than the tolerance (0: identical bits).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from benches.clinic_films import CASES
from benches.perf import REAL_SPINES, clinic_payloads
from benches.truth import payload_from_truth, read_verse
from spine_engine import register
from spine_engine.frames import frames_from_centreline
from tools.loadbench import payload as loadbench_payload

IGNORED = ("runtime_ms",)
"""Fields that differ from run to run whatever the code (wall-clock figures)."""


def payloads() -> Iterator[tuple[str, dict[str, Any]]]:
    """(name, payload) of the fixed set, in a fixed order."""
    for i in range(30):
        yield f"loadbench-{i}", loadbench_payload(i)
    levels = list(range(17))
    for spine_id, positions in read_verse(REAL_SPINES):
        rotations = frames_from_centreline(positions)
        for boundary in (True, False):
            for lateral in (False, True):
                rng = np.random.default_rng(7)
                yield (f"{spine_id}-boundary{int(boundary)}-lateral{int(lateral)}",
                       payload_from_truth(positions, rotations, levels, levels if lateral else None, noise_mm=1.0,
                                          rng=rng, boundary=boundary))  # fmt: skip
        yield f"{spine_id}-perf", payload_from_truth(positions, rotations, levels)
        for form, corners, pedicles in (("corners", levels[::2], None), ("pedicles", None, levels)):
            for boundary in (True, False):
                rng = np.random.default_rng(11)
                yield (f"{spine_id}-{form}-boundary{int(boundary)}",
                       payload_from_truth(positions, rotations, levels, None if boundary else levels, noise_mm=1.0,
                                          rng=rng, corner_levels=corners, pedicle_levels=pedicles,
                                          boundary=boundary))  # fmt: skip
    for case in CASES:
        for i, payload in enumerate(clinic_payloads(case)):
            yield f"clinic-{case}-{i}", payload


def dump(path: Path) -> int:
    """Write {name: result or the error's repr} of every payload to ``path`` (JSON; floats written
    by ``repr``, which round-trips every bit)."""
    results: dict[str, Any] = {}
    for name, payload in payloads():
        try:
            results[name] = register(payload)
        except Exception as exc:  # an error is an output too: it must stay the same
            results[name] = f"error: {exc!r}"
    path.write_text(json.dumps(results))
    print(f"{len(results)} payloads, {sum(isinstance(v, str) for v in results.values())} errors -> {path}")
    return 0


class Comparison:
    """The walk of two results: floats compared, the largest relative difference, other mismatches."""

    def __init__(self) -> None:
        self.floats = 0
        self.worst = (0.0, "")
        self.mismatches: list[str] = []

    def walk(self, a: Any, b: Any, path: str) -> None:
        if path.rsplit(".", 1)[-1] in IGNORED:
            return
        if isinstance(a, dict) and isinstance(b, dict):
            if set(a) != set(b):
                self.mismatches.append(f"{path}: keys {sorted(set(a) ^ set(b))}")
                return
            for key in a:
                self.walk(a[key], b[key], f"{path}.{key}")
        elif isinstance(a, list) and isinstance(b, list):
            if len(a) != len(b):
                self.mismatches.append(f"{path}: {len(a)} against {len(b)} items")
                return
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                self.walk(x, y, f"{path}[{i}]")
        elif isinstance(a, float) and isinstance(b, float):
            self.floats += 1
            if a != b and not (math.isnan(a) and math.isnan(b)):
                relative = abs(a - b) / max(abs(a), abs(b))
                if relative > self.worst[0]:
                    self.worst = (relative, f"{path}: {a!r} against {b!r}")
        elif a != b or type(a) is not type(b):
            self.mismatches.append(f"{path}: {a!r} against {b!r}")


def compare(before: Path, after: Path, tolerance: float) -> int:
    a, b = json.loads(before.read_text()), json.loads(after.read_text())
    walk = Comparison()
    walk.walk(a, b, "")
    print(f"{len(a)} payloads, {walk.floats} floats compared; largest relative difference {walk.worst[0]:.3g}"
          + (f" ({walk.worst[1]})" if walk.worst[1] else ""))  # fmt: skip
    for line in walk.mismatches[:20]:
        print("mismatch", line)
    if len(walk.mismatches) > 20:
        print(f"... {len(walk.mismatches) - 20} more mismatches")
    return 1 if walk.mismatches or walk.worst[0] > tolerance else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.engine_outputs", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    dump_args = commands.add_parser("dump", help="write register()'s outputs over the fixed payloads")
    dump_args.add_argument("path", type=Path)
    compare_args = commands.add_parser("compare", help="compare two dumps; exit 1 when they differ")
    compare_args.add_argument("before", type=Path)
    compare_args.add_argument("after", type=Path)
    compare_args.add_argument("--tolerance", type=float, default=0.0, help="largest relative difference allowed")
    args = parser.parse_args(argv)
    if args.command == "dump":
        return dump(args.path)
    return compare(args.before, args.after, args.tolerance)


if __name__ == "__main__":
    sys.exit(main())
