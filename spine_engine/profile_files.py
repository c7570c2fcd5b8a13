"""Where the shipped elastic profiles lie and which names they have, apart from ``anatomy`` (which
reads them, with numpy and scipy): validation names an unknown ``options.profile`` with these alone,
so that the API refuses it at the door without loading the engine's numerics."""

from __future__ import annotations

import re
from pathlib import Path

PROFILES_DIR = Path(__file__).resolve().parent / "profiles"
PROFILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
"""A profile's name: the stem of its file in ``PROFILES_DIR`` (no path separator, no leading dot)."""


def list_profiles() -> list[str]:
    """Names of the profiles shipped in ``spine_engine/profiles/`` (file stems), sorted."""
    return sorted(p.stem for p in PROFILES_DIR.glob("*.json"))


_FOUND: set[str] = set()
"""Names ``is_profile`` has found, as ``anatomy.load_profile`` keeps the profiles it has read."""


def is_profile(name: str) -> bool:
    """Whether ``name`` is a shipped profile's (``PROFILE_NAME`` and a file of that name). A name once
    found costs no file-system call again (``forget_found``); a missing one is looked for every time."""
    if name in _FOUND:
        return True
    found = PROFILE_NAME.fullmatch(name) is not None and (PROFILES_DIR / f"{name}.json").is_file()
    if found:
        _FOUND.add(name)
    return found


def forget_found() -> None:
    """Forget the names ``is_profile`` has found (``anatomy.save_profile`` calls it, as it forgets the
    profiles read)."""
    _FOUND.clear()
