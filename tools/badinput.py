"""Bad input sent to a running spine service, and the answer each gets, as a Markdown table.

``python -m tools.badinput --spawn`` starts its own service (``spine serve --no-worker`` on the
embedded default, in a temp dir, on a free port of 127.0.0.1), makes the keys it needs with
``spine keys``, sends every kind of bad input below, prints the table and stops the service.
``--url URL --api-key KEY`` targets a running service instead (loopback only; then the revoked-key
and other-client rows need ``--revoked-key`` and ``--other-client-key``).

The table (docs/reliability.md holds it; tests/api/test_bad_input.py checks both the answers and that
the document is current) has, per input: the request, the status, the problem type and the JSON
paths of the offending fields. Nothing in it depends on ids or timing.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx

from services.core.config import Settings
from services.db.engine import session_scope
from services.db.keys import create_key, revoke
from services.db.migrate import upgrade
from spine_client.landmarks import LEVELS  # the contract's level names (a client's view)
from tools.loadbench import check_loopback
from tools.processes import run_tool, stop_processes

IDENTITY = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]
PROBLEMS = "https://spine.example/problems/"


def good_payload() -> dict[str, Any]:
    landmarks = [{"level": lv, "point": [round(100.0 + 15.0 * math.sin(math.pi * i / 16), 3), 50.0 + 26.25 * i]}
                 for i, lv in enumerate(LEVELS)]  # fmt: skip
    return {
        "pa": {"landmarks": landmarks},
        "boundary": {
            "T1": {"position": [0.0, 0.0, 0.0], "directors": copy.deepcopy(IDENTITY)},
            "L5": {"position": [0.0, 0.0, -420.0], "directors": copy.deepcopy(IDENTITY)},
        },
    }


def edited(change: Callable[[dict[str, Any]], None]) -> bytes:
    payload = good_payload()
    change(payload)
    return json.dumps(payload).encode()


def with_literal(token: str) -> bytes:
    """The good payload with T1's column replaced by a raw JSON token (NaN, Infinity, 1e400…)."""
    text = json.dumps(good_payload())
    first = json.dumps(good_payload()["pa"]["landmarks"][0]["point"][0])
    return text.replace(f"[{first},", f"[{token},", 1).encode()


@dataclass
class Case:
    kind: str
    request: str
    method: str = "POST"
    path: str = "/v1/jobs"
    body: bytes | Callable[[], Iterator[bytes]] | None = None
    content_type: str | None = "application/json"
    key: str = "client"  # client, none, malformed, wrong, revoked
    headers: dict[str, str] | None = None
    params: dict[str, str] | None = None


def _set(path: Sequence[str | int], value: Any) -> Callable[[dict[str, Any]], None]:
    def change(payload: dict[str, Any]) -> None:
        target: Any = payload
        for part in path[:-1]:
            target = target[part]
        target[path[-1]] = value

    return change


def with_key_twice() -> bytes:
    """The good payload with the PA view's ``units`` given twice, ``px`` then ``mm``."""
    return json.dumps(good_payload()).replace('"pa": {', '"pa": {"units": "px", "units": "mm", ', 1).encode()


def _duplicate_level(payload: dict[str, Any]) -> None:
    payload["pa"]["landmarks"][5]["level"] = "T5"


def _wrong_types(payload: dict[str, Any]) -> None:
    payload["pa"]["landmarks"][0]["point"] = ["a", 1]
    payload["pa"]["landmarks"][1]["level"] = 5


def _swap_t1_t2(payload: dict[str, Any]) -> None:
    first, second = payload["pa"]["landmarks"][0], payload["pa"]["landmarks"][1]
    first["point"], second["point"] = second["point"], first["point"]


def _t2_336_mm_below_t1(payload: dict[str, Any]) -> None:
    payload["pa"].update(units="px", pixel_spacing=[0.2, 0.2])
    payload["pa"]["landmarks"] = [{"level": "T1", "point": [500.0, 250.0]}, {"level": "T2", "point": [500.0, 1930.0]}]


