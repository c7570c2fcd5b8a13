"""The client's command line as a script uses it, against a real `spine serve` (API and Celery worker on
the embedded default): a closed stdout (`| head -1`) ends with 141 and no traceback, for the client's
commands and the operator's; `-` reads a landmark CSV from stdin and writes a DICOM export to stdout; a
landmark CSV that is not UTF-8, a payload file JSON does not allow (empty, NaN, 1e400, nested too deep)
and a `--base` that is not a payload object are usage errors naming the file and why, before any
request; a byte-order mark is skipped; a `--timeout` below 0 or not finite is a usage error; a job that
ends as the wait times out is printed and exits as ended; a service that stops answering ends the wait
by its timeout, naming the job made; a failed job says why on stderr; a summary that cannot be written
is refused before any job is made; a batch over the service's body limit is halved instead of sinking
the run; a run cut short names its run key; a server's control characters never reach the terminal;
`get --measures --format json` prints JSON; `--version` prints the version; a URL the service has no
route for exits 4 (check --url), not 5 (no such job); `list` and summary.csv give each angle with its SD
and model-estimate mark, in columns added at the end, and `get --format csv` marks the frontal tilts
when `cobb` is unreliable; `--help` shows the option values docs/client.md names."""

from __future__ import annotations

import argparse
import csv
import http.server
import io
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import tomllib
import uuid
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import Any
from unittest import mock

import pytest

import spine_client
from spine_client import NotFound, RouteNotFound, SpineClient, cli, tables
from spine_client.client import LAST_LOOK_S
from spine_client.errors import WaitTimeout
from spine_engine.levels import LEVELS
from tests.cli.test_service_cli import Serve
from tests.conftest import engine_refused_payload, spine_payload

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]
CLIENT_DOC = ROOT / "docs" / "client.md"
BATCH_LIMIT = 65_536
"""The service's ``SPINE_MAX_BATCH_BODY_BYTES`` here: above a batch of a few plain payloads (about 3 kB
each), below one padded to twice it."""
UIDS = ["--study-instance-uid", "1.2.3", "--pa-sop-instance-uid", "1.2.3.4", "--print-payload"]
"""A landmark CSV's images by UID, printed instead of sent: no service involved."""


@pytest.fixture(scope="module")
def serve(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Serve]:
    with mock.patch.dict(os.environ, {"SPINE_MAX_BATCH_BODY_BYTES": str(BATCH_LIMIT)}):
        started = Serve(tmp_path_factory.mktemp("serve"))
    try:
        yield started
    finally:
        started.interrupt()


def _argv(serve: Serve) -> list[str]:
    return ["--url", serve.base, "--api-key", serve.api_key]


def _job_count(serve: Serve) -> int:
    return len(serve.client.get("/v1/jobs", params={"limit": 500}).json()["jobs"])


@pytest.fixture(scope="module")
def idle(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Serve]:
    """A `spine serve` without worker: its jobs stay queued."""
    started = Serve(tmp_path_factory.mktemp("idle"), worker=False)
    try:
        yield started
    finally:
        started.interrupt()


@pytest.fixture(scope="module")
def succeeded(serve: Serve) -> str:
    job = serve.wait(serve.client.post("/v1/jobs", json=spine_payload()).json()["id"])
    assert job["status"] == "succeeded", job["error"]
    return str(job["id"])


# ------------------------------------------------------------------ a closed stdout


