"""The client's optional dependencies, imported only when a command needs them (the one place in
``spine_client`` that imports inside functions): without them the client needs httpx and pydantic only.

- pydicom (``pip install 'spine-client[dicom]'``): ``spine submit --pa-dicom`` and
  ``SpineClient.submit_dicom`` read the radiographs' headers (``spine_client.dicom_input``).
- rich (``pip install 'spine-client[rich]'``): ``spine list``'s table and ``spine submit-dir``'s
  progress bar; without it the table is plain text and there is no progress bar.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from types import ModuleType
from typing import Any


class MissingExtra(ImportError):
    """An optional dependency a command needs is not installed; the message says which extra gives it."""


def dicom_input() -> ModuleType:
    """``spine_client.dicom_input`` (pydicom), or ``MissingExtra``."""
    try:
        from spine_client import dicom_input as module  # optional dependency: pydicom
    except ModuleNotFoundError as exc:
        if exc.name != "pydicom" and not str(exc.name).startswith("pydicom."):
            raise
        raise MissingExtra("reading DICOM files needs pydicom: pip install 'spine-client[dicom]'") from None
    return module


def print_table(columns: Sequence[str], rows: Sequence[Sequence[str]], title: str, *, width: int | None) -> None:
    """``rows`` under ``columns`` on stdout: a rich table, or aligned plain text without rich."""
    try:
        from rich.console import Console  # optional dependency: rich
        from rich.table import Table
    except ModuleNotFoundError:
        widths = [max([len(c), *(len(r[i]) for r in rows)]) for i, c in enumerate(columns)]
        lines = [title, "  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True))]
        lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths, strict=True)) for row in rows]
        sys.stdout.write("\n".join(line.rstrip() for line in lines) + "\n")
        return
    table = Table(*columns, title=title)
    for row in rows:
        table.add_row(*row)
    Console(width=width).print(table)


class _NoProgress:
    """Stands for rich's ``Progress`` when rich is absent: counts nothing, prints nothing."""

    def add_task(self, description: str, total: float | None = None) -> int:
        return 0

    def advance(self, task: int, advance: float = 1) -> None:
        return None


@contextmanager
def progress(*, disable: bool) -> Iterator[Any]:
    """A progress display on stderr (rich's ``Progress``: description, bar, done/total, elapsed time),
    or one that shows nothing without rich."""
    try:
        from rich.console import Console  # optional dependency: rich
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
    except ModuleNotFoundError:
        yield _NoProgress()
        return
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True), disable=disable) as bar:
        yield bar