def _crossed_corners(payload: dict[str, Any]) -> None:
    column, row = payload["pa"]["landmarks"][4].pop("point")
    top_left, top_right = [column - 15.0, row], [column + 15.0, row]
    bottom_left, bottom_right = [column - 15.0, row + 18.0], [column + 15.0, row + 18.0]
    payload["pa"]["landmarks"][4]["corners"] = [top_left, bottom_left, top_right, bottom_right]  # TR and BL swapped


def _corners_upside_down(payload: dict[str, Any]) -> None:
    column, row = payload["pa"]["landmarks"][4].pop("point")
    top_left, top_right = [column + 15.0, row + 18.0], [column - 15.0, row + 18.0]  # the body turned 180°
    bottom_left, bottom_right = [column + 15.0, row], [column - 15.0, row]
    payload["pa"]["landmarks"][4]["corners"] = [top_left, top_right, bottom_left, bottom_right]


def _pedicles_swapped(payload: dict[str, Any]) -> None:
    column, row = payload["pa"]["landmarks"][4]["point"]
    payload["pa"]["landmarks"][4]["pedicles"] = [[column + 12.0, row + 8.0], [column - 12.0, row + 8.0]]


def _many_landmarks(payload: dict[str, Any]) -> None:
    payload["pa"]["landmarks"] = payload["pa"]["landmarks"] * 7  # 119 landmarks


