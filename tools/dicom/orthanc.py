"""A throwaway Orthanc for tests, the benchmark and the example loop: Debian's ``orthanc`` and
``orthanc-dicomweb`` started as ``/usr/sbin/Orthanc config.json`` with storage in a given folder, HTTP on
a free loopback port with ``RemoteAccessAllowed`` false and HTTP basic authentication, stopped by its
PID. Orthanc 1.10 (Debian 12) cannot bind its DICOM (DIMSE) port to loopback only, so its DICOM
server is off: DICOMweb is the only way in.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import requests

ORTHANC = os.environ.get("SPINE_TEST_ORTHANC", "/usr/sbin/Orthanc")
DICOMWEB_PLUGIN = os.environ.get("SPINE_TEST_ORTHANC_DICOMWEB", "/usr/share/orthanc/plugins/libOrthancDicomWeb.so")
ORTHANC_START_TIMEOUT_S = 30.0
"""Seconds to wait for Orthanc's REST API: it answers within about a second on an idle machine; the
margin covers two busy cores shared by several test runs."""


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


def start_orthanc(
    folder: Path, extra: dict[str, Any] | None = None, *, port: int | None = None
) -> tuple[subprocess.Popen[bytes], OrthancServer]:
    """Start Orthanc on ``port`` (default: a free loopback port) with storage under ``folder``; wait until
    it answers. Started again on the same ``folder``, it serves what it stored before."""
    port = port or free_port()
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


@contextlib.contextmanager
def running_orthanc(folder: Path, extra: dict[str, Any] | None = None) -> Iterator[OrthancServer]:
    """``start_orthanc`` for the duration of the block, then ``stop_orthanc``."""
    proc, server = start_orthanc(folder, extra)
    try:
        yield server
    finally:
        stop_orthanc(proc)


def stop_orthanc(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to this Orthanc's PID (it started its own session), SIGKILL after 10 s."""
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)
