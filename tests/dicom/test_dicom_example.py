"""examples/orthanc: Orthanc with the example's configuration and Lua script announces a stable DX
series with its UIDs (the way in from the PACS side), and the announced UIDs make a by-reference
payload that the DICOM layer resolves from that Orthanc."""

from __future__ import annotations

import http.server
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs
from services.dicom.reference import resolve_by_reference
from spine_client.dicom_input import payload_by_reference
from spine_engine.levels import LEVELS
from tools.dicom import synthetic
from tools.dicom.orthanc import free_port, orthanc_missing, start_orthanc, stop_orthanc

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "orthanc"
ANNOUNCE_TIMEOUT_S = 30.0
"""The example's series are announced StableAge (here 1 s) after their last instance, and Orthanc checks
stability about once a second; 30 s covers a loaded machine."""


@pytest.fixture
def receiver() -> Iterator[tuple[str, list[dict[str, Any]]]]:
    received: list[dict[str, Any]] = []

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers["content-length"]))
            received.append(json.loads(body))
            self.send_response(204)
            self.end_headers()

        def log_message(self, *_: Any) -> None:
            pass

    server = http.server.HTTPServer(("127.0.0.1", free_port()), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_port}/radiographs", received
    finally:
        server.shutdown()
        server.server_close()


def test_example_announces_a_radiograph_and_its_uids_resolve(
    tmp_path: Path, receiver: tuple[str, list[dict[str, Any]]], monkeypatch: pytest.MonkeyPatch
) -> None:
    reason = orthanc_missing()
    if reason:
        pytest.skip(reason)
    url, received = receiver
    config = json.loads((EXAMPLE / "orthanc.json").read_text(encoding="utf-8"))
    for key in ("StorageDirectory", "IndexDirectory", "HttpPort", "DicomPort", "RegisteredUsers"):
        config.pop(key)
    config.update(RemoteAccessAllowed=False, DicomServerEnabled=False, StableAge=1,
                  LuaScripts=[str(EXAMPLE / "spine-notify.lua")])  # fmt: skip
    assert config["Plugins"] == ["/usr/share/orthanc/plugins/libOrthancDicomWeb.so"]
    monkeypatch.setenv("SPINE_NOTIFY_URL", url)  # Orthanc inherits the environment
    proc, server = start_orthanc(tmp_path, config)
    try:
        image = synthetic.radiograph(imager_pixel_spacing=(0.15, 0.15), rows=3200, columns=1200)
        report = synthetic.radiograph(modality="CR")
        report.Modality = "SR"  # not a radiograph: not announced
        with Pacs(DicomwebConfig(server.dicomweb_url, server.username, server.password)) as pacs:
            pacs.store([image, report])
            deadline = time.monotonic() + ANNOUNCE_TIMEOUT_S
            while not received and time.monotonic() < deadline:
                time.sleep(0.1)
            assert len(received) == 1, "Orthanc did not announce the stable DX series"
            note = received[0]
            assert note["study_instance_uid"] == image.StudyInstanceUID
            assert note["series_instance_uid"] == image.SeriesInstanceUID
            assert note["sop_instance_uids"] == [image.SOPInstanceUID]
            assert (note["modality"], note["accession_number"], note["patient_id"]) == ("DX", "ACC-42", "P-0001")
            csv = tmp_path / "landmarks.csv"
            csv.write_text("".join(f"{lv},{600 + i},{300 + 160 * i}\n" for i, lv in enumerate(LEVELS)))
            payload = payload_by_reference(csv, note["study_instance_uid"], note["sop_instance_uids"][0])
            resolved, provenance = resolve_by_reference(payload, pacs)
        assert resolved["pa"]["pixel_spacing"] == [0.15, 0.15]
        assert provenance is not None and provenance.pa is not None
        assert provenance.pa.sop_instance_uid == image.SOPInstanceUID
        time.sleep(3.0)  # the SR-modality series became stable too (StableAge 1 s) and must not be announced
        assert len(received) == 1
    finally:
        stop_orthanc(proc)