def _ten_megabytes() -> Iterator[bytes]:
    yield b'{"pa": {"landmarks": ['
    chunk = json.dumps({"level": "T1", "point": [1.0, 2.0]}).encode() + b","
    for _ in range(10 * 1024 * 1024 // len(chunk)):
        yield chunk
    yield b'{"level": "T1", "point": [1.0, 2.0]}]}}'


def cases() -> list[Case]:
    deep_field = "[" * 500 + "1" + "]" * 500
    return [
        Case("malformed JSON", "body `{\"pa\": [1, 2`", body=b'{"pa": [1, 2'),
        Case("empty body", "no body, content type JSON", body=b""),
        Case("not UTF-8", "body bytes `\\xff\\xfe{}`", body=b"\xff\xfe{}"),
        Case("JSON but not an object", "body `[1, 2, 3]`", body=b"[1, 2, 3]"),
        Case("wrong types", 'a point `["a", 1]`, a level `5`', body=edited(_wrong_types)),
        Case("number as a string", '`"12.5"` as a coordinate', body=with_literal('"12.5"')),
        Case("boolean as a number", "`true` as a coordinate", body=with_literal("true")),
        Case("NaN", "`NaN` as a coordinate", body=with_literal("NaN")),
        Case("infinity", "`Infinity` as a coordinate", body=with_literal("Infinity")),
        Case("huge number (float overflow)", "`1e400` as a coordinate", body=with_literal("1e400")),
        Case("huge number (finite)", "`1e300` as a coordinate", body=with_literal("1e300")),
        Case("huge number (too many digits)", "an integer of 5000 digits", body=with_literal("9" * 5000)),
        Case("unknown level", "level `T13`", body=edited(_set(("pa", "landmarks", 3, "level"), "T13"))),
        Case("duplicate levels", "T5 twice", body=edited(_duplicate_level)),
        Case("duplicate key", '`"units": "px", "units": "mm"` in the PA view', body=with_key_twice()),
        Case("duplicate key in a batch entry", "the same, in the first of two payloads", path="/v1/jobs/batch",
             body=b'{"jobs": [' + with_key_twice() + b", " + json.dumps(good_payload()).encode() + b"]}"),
        Case("landmarks out of order", "T1 drawn below T2 on the PA image (points swapped)", body=edited(_swap_t1_t2)),
        Case("levels implausibly far apart", "PA T1 and T2 1680 px apart at 0.2 mm/px (336 mm: the click meant "
             "for L5 labelled T2)", body=edited(_t2_336_mm_below_t1)),
        Case("crossed corners", "T5's corners with top-right and bottom-left swapped", body=edited(_crossed_corners)),
        Case("corners turned upside down", "T5's corners given turned 180° (its top edge running left)",
             body=edited(_corners_upside_down)),
        Case("pedicles swapped", "T5's pedicles given image-right first", body=edited(_pedicles_swapped)),
        Case("no room for the spine", "PA `acquisition` `{\"projection_model\": \"perspective\", "
             "\"distance_source_to_detector_mm\": 150}` (the SOD taken 200 mm before the detector)",
             body=edited(_set(("pa", "acquisition"), {"projection_model": "perspective",
                                                      "distance_source_to_detector_mm": 150.0}))),
        Case("landmarks off the image", "PA `acquisition.image_size` `[100, 100]` with landmarks beyond it",
             body=edited(_set(("pa", "acquisition"), {"image_size": [100.0, 100.0]}))),
        Case("too many landmarks", "119 landmarks in the PA view", body=edited(_many_landmarks)),
        Case("non-orthonormal directors", "T1 directors `[[2,0,0],[0,-1,0],[0,0,-1]]`",
             body=edited(_set(("boundary", "T1", "directors"), [[2.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]]))),
        Case("left-handed directors", "T1 directors `[[1,0,0],[0,-1,0],[0,0,1]]`",
             body=edited(_set(("boundary", "T1", "directors"), [[1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]]))),
        Case("unknown field", "`\"colour\": \"blue\"` at the top", body=edited(_set(("colour",), "blue"))),
        Case("unknown profile", "`options.profile` `\"defualt\"`",
             body=edited(_set(("options",), {"profile": "defualt"}))),
        Case("NUL character in a text", "`options.profile` `\"x\\u0000y\"` (PostgreSQL stores no NUL)",
             body=edited(_set(("options",), {"profile": "x\x00y"}))),
        Case("study date not YYYY-MM-DD", "`study.study_date` `\"2026-02-10T00:00:00\"` (a date-time)",
             body=edited(_set(("study",), {"study_instance_uid": "1.2.3", "study_date": "2026-02-10T00:00:00"}))),
        Case("study date as a number", "`study.study_date` `86400` (lax parsers read Unix seconds)",
             body=edited(_set(("study",), {"study_instance_uid": "1.2.3", "study_date": 86400}))),
        Case("blank Patient ID", "`study.patient_id` `\"  \"` (an empty DICOM LO)",
             body=edited(_set(("study",), {"study_instance_uid": "1.2.3", "patient_id": "  "}))),
        Case("deep nesting (parser)", "100,000 nested `[`", body=b"[" * 100_000 + b"]" * 100_000),
        Case("deep nesting (in a field)", "a point nested 500 deep",
             body=edited(_set(("pa", "landmarks", 0, "point"), json.loads(deep_field)))),
        Case("10 MB body", "10 MiB of landmarks, streamed without Content-Length", body=_ten_megabytes),
        Case("batch of 1001", "`{\"jobs\": [...1001 payloads]}`", path="/v1/jobs/batch",
             body=json.dumps({"jobs": [good_payload()] * 1001}).encode()),
        Case("batch entry not an object", "`{\"jobs\": [[null]]}` (answered per entry)", path="/v1/jobs/batch",
             body=b'{"jobs": [[null]]}'),
        Case("wrong content type", "`text/plain`", body=json.dumps(good_payload()).encode(), content_type="text/plain"),
        Case("form content type", "`application/x-www-form-urlencoded`", body=b"pa=1",
             content_type="application/x-www-form-urlencoded"),
        Case("no content type", "payload without Content-Type", body=json.dumps(good_payload()).encode(),
             content_type=None),
        Case("oversized Idempotency-Key", "256 characters", body=json.dumps(good_payload()).encode(),
             headers={"Idempotency-Key": "k" * 256}),
        Case("empty Idempotency-Key", "`Idempotency-Key:` with no value", body=json.dumps(good_payload()).encode(),
             headers={"Idempotency-Key": ""}),
        Case("unknown query parameter", "`GET /v1/jobs?stauts=queued`", method="GET", path="/v1/jobs",
             params={"stauts": "queued"}, content_type=None),
        Case("control character in a DICOM filter", "`GET /v1/jobs?patient_id=A%0AB` (a line break in an LO)",
             method="GET", path="/v1/jobs", params={"patient_id": "A\nB"}, content_type=None),
        Case("empty DICOM filter", "`GET /v1/jobs?patient_id=` (no Patient ID is empty)",
             method="GET", path="/v1/jobs", params={"patient_id": ""}, content_type=None),
        Case("number as a timestamp", "`GET /v1/jobs?created_after=0.5`", method="GET", path="/v1/jobs",
             params={"created_after": "0.5"}, content_type=None),
        Case("timestamp beyond year 9999 in UTC", "`GET /v1/jobs?created_before=9999-12-31T23:59:59-14:00`",
             method="GET", path="/v1/jobs", params={"created_before": "9999-12-31T23:59:59-14:00"}, content_type=None),
        Case("method not allowed", "`DELETE /v1/jobs`", method="DELETE", path="/v1/jobs", content_type=None),
        Case("bad job id", "`GET /v1/jobs/not-a-uuid`", method="GET", path="/v1/jobs/not-a-uuid", content_type=None),
        Case("another client's job", "`GET /v1/jobs/{id}` of a job another client made", method="GET",
             path="/v1/jobs/{other}", content_type=None),
        Case("unknown job", "`GET /v1/jobs/{random uuid}`", method="GET",
             path="/v1/jobs/00000000-0000-4000-8000-000000000000", content_type=None),
        Case("missing API key", "no `Authorization`", body=json.dumps(good_payload()).encode(), key="none"),
        Case("malformed API key", "`Authorization: Bearer hello`", body=json.dumps(good_payload()).encode(),
             key="malformed"),
        Case("wrong API key", "a well-formed key with a wrong secret", body=json.dumps(good_payload()).encode(),
             key="wrong"),
        Case("revoked API key", "a key after `spine keys revoke`", body=json.dumps(good_payload()).encode(),
             key="revoked"),
        Case("not Bearer", "`Authorization: Basic dXNlcjpwYXNz`", body=json.dumps(good_payload()).encode(),
             key="basic"),
    ]


@dataclass
class Keys:
    client: str
    revoked: str | None
    other_job: str | None


def _auth(case: Case, keys: Keys) -> dict[str, str]:
    if case.key == "none":
        return {}
    if case.key == "malformed":
        return {"Authorization": "Bearer hello"}
    if case.key == "basic":
        return {"Authorization": "Basic dXNlcjpwYXNz"}
    if case.key == "wrong":
        key_id = keys.client.split("_")[1]
        return {"Authorization": f"Bearer spine_{key_id}_{'A' * 43}"}
    if case.key == "revoked":
        return {"Authorization": f"Bearer {keys.revoked}"} if keys.revoked else {}
    return {"Authorization": f"Bearer {keys.client}"}


def send(client: httpx.Client, case: Case, keys: Keys) -> dict[str, Any]:
    headers = {**_auth(case, keys), **(case.headers or {})}
    if case.content_type is not None:
        headers["Content-Type"] = case.content_type
    path = case.path.replace("{other}", keys.other_job or "00000000-0000-4000-8000-000000000001")
    content = case.body() if callable(case.body) else case.body
    response = client.request(case.method, path, content=content, headers=headers, params=case.params)
    body: Any = {}
    if "json" in response.headers.get("content-type", ""):
        body = response.json()
    row: dict[str, Any] = {"kind": case.kind, "request": case.request, "status": response.status_code}
    problem = body if response.status_code >= 400 else None
    if problem is None and isinstance(body, dict) and body.get("results"):  # a batch: the first entry's problem
        first = body["results"][0]
        problem = first.get("problem")
        row["status"] = f"{response.status_code} (entry {first.get('status')})"
    if response.status_code == 405:  # RFC 9110 §15.5.6: the methods the resource has
        row["status"] = f"405 (Allow: {response.headers.get('allow', '')})"
    row["type"] = str(problem.get("type", "")).removeprefix(PROBLEMS) if isinstance(problem, dict) else ""
    paths = [e.get("path", "") for e in (problem or {}).get("errors") or []] if isinstance(problem, dict) else []
    row["fields"] = ", ".join(sorted({p or "(body)" for p in paths}))[:120]
    row["detail"] = re.sub(r"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}", "<id>",
                           str((problem or {}).get("detail", "")))  # fmt: skip
    row["www_authenticate"] = response.headers.get("www-authenticate", "")
    return row


def run(base_url: str, keys: Keys) -> list[dict[str, Any]]:
    with httpx.Client(base_url=base_url, timeout=60) as client:
        return [send(client, case, keys) for case in cases()]


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| bad input | request | answer | problem type | offending fields |", "| --- | --- | --- | --- | --- |"]
    for r in rows:
        fields = f"`{r['fields']}`" if r["fields"] else ""
        kind = f"`{r['type']}`" if r["type"] else ""
        lines.append(f"| {r['kind']} | {r['request']} | {r['status']} | {kind} | {fields} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ --spawn


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])




