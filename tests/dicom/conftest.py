"""Fixtures of the DICOM tests: a throwaway Orthanc with its DICOMweb plugin, and payloads.

Orthanc is Debian's (packages ``orthanc``, ``orthanc-dicomweb``; ``dcmtk`` for dsrdump), started as
``/usr/sbin/Orthanc config.json`` with its storage in a temporary folder, HTTP on a free loopback
port with ``RemoteAccessAllowed`` false, and stopped by its PID. Orthanc 1.10 cannot bind its DICOM
(DIMSE) port to loopback only, so the DICOM server is off: the tests use DICOMweb only. When Orthanc
or the plugin is missing the tests that need it are skipped, saying why (CI counts skips as failures).
"""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import requests

ORTHANC = os.environ.get("SPINE_TEST_ORTHANC", "/usr/sbin/Orthanc")
DICOMWEB_PLUGIN = os.environ.get("SPINE_TEST_ORTHANC_DICOMWEB", "/usr/share/orthanc/plugins/libOrthancDicomWeb.so")
ORTHANC_START_TIMEOUT_S = 30.0
"""Seconds to wait for Orthanc's REST API: it answers within about a second on an idle machine; the
margin covers two busy cores shared by several test runs."""

LEVELS = ["T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12",
          "L1", "L2", "L3", "L4", "L5"]  # fmt: skip
IDENTITY_LPS = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class OrthancServer:
    url: str
    """REST root, e.g. http://127.0.0.1:PORT"""
    dicomweb_url: str
    pid: int
    username: str
    password: str
    log: Path

    def auth(self) -> tuple[str, str]:
        return (self.username, self.password)


def orthanc_missing() -> str | None:
    if not os.access(ORTHANC, os.X_OK):
        return f"Orthanc is not installed ({ORTHANC} missing: apt-get install orthanc orthanc-dicomweb)"
    if not os.path.exists(DICOMWEB_PLUGIN):
        return (
            f"Orthanc's DICOMweb plugin is not installed ({DICOMWEB_PLUGIN} missing: apt-get install orthanc-dicomweb)"
        )
    return None


def start_orthanc(folder: Path, extra: dict[str, Any] | None = None) -> tuple[subprocess.Popen[bytes], OrthancServer]:
    """Start Orthanc on a free loopback port with storage under ``folder``; wait until it answers."""
    port = free_port()
    username, password = "spine", "spine-test-password"
    config = {
        "Name": "spine-test",
        "StorageDirectory": str(folder / "storage"),
        "IndexDirectory": str(folder / "index"),
        "HttpPort": port,
        "RemoteAccessAllowed": False,
        "AuthenticationEnabled": True,
        "RegisteredUsers": {username: password},
        "DicomServerEnabled": False,
        "DicomPort": free_port(),
        "Plugins": [DICOMWEB_PLUGIN],
        "DicomWeb": {
            "Enable": True,
            "Root": "/dicom-web/",
            "EnableWado": False,
            "StudiesMetadata": "Full",
            "SeriesMetadata": "Full",
        },
        "StableAge": 1,
        "SaveJobs": False,
        "OrthancExplorerEnabled": False,
        "WebDavEnabled": False,
        "HttpThreadsCount": 8,
        **(extra or {}),
    }
    path = folder / "config.json"
    path.write_text(json.dumps(config, indent=2), encoding="utf-8")
    log = folder / "orthanc.log"
    with log.open("wb") as out:
        proc = subprocess.Popen([ORTHANC, str(path)], cwd=folder, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)  # fmt: skip
    server = OrthancServer(f"http://127.0.0.1:{port}", f"http://127.0.0.1:{port}/dicom-web", proc.pid,
                           username, password, log)  # fmt: skip
    deadline = time.monotonic() + ORTHANC_START_TIMEOUT_S
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"Orthanc exited with {proc.returncode}: {log.read_text(errors='replace')[-2000:]}")
        try:
            if requests.get(f"{server.url}/system", auth=server.auth(), timeout=1).ok:
                return proc, server
        except requests.RequestException:
            pass
        if time.monotonic() > deadline:
            stop_orthanc(proc)
            raise RuntimeError(f"Orthanc did not answer within {ORTHANC_START_TIMEOUT_S:g} s: "
                               f"{log.read_text(errors='replace')[-2000:]}")  # fmt: skip
        time.sleep(0.1)


def stop_orthanc(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to this Orthanc's PID (it started its own session), SIGKILL after 10 s."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)


@pytest.fixture(scope="session")
def orthanc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OrthancServer]:
    reason = orthanc_missing()
    if reason:
        pytest.skip(reason)
    proc, server = start_orthanc(tmp_path_factory.mktemp("orthanc"))
    try:
        yield server
    finally:
        stop_orthanc(proc)


def spine_payload(
    curve_mm: float = 15.0, length_mm: float = 420.0, *, spacing_mm: float | None = None
) -> dict[str, Any]:
    """A PA payload: 17 endplate midpoints on a C-curve (mm, or px when ``spacing_mm`` is given), T1 and L5 given."""
    landmarks = []
    for i, level in enumerate(LEVELS):
        t = i / (len(LEVELS) - 1)
        col, row = 100.0 + curve_mm * math.sin(math.pi * t), 50.0 + length_mm * t
        if spacing_mm:
            col, row = col / spacing_mm, row / spacing_mm
        landmarks.append({"level": level, "point": [round(col, 3), round(row, 3)]})
    pa: dict[str, Any] = {"landmarks": landmarks}
    if spacing_mm:
        pa["units"] = "px"
    return {
        "pa": pa,
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": IDENTITY_LPS},
            "L5": {"position": [0.0, 0.0, -length_mm], "directors": IDENTITY_LPS},
        },
    }
