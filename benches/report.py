"""Printing and saving experiment tables: an aligned text table, JSON, and a PNG plot."""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any


def format_table(columns: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """Rows as an aligned plain-text table; floats with 3 decimals."""
    cells = [[f"{c:.3f}" if isinstance(c, float) else str(c) for c in row] for row in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in cells)) for i, h in enumerate(columns)]
    lines = ["  ".join(str(h).rjust(w) for h, w in zip(columns, widths, strict=True))]
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)) for row in cells]
    return "\n".join(lines)


def write_json(path: Path, data: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")


def shared_data_dir(name: str) -> Path:
    """Folder of data set ``name``: ``$SPINE_SHARED_DATA/<name>``, else ``../shared/data/<name>``
    beside the repository. Evaluation data stays outside the repository; commands take ``--data``."""
    env = os.environ.get("SPINE_SHARED_DATA")
    base = Path(env) if env else Path(__file__).resolve().parents[1].parent / "shared" / "data"
    return base / name


def subplots(*args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """``plt.subplots`` on the Agg backend (no display needed): (figure, axes)."""
    import matplotlib  # lazy: plotting only, the benches' JSON needs no matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: after the Agg backend is chosen

    return plt.subplots(*args, **kwargs)


def save_figure(fig: Any, path: Path, dpi: int = 120) -> None:
    """Lay out, write as PNG (creating the folder) and close ``fig``."""
    import matplotlib.pyplot as plt  # lazy: plotting only

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