@contextmanager
def spawned() -> Iterator[tuple[str, Keys]]:
    """An embedded-default service of its own (API only), with a client key, a revoked key and a job
    of another client."""
    data_dir = Path(tempfile.mkdtemp(prefix="spine-badinput-"))
    env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
    env.update(SPINE_DATA_DIR=str(data_dir), SPINE_LOG_LEVEL="WARNING", SPINE_SERVE_WORKER="false")
    spine = [sys.executable, "-m", "services.cli"]
    settings = Settings(data_dir=data_dir)
    upgrade(settings, quiet=True)
    with session_scope(settings) as session:  # the database `spine keys create|revoke` writes to
        client, other, revoked = (create_key(session, name)[1]
                                  for name in ("bad-input-client", "another-client", "revoked-client"))  # fmt: skip
        revoke(session, "revoked-client")
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    log = (data_dir / "serve.log").open("wb")
    proc = subprocess.Popen([*spine, "serve", "--no-worker", "--host", "127.0.0.1", "--port", str(port)], env=env,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(url + "/healthz", timeout=1).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the spawned service did not start: " + (data_dir / "serve.log").read_text())
            time.sleep(0.2)
        made = httpx.post(url + "/v1/jobs", json=good_payload(), headers={"Authorization": f"Bearer {other}"})
        assert made.status_code == 202, made.text
        yield url, Keys(client=client, revoked=revoked, other_job=made.json()["id"])
    finally:
        stop_processes([proc])
        log.close()


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.badinput", description=__doc__.splitlines()[0])
    parser.add_argument("--spawn", action="store_true", help="start a service of its own, stop it after")
    parser.add_argument("--url", default="http://127.0.0.1:8000", help="base URL of a running service (loopback)")
    parser.add_argument("--api-key", default=os.environ.get("SPINE_API_KEY"), help="a client key (not --spawn)")
    parser.add_argument("--revoked-key", help="a revoked key (not --spawn)")
    parser.add_argument("--other-job", help="a job id of another client (not --spawn)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON instead of the table")
    args = parser.parse_args(argv)
    if args.spawn:
        with spawned() as (url, keys):
            rows = run(url, keys)
    else:
        check_loopback(args.url)
        if not args.api_key:
            parser.error("--api-key (or SPINE_API_KEY) is needed without --spawn")
        rows = run(args.url, Keys(args.api_key, args.revoked_key, args.other_job))
    sys.stdout.write(json.dumps(rows, indent=2) + "\n" if args.json else table(rows))
    return 0


if __name__ == "__main__":
    run_tool(main, "badinput")