def _into_closed_pipe(argv: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """Run ``argv`` with stdout a pipe whose reader is already gone: its first write fails (EPIPE), as
    under ``| head -1`` once head has exited."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run(argv, stdout=write_end, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                              env={**os.environ, **env}, timeout=120)  # fmt: skip
    finally:
        os.close(write_end)


@pytest.mark.parametrize("command", [["list", "--format", "json"], ["list"], ["get", "{id}", "--format", "csv"],
                                     ["get", "{id}"]])  # fmt: skip
def test_a_closed_stdout_ends_the_client_with_141_and_no_traceback(
    command: list[str], serve: Serve, succeeded: str
) -> None:
    argv = [sys.executable, "-m", "spine_client", *(a.format(id=succeeded) for a in command), *_argv(serve)]
    done = _into_closed_pipe(argv, {})
    assert done.returncode == 141, done.stderr  # cli.EXIT_BROKEN_PIPE
    assert done.stderr == "", done.stderr


@pytest.mark.parametrize("command", [["openapi"], ["list"]])
def test_a_closed_stdout_ends_the_operator_command_with_141_and_no_traceback(
    command: list[str], serve: Serve, tmp_path: Path
) -> None:
    env = {"SPINE_DATA_DIR": str(tmp_path), "SPINE_URL": serve.base, "SPINE_API_KEY": serve.api_key}
    done = _into_closed_pipe([sys.executable, "-m", "services.cli", *command], env)
    assert done.returncode == 141, done.stderr
    assert done.stderr == "", done.stderr


# ------------------------------------------------------------------ input files and `-`


def _stdin(monkeypatch: pytest.MonkeyPatch, data: bytes) -> None:
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data), encoding="utf-8"))


def test_a_landmark_csv_that_is_not_utf8_is_a_usage_error_naming_the_byte(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv_path = tmp_path / "landmarks.csv"
    csv_path.write_bytes(b"T1,1,2\nT2,3,4\nT3,5,\xe96\n")  # Latin-1 e-acute: not UTF-8
    assert cli.main(["submit", str(csv_path), *UIDS]) == cli.EXIT_USAGE
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == f"spine: error: {csv_path}: not UTF-8 text: byte 0xe9 at offset 19\n"


def test_a_landmark_csv_from_stdin_with_a_byte_order_mark(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _stdin(monkeypatch, "\ufefflevel,column,row\nT1,1,2\nL5,3,4\n".encode())  # a spreadsheet's UTF-8 CSV
    assert cli.main(["submit", "-", *UIDS]) == cli.EXIT_OK
    payload = json.loads(capsys.readouterr().out)
    assert [lm["level"] for lm in payload["pa"]["landmarks"]] == ["T1", "L5"]
    _stdin(monkeypatch, b"T1,1,2\n")
    assert cli.main(["submit", "-", *UIDS, "--base", "-"]) == cli.EXIT_USAGE
    assert "FILE and --base cannot both be -" in capsys.readouterr().err


@pytest.mark.parametrize(("content", "says"), [
    (b"", "is empty: a JSON document was expected"),
    (b" \n", "is empty: a JSON document was expected"),
    (b'{"pa": {"landmarks": [{"level": "T1", "point": [NaN, 1]}]}}', "is not valid JSON: NaN is not a JSON number"),
    (b'{"pa": {"landmark_sd_mm": -Infinity}}', "is not valid JSON: -Infinity is not a JSON number"),
    (b'{"pa": {"landmark_sd_mm": 1e400}}', "is not valid JSON: the number 1e400 is beyond a double's range"),
    (b"[" * 100_000 + b"]" * 100_000, "nests arrays or objects deeper than this reader can follow"),
    (b'{"pa": "\xe9"}', "is not UTF-8 text, as JSON is (RFC 8259 §8.1): byte 0xe9 at offset 8"),
])  # fmt: skip
def test_a_payload_file_json_does_not_allow_is_a_usage_error_before_any_request(
    content: bytes, says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "payload.json"
    path.write_bytes(content)
    # port 1: a request would be exit 4; the payload is refused before, with one line naming the file
    assert cli.main(["submit", str(path), "--url", "http://127.0.0.1:1", "--retries", "0"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert err.startswith(f"spine: error: {path} {says}") and err.count("\n") == 1, err


def test_a_payload_with_a_byte_order_mark_is_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """RFC 8259 §8.1 lets a parser ignore a byte-order mark; Windows tools (PowerShell 5's UTF-8) write one."""
    payload = spine_payload()
    (tmp_path / "p.json").write_bytes(b"\xef\xbb\xbf" + json.dumps(payload).encode())
    assert cli.main(["submit", str(tmp_path / "p.json"), "--print-payload"]) == cli.EXIT_OK
    assert json.loads(capsys.readouterr().out) == payload
    _stdin(monkeypatch, b"\xef\xbb\xbf" + json.dumps(payload).encode())
    assert cli.main(["submit", "-", "--print-payload"]) == cli.EXIT_OK
    assert json.loads(capsys.readouterr().out) == payload


@pytest.mark.parametrize(("base", "says"), [
    ([1, 2], "a payload is a JSON object, not an array"), ("x", "a payload is a JSON object, not a string"),
    ({"pa": 3}, "pa is a JSON object, not a number"), ({"study": []}, "study is a JSON object, not an array"),
])  # fmt: skip
def test_a_base_that_is_not_a_payload_object_is_a_usage_error(
    base: Any, says: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "landmarks.csv").write_text("T1,1,2\nL5,3,4\n", encoding="utf-8")
    (tmp_path / "base.json").write_text(json.dumps(base), encoding="utf-8")
    argv = ["submit", str(tmp_path / "landmarks.csv"), *UIDS, "--base", str(tmp_path / "base.json")]
    assert cli.main(argv) == cli.EXIT_USAGE
    assert capsys.readouterr().err == f"spine: error: --base {tmp_path / 'base.json'}: {says}\n"


def test_a_dicom_export_to_stdout(
    serve: Serve, succeeded: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsysbinary: pytest.CaptureFixture[bytes],
) -> None:  # fmt: skip
    monkeypatch.chdir(tmp_path)
    assert cli.main(["get", succeeded, "--sr", "-", *_argv(serve)]) == cli.EXIT_OK
    out = capsysbinary.readouterr().out
    assert out[128:132] == b"DICM"  # a Part 10 file: 128-byte preamble, then "DICM" (PS3.10 §7.1)
    assert not (tmp_path / "-").exists()
    assert cli.main(["get", succeeded, "--sr", "-", "--figure-dcm", "-", *_argv(serve)]) == cli.EXIT_USAGE


# ------------------------------------------------------------------ waiting


@pytest.mark.parametrize("command", ["submit", "submit-dir"])
@pytest.mark.parametrize("timeout", ["-1", "nan", "inf", "soon"])
def test_a_wait_timeout_below_0_or_not_finite_is_a_usage_error(
    command: str, timeout: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "p.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    target = str(tmp_path / "p.json") if command == "submit" else str(tmp_path)
    with pytest.raises(SystemExit) as stopped:  # port 1: a request would be exit 4, not a usage error
        cli.main([command, target, "--timeout", timeout, "--url", "http://127.0.0.1:1", "--retries", "0"])
    assert stopped.value.code == cli.EXIT_USAGE
    assert "argument --timeout: must be a number of seconds, 0 or more" in capsys.readouterr().err


def test_a_job_that_ends_as_the_wait_times_out_is_printed_and_exits_as_ended(
    idle: Serve, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The job ends between the wait's last look (queued: no worker) and the job the command prints: it
    is cancelled there, through the service. The printed job and the exit code agree (1: cancelled)."""
    waited = SpineClient.wait

    def wait_then_cancel(client: SpineClient, job_id: Any, timeout: float | None = None) -> Any:
        try:
            return waited(client, job_id, timeout)
        except WaitTimeout:
            assert idle.client.post(f"/v1/jobs/{job_id}/cancel").json()["status"] == "cancelled"
            raise

    monkeypatch.setattr(SpineClient, "wait", wait_then_cancel)
    (tmp_path / "p.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    code = cli.main(["submit", str(tmp_path / "p.json"), "--timeout", "0", *_argv(idle)])
    captured = capsys.readouterr()
    assert json.loads(captured.out)["status"] == "cancelled"
    assert code == cli.EXIT_JOB_FAILED, captured.err
    assert "still queued" not in captured.err and "cancelled" in captured.err


def test_a_service_that_stops_answering_ends_the_wait_by_its_timeout(
    idle: Serve, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`spine serve` is stopped (SIGSTOP: connections are accepted, nothing answers) once the job is made:
    the polls' retries end with `--timeout`, not after every retry's request timeout and backoff
    (4 tries of 5 s here), with exit 4 and the last error."""
    submitted = SpineClient.submit

    def submit_then_stall(client: SpineClient, payload: Any, **kwargs: Any) -> Any:
        job = submitted(client, payload, **kwargs)
        os.kill(idle.proc.pid, signal.SIGSTOP)
        return job

    monkeypatch.setattr(SpineClient, "submit", submit_then_stall)
    (tmp_path / "p.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    timeout_s = 2.0
    started = time.monotonic()
    try:
        code = cli.main(["submit", str(tmp_path / "p.json"), "--timeout", str(timeout_s), "--request-timeout", "5",
                         "--retries", "3", *_argv(idle)])  # fmt: skip
    finally:
        os.kill(idle.proc.pid, signal.SIGCONT)
    took = time.monotonic() - started
    err = capsys.readouterr().err
    assert code == cli.EXIT_SERVER and "ReadTimeout" in err, err
    made = re.search(r"^spine: note: job (\S+) was made and goes on", err, flags=re.M)  # its only trace
    assert made and idle.client.get(f"/v1/jobs/{made.group(1)}").json()["status"] == "queued", err
    # the timeout, one last look of at most LAST_LOOK_S, and 2 s for the submission and a loaded machine
    assert took < timeout_s + LAST_LOOK_S + 2.0, took


def test_a_failed_job_says_why_on_stderr(serve: Serve, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "p.json").write_text(json.dumps(engine_refused_payload()), encoding="utf-8")
    assert cli.main(["submit", str(tmp_path / "p.json"), "--timeout", "60", *_argv(serve)]) == cli.EXIT_JOB_FAILED
    captured = capsys.readouterr()
    job = json.loads(captured.out)
    assert job["status"] == "failed"
    lines = captured.err.splitlines()
    assert lines[0].startswith(f"spine: error: job {job['id']} failed: ")
    assert [line.split(":")[1].strip() for line in lines[1:]] == [e["path"] for e in job["error"]["errors"]]


# ------------------------------------------------------------------ submit-dir


def test_a_summary_that_cannot_be_written_is_refused_before_any_job(
    serve: Serve, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "a.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    before = _job_count(serve)
    summary = tmp_path / "missing" / "summary.csv"
    argv = ["submit-dir", str(tmp_path), "--summary", str(summary), "--no-progress", *_argv(serve)]
    assert cli.main(argv) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert err == f"spine: error: cannot write the summary {summary}: No such file or directory\n"
    assert _job_count(serve) == before


def test_a_batch_over_the_body_limit_is_halved_and_only_the_payload_too_large_rejected(
    serve: Serve, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for name in ("a", "c"):
        (tmp_path / f"{name}.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    big = {**spine_payload(), "note": "x" * (2 * BATCH_LIMIT)}  # too large alone, whatever it holds
    (tmp_path / "b.json").write_text(json.dumps(big), encoding="utf-8")
    argv = ["submit-dir", str(tmp_path), "--no-wait", "--json", "--no-progress", "--run-key", uuid.uuid4().hex]
    assert cli.main([*argv, *_argv(serve)]) == cli.EXIT_USAGE  # one file rejected
    outcome = json.loads(capsys.readouterr().out)
    rows = {row["file"]: row for row in outcome["files"]}
    assert rows["a.json"]["status"] == rows["c.json"]["status"] == "queued"
    assert rows["b.json"]["status"] == "rejected" and rows["b.json"]["problem_type"] == "payload-too-large"
    assert not any(serve.client.get(f"/v1/jobs/{rows[n]['job_id']}").is_error for n in ("a.json", "c.json"))


def test_a_run_cut_short_names_its_run_key_and_the_rerun_makes_no_job_twice(
    idle: Serve, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`spine serve` stops answering (SIGSTOP) once the jobs are made, so the wait ends with exit 4; the
    run key, random when not given, is on stderr, and the rerun with it finds the same jobs."""
    for name in ("a", "b"):
        (tmp_path / f"{name}.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    submitted = SpineClient.submit_batch

    def submit_then_stall(client: SpineClient, payloads: Any, **kwargs: Any) -> Any:
        batch = submitted(client, payloads, **kwargs)
        os.kill(idle.proc.pid, signal.SIGSTOP)
        return batch

    argv = ["submit-dir", str(tmp_path), "--no-progress", "--json", *_argv(idle)]
    with monkeypatch.context() as patched:
        patched.setattr(SpineClient, "submit_batch", submit_then_stall)
        try:
            code = cli.main([*argv, "--request-timeout", "1", "--retries", "0"])
        finally:
            os.kill(idle.proc.pid, signal.SIGCONT)
    err = capsys.readouterr().err
    assert code == cli.EXIT_SERVER, err
    found = re.search(r"^spine: note: rerun with --run-key (\S+) ", err, flags=re.M)
    assert found, err
    made = _job_count(idle)
    assert cli.main([*argv, "--no-wait", "--run-key", found.group(1)]) == cli.EXIT_OK
    assert {row["status"] for row in json.loads(capsys.readouterr().out)["files"]} == {"queued"}
    assert _job_count(idle) == made


# ------------------------------------------------------------------ what a server says


class _Garbled(http.server.BaseHTTPRequestHandler):
    def do_GET(self) -> None:
        body = b"\x1b[2J\x1b[31mproxy down\r\nreally\x07"  # clear screen, red, a second line, a bell
        self.send_response(500)
        self.send_header("content-type", "text/plain")
        self.send_header("content-length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *_: Any) -> None:
        pass


def test_a_servers_control_characters_never_reach_the_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    httpd = http.server.HTTPServer(("127.0.0.1", 0), _Garbled)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{httpd.server_address[1]}"
        assert cli.main(["list", "--url", url, "--api-key", "k", "--retries", "0"]) == cli.EXIT_SERVER
    finally:
        httpd.shutdown()
        httpd.server_close()
    err = capsys.readouterr().err
    assert err == "spine: error: 500 Internal Server Error: \\x1b[2J\\x1b[31mproxy down\\x0d\\x0areally\\x07\n"


# ------------------------------------------------------------------ what the commands print


@pytest.fixture(scope="module")
def cut_film(serve: Serve) -> dict[str, Any]:
    """A succeeded job whose PA film shows T1–T8 only (T1 and L5 given): its frontal Cobb angles depend on
    levels no landmark shows, so ``fit.unreliable`` lists ``cobb`` (docs/measures.md, "What the input
    does not determine"), and with no lateral film its kyphosis and lordosis come from the prior."""
    payload = spine_payload(curve_mm=30.0)
    payload["pa"]["landmarks"] = payload["pa"]["landmarks"][: LEVELS.index("T8") + 1]
    job = serve.wait(serve.client.post("/v1/jobs", json=payload).json()["id"])
    assert job["status"] == "succeeded", job["error"]
    assert "cobb" in job["result"]["fit"]["unreliable"], job["result"]["fit"]
    return job


def _major(job: dict[str, Any]) -> dict[str, Any]:
    return next(c for c in job["result"]["measures"]["cobb"] if c["major"])


def _marks(job: dict[str, Any]) -> set[str]:
    """The columns of a job's row (summary.csv) that ``fit.unreliable`` makes the model's prior's."""
    unreliable = set(job["result"]["fit"]["unreliable"])
    return {c for c, q in (("major_cobb_deg", "cobb"), ("thoracic_kyphosis_t4_t12_deg", "kyphosis"),
                           ("lumbar_lordosis_l1_l5_deg", "lordosis")) if q in unreliable}  # fmt: skip


def test_measures_as_json_when_json_is_asked(
    serve: Serve, cut_film: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    """`get --measures --format json` printed CSV; `--measures` alone stays CSV (docs/client.md)."""
    job_id = cut_film["id"]
    assert cli.main(["get", job_id, "--measures", "--format", "json", *_argv(serve)]) == cli.EXIT_OK
    printed = json.loads(capsys.readouterr().out)
    assert cli.main(["get", job_id, "--measures", *_argv(serve)]) == cli.EXIT_OK
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert printed["job_id"] == job_id and [r["measure"] for r in printed["measures"]] == [r["measure"] for r in rows]
    for record, row in zip(printed["measures"], rows, strict=True):
        assert set(record) == set(row)
        assert record["value"] == float(row["value"]) and record["sd"] == (float(row["sd"]) if row["sd"] else None)
        assert record["model_estimate"] is (row["model_estimate"] == "model estimate")
    cobb = next(r for r in printed["measures"] if r["measure"] == "cobb_angle" and r["major"])
    assert (cobb["value"], cobb["sd"], cobb["model_estimate"]) == (_major(cut_film)["angle_deg"],
                                                                   _major(cut_film)["angle_sd_deg"], True)  # fmt: skip


def test_version_prints_the_packages_version(capsys: pytest.CaptureFixture[str]) -> None:
    """`spine --version` was a usage error (exit 2, "COMMAND required"); it prints the version, exit 0:
    the client's (spine_client/pyproject.toml) and the service's command's (pyproject.toml, installed)."""
    with pytest.raises(SystemExit) as stopped:
        cli.main(["--version"])
    assert stopped.value.code == 0
    assert capsys.readouterr().out == f"spine {spine_client.__version__}\n"
    declared = tomllib.loads((ROOT / "spine_client" / "pyproject.toml").read_text())["project"]["version"]
    assert spine_client.__version__ == declared
    done = subprocess.run([sys.executable, "-m", "services.cli", "--version"], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)  # fmt: skip
    assert (done.returncode, done.stdout) == (0, f"spine {metadata.version('spine-reconstruction')}\n"), done.stderr


def test_a_url_that_is_not_the_services_base_exits_4_not_5(serve: Serve, capsys: pytest.CaptureFixture[str]) -> None:
    """A path added to the service's URL answers 404 ``route-not-found``: a wrong URL (exit 4, check
    --url), not a job that does not exist (exit 5, which a job id the service does not have still is)."""
    argv = ["--api-key", serve.api_key, "--retries", "0"]
    assert cli.main(["list", "--url", f"{serve.base}/docs", *argv]) == cli.EXIT_SERVER
    err = capsys.readouterr().err
    assert "route-not-found" not in err and "check --url" in err, err
    assert cli.main(["get", str(uuid.uuid4()), "--url", f"{serve.base}/docs", *argv]) == cli.EXIT_SERVER
    assert "check --url" in capsys.readouterr().err
    assert cli.main(["get", str(uuid.uuid4()), "--url", serve.base, *argv]) == cli.EXIT_NOT_FOUND
    assert "check --url" not in capsys.readouterr().err
    with SpineClient(f"{serve.base}/docs", serve.api_key, retries=0) as client, pytest.raises(RouteNotFound) as wrong:
        client.list()
    assert not isinstance(wrong.value, NotFound) and wrong.value.kind == "route-not-found"


LIST_CSV_BEFORE = ["job_id", "status", "created_at", "finished_at", "major_cobb_deg", "major_upper", "major_lower",
                   "problem_type"]  # fmt: skip
"""`spine list --format csv`'s columns before the SD and the mark: a script's contract, kept in place."""
SUMMARY_BEFORE = ["file", "job_id", "status", "major_cobb_deg", "major_upper", "major_lower", "major_apex",
                  "major_convexity", "thoracic_kyphosis_t4_t12_deg", "lumbar_lordosis_l1_l5_deg",
                  "mean_registration_error_mm", "problem_type", "detail"]  # fmt: skip
"""summary.csv's columns before the SDs and the mark: a script's contract, kept in place."""


def test_list_gives_the_major_cobb_angle_with_its_sd_and_mark(
    serve: Serve, succeeded: str, cut_film: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    full = serve.client.get(f"/v1/jobs/{succeeded}").json()
    assert cli.main(["list", "--format", "csv", "--limit", "500", *_argv(serve)]) == cli.EXIT_OK
    out = capsys.readouterr().out
    header = out.splitlines()[0].split(",")
    assert header[: len(LIST_CSV_BEFORE)] == LIST_CSV_BEFORE and header == tables.LIST_COLUMNS
    rows = {r["job_id"]: r for r in csv.DictReader(io.StringIO(out))}
    for job in (cut_film, full):
        row = rows[job["id"]]
        assert float(row["major_cobb_sd_deg"]) == _major(job)["angle_sd_deg"]
        assert set(filter(None, row["model_estimate"].split(";"))) == _marks(job) & {"major_cobb_deg"}
    assert rows[cut_film["id"]]["model_estimate"] == "major_cobb_deg"  # the film shows T1-T8 only

    assert cli.main(["list", "--limit", "500", *_argv(serve)]) == cli.EXIT_OK
    table = capsys.readouterr().out
    major = _major(cut_film)
    assert f"{major['angle_deg']:.1f} ± {major['angle_sd_deg']:.1f} (model estimate)" in table, table


def test_get_csv_marks_the_frontal_tilts_when_the_cobb_angles_are_the_priors(
    serve: Serve, cut_film: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["get", cut_film["id"], "--format", "csv", *_argv(serve)]) == cli.EXIT_OK
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert all("frontal_tilt_deg" in r["model_estimate"].split(";") for r in rows), rows[0]["model_estimate"]


def test_the_summary_gives_each_angle_with_its_sd_and_mark(
    serve: Serve, cut_film: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "cut.json").write_text(json.dumps(cut_film["payload"]), encoding="utf-8")
    (tmp_path / "full.json").write_text(json.dumps(spine_payload()), encoding="utf-8")
    argv = ["submit-dir", str(tmp_path), "--no-progress", "--timeout", "120", *_argv(serve)]
    assert cli.main(argv) == cli.EXIT_OK, capsys.readouterr().err
    summary = (tmp_path / "summary.csv").read_text(encoding="utf-8")
    header = summary.splitlines()[0].split(",")
    assert header[: len(SUMMARY_BEFORE)] == SUMMARY_BEFORE and header == tables.SUMMARY_COLUMNS
    for row in csv.DictReader(io.StringIO(summary)):
        job = serve.client.get(f"/v1/jobs/{row['job_id']}").json()
        measures = job["result"]["measures"]
        assert float(row["major_cobb_sd_deg"]) == _major(job)["angle_sd_deg"]
        for name in ("thoracic_kyphosis_t4_t12", "lumbar_lordosis_l1_l5"):
            assert float(row[f"{name}_sd_deg"]) == measures[f"{name}_sd_deg"]
        assert set(filter(None, row["model_estimate"].split(";"))) == _marks(job)
        if row["file"] == "cut.json":
            assert "major_cobb_deg" in row["model_estimate"].split(";")


# ------------------------------------------------------------------ --help and docs/client.md


def _subcommands() -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize("command", sorted(_subcommands()))
def test_help_shows_the_values_docs_client_md_names(command: str) -> None:
    """Each ``[--option VALUE]`` of the command's rows in docs/client.md's table, and its positional
    (``ID``, ``DIR``, ``FILE``), reads the same in ``spine COMMAND --help``."""
    usage = " ".join(_subcommands()[command].format_usage().split())
    rows = re.findall(rf"^\| `spine {re.escape(command)}( [^`]*)?`", CLIENT_DOC.read_text(), flags=re.M)
    documented = {m for row in rows for m in re.findall(r"\[(--[a-z-]+ [A-Z][A-Za-z.]*)\]", row)}
    missing = sorted(d for d in documented if f"[{d}]" not in usage)
    assert not missing, f"spine {command} --help: {usage}"
    positionals = {row.split()[0] for row in rows if re.fullmatch(r"[A-Z]+", row.split()[0] if row.strip() else "")}
    assert all(re.search(rf" {p}$", usage) for p in positionals - {"CSV"}), (positionals, usage)
