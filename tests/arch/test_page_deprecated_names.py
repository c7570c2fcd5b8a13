"""The page reads the result's deprecated aliases (``pa_bending_deg``, ``lateral_bending_deg``; openapi.yaml
names ``sagittal_bending_deg`` and ``frontal_bending_deg``) in one place only, ``types.ts``'s
``sagittalBending`` / ``frontalBending`` fallbacks, so that removing the aliases after their deprecation
changes one line: the projections, the 3D view and the CSV read the bending through those."""

from __future__ import annotations

import re
from pathlib import Path

WEB_SRC = Path(__file__).resolve().parents[2] / "web" / "src"
DEPRECATED = re.compile(r"\.(pa_bending_deg|lateral_bending_deg)\b")


def test_the_page_reads_deprecated_bending_names_only_in_types_fallbacks() -> None:
    readers = {
        f"{path.name}:{number}"
        for path in sorted(WEB_SRC.glob("*.ts"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if DEPRECATED.search(line)
    }
    fallbacks = {
        f"types.ts:{number}"
        for number, line in enumerate((WEB_SRC / "types.ts").read_text().splitlines(), 1)
        if DEPRECATED.search(line) and ("export const frontalBending" in line or "export const sagittalBending" in line)
    }
    assert len(fallbacks) == 2 and readers == fallbacks, sorted(readers - fallbacks)
