"""No issue numbers in code, docs or shipped data: the word "issue" and a tracker's number mean nothing to a
reader of the repository.
History lives in CHANGELOG.md; a third party's issue (another project's tracker) names its project."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SUFFIXES = {".py", ".md", ".json", ".ts", ".yaml", ".yml", ".toml", ".html", ".css", ".cfg", ".ini"}
SKIP = {"CHANGELOG.md"}
PATTERN = re.compile(r"(?<![\w-])(?:issue|issues)\s*#?\d+", re.IGNORECASE)
PROJECTS = "redis-py|kombu|celery|numba|highdicom|pydicom|orthanc|fastapi"
THIRD_PARTY = re.compile(rf"\b(?:{PROJECTS})\s+issue\s*#?\d+", re.IGNORECASE)


def _tracked() -> list[Path]:
    out = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    return [ROOT / name for name in out.splitlines() if Path(name).suffix in SUFFIXES or name == "Makefile"]


def test_no_issue_numbers_in_the_repository() -> None:
    found = []
    for path in _tracked():
        if path.name in SKIP or "services/api/static" in path.as_posix() or not path.is_file():
            continue
        text = path.read_text(errors="replace")
        third_party = {m.start() + m.group(0).lower().index("issue") for m in THIRD_PARTY.finditer(text)}
        for m in PATTERN.finditer(text):
            if m.start() not in third_party:
                line = text.count("\n", 0, m.start()) + 1
                found.append(f"{path.relative_to(ROOT)}:{line}: {m.group(0)}")
    assert not found, found
