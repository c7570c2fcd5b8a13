"""The PACS's credentials never reach an error message: a job's error, a STOW attempt's error and the
webhook that carries them are built from the DICOM layer's messages, which API clients read."""

from __future__ import annotations

import socket

import pytest

from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs, shown_url
from services.dicom.errors import PacsUnavailable

USER, PASSWORD, TOKEN = "pacs-user", "S3cret-pw", "query-token-9"


def _closed_port() -> int:
    """A loopback port nothing listens on (bound, then closed: connecting to it is refused)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_shown_url_drops_userinfo_and_query() -> None:
    assert shown_url("http://u:p@pacs.example:8042/dicom-web?token=t#f") == "http://pacs.example:8042/dicom-web"
    assert shown_url("https://u:p@ss@[::1]:8042/dw") == "https://[::1]:8042/dw"
    assert shown_url("http://pacs.example/dicom-web") == "http://pacs.example/dicom-web"


@pytest.mark.parametrize("url_tail", ["/dicom-web", "/dicom-web/", f"/dicom-web?apikey={TOKEN}"])
def test_an_unreachable_pacs_is_named_without_its_credentials(url_tail: str) -> None:
    port = _closed_port()
    config = DicomwebConfig(url=f"http://{USER}:{PASSWORD}@127.0.0.1:{port}{url_tail}", timeout_s=2)
    with Pacs(config) as pacs, pytest.raises(PacsUnavailable) as caught:
        pacs.find_series("1.2.3", "1.2.5")
    message = caught.value.message
    assert PASSWORD not in message and USER not in message and TOKEN not in message, message
    assert f"127.0.0.1:{port}" in message  # the PACS is still named, for the operator's diagnosis
