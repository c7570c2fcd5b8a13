"""Each setting is decided in one place: whether the service has a PACS, and how to reach it, is
``Settings.dicomweb`` (``services/core/config.py``); every other module receives that decision
(``settings.dicomweb``, ``settings.stores_dicom_results``) and reads no ``dicomweb_*`` field itself."""

from __future__ import annotations

import ast
from pathlib import Path

from services.core.config import DicomwebConfig, Settings

ROOT = Path(__file__).resolve().parents[2]
DECIDED = {"dicomweb_url", "dicomweb_username", "dicomweb_password", "dicomweb_token", "dicomweb_timeout_s",
           "dicomweb_store_results"}  # fmt: skip
"""Fields that only ``Settings.dicomweb`` and ``Settings.stores_dicom_results`` read."""


def test_only_the_settings_read_the_pacs_fields() -> None:
    readers = []
    for path in sorted((ROOT / "services").rglob("*.py")):
        if path == ROOT / "services" / "core" / "config.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Attribute) and node.attr in DECIDED:
                readers.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.attr}")
    assert readers == []


def test_the_pacs_of_the_settings() -> None:
    assert Settings(dicomweb_store_results=True).dicomweb is None
    assert not Settings(dicomweb_store_results=True).stores_dicom_results
    settings = Settings(dicomweb_url="http://pacs:8042/dicom-web", dicomweb_username="u", dicomweb_password="p",
                        dicomweb_token="t", dicomweb_timeout_s=3)  # fmt: skip
    assert settings.dicomweb == DicomwebConfig("http://pacs:8042/dicom-web", "u", "p", "t", 3.0)
    assert not settings.stores_dicom_results
    assert settings.model_copy(update={"dicomweb_store_results": True}).stores_dicom_results
