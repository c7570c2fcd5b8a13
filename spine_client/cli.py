"""The client's command line: ``spine submit | submit-dir | get | list | cancel | store | fhir``.

Exit codes (docs/client.md), for scripts:

    0  success (with --wait / submit-dir: every job succeeded)
    1  a job failed or was cancelled
    2  usage error or invalid input (bad arguments, unreadable JSON, a payload the service refused)
    3  timeout: a job did not finish within --timeout
    4  server or network error (5xx, 429 or no answer, still after the retries), or a URL that is not
       the service's (an answer not of its API; a 404 route-not-found: the service has no such path)
    5  not found (no such job)
    6  authentication or authorisation refused (401, 403: check --api-key / SPINE_API_KEY)
    7  conflict with the job's state (cancel of a finished job, CSV or FHIR of a job without result,
       an Idempotency-Key reused with another body, store of a job whose results are being stored or
       are never stored)
  130  interrupted (Ctrl-C: SIGINT, 128 + 2, as a shell reports a command a signal ended)
  141  stdout closed by its reader (`| head -1`: SIGPIPE, 128 + 13); what was written stays written
"""

from __future__ import annotations

import argparse
import codecs
import json
import math
import os
import sys
import time
import traceback
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spine_client import __version__, optional, tables
from spine_client.client import API_KEY_ENV, DEFAULT_URL, URL_ENV, SpineClient, base_url_problem, service_url
from spine_client.errors import (
    ApiError,
    Conflict,
    Forbidden,
    InvalidRequest,
    NotFound,
    RouteNotFound,
    SpineError,
    Unauthorized,
    WaitTimeout,
)
from spine_client.landmarks import LandmarkCsvError, payload_by_reference

EXIT_OK = 0
EXIT_JOB_FAILED = 1
EXIT_USAGE = 2
EXIT_TIMEOUT = 3
EXIT_SERVER = 4
EXIT_NOT_FOUND = 5
EXIT_AUTH = 6
EXIT_CONFLICT = 7
EXIT_INTERRUPTED = 130
"""128 + SIGINT (2): what a shell reports for a command Ctrl-C ended."""
EXIT_BROKEN_PIPE = 141
"""128 + SIGPIPE (13): what a shell reports for a command whose reader closed the pipe (``| head -1``)."""
EXIT_INTERNAL = 70
"""An error of the client itself, a bug (sysexits.h ``EX_SOFTWARE``): apart from 1, a job that failed."""

FINAL = ("succeeded", "failed", "cancelled")


class UsageError(Exception):
    """Bad input on the command line side (exit 2)."""


def exit_code(exc: BaseException) -> int:
    if isinstance(exc, RouteNotFound):  # a 404 of the URL, not of a job: check --url
        return EXIT_SERVER
    if isinstance(exc, WaitTimeout):
        return EXIT_TIMEOUT
    if isinstance(exc, NotFound):
        return EXIT_NOT_FOUND
    if isinstance(exc, (Unauthorized, Forbidden)):
        return EXIT_AUTH
    if isinstance(exc, Conflict):
        return EXIT_CONFLICT
    if isinstance(exc, (InvalidRequest, UsageError)):
        return EXIT_USAGE
    return EXIT_SERVER


_CONTROLS = {c: f"\\x{c:02x}" for c in (*range(0x20), 0x7F, *range(0x80, 0xA0))}
"""C0 and C1 control characters and DEL, written as ``\\xNN``: a server's or a file's text in a message
can neither move the terminal's cursor, recolour it, nor break the message's one line."""


def _err(message: str) -> None:
    sys.stderr.write(f"spine: {message.translate(_CONTROLS)}\n")


def _report(exc: BaseException) -> None:
    if isinstance(exc, ApiError):
        _err(f"error: {exc}")
        for e in exc.problem.errors or []:
            _err(f"  {e.path or '(body)'}: {e.msg}")
        if isinstance(exc, RouteNotFound):
            _err(f"  the service has no such path: check --url (or ${URL_ENV}), the service's base URL, "
                 f"such as {DEFAULT_URL}")  # fmt: skip
    else:
        _err(f"error: {exc}")


def _print_json(body: Any) -> None:
    sys.stdout.write(json.dumps(body, indent=2, ensure_ascii=False) + "\n")


def _finite(text: str) -> float:
    """A JSON number with a fraction or exponent, refused beyond a double's range (``1e400``): RFC 8259 §6
    lets a parser limit the range, and the service's JSON has no infinity."""
    number = float(text)
    if not math.isfinite(number):
        raise ValueError(f"the number {text} is beyond a double's range")
    return number


def _not_json(constant: str) -> Any:
    """``NaN``, ``Infinity``, ``-Infinity``: Python's extensions, not JSON (RFC 8259 §6 has no such number)."""
    raise ValueError(f"{constant} is not a JSON number")


def _load_json(path: str) -> Any:
    """The JSON document of a file, or of stdin for ``-``: UTF-8, a leading byte-order mark skipped (RFC
    8259 §8.1 lets a parser ignore it; Windows tools write it). ``UsageError`` naming the file and why:
    unreadable, empty, not UTF-8, not JSON (where), a number JSON does not have, nesting too deep."""
    name = "stdin" if path == "-" else path
    try:
        data = sys.stdin.buffer.read() if path == "-" else Path(path).read_bytes()
    except OSError as exc:
        raise UsageError(f"cannot read {path}: {exc.strerror or exc}") from None
    skipped = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        text = data[skipped:].decode("utf-8")
    except UnicodeDecodeError as exc:
        at = skipped + exc.start
        raise UsageError(f"{name} is not UTF-8 text, as JSON is (RFC 8259 §8.1): byte 0x{data[at]:02x} "
                         f"at offset {at}") from None  # fmt: skip
    if not text.strip():
        raise UsageError(f"{name} is empty: a JSON document was expected")
    try:
        return json.loads(text, parse_float=_finite, parse_constant=_not_json)
    except json.JSONDecodeError as exc:
        raise UsageError(f"{name} is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except ValueError as exc:  # _finite, _not_json, an integer of more digits than int() takes
        raise UsageError(f"{name} is not valid JSON: {exc}") from None
    except RecursionError:
        raise UsageError(f"{name} nests arrays or objects deeper than this reader can follow "
                         f"(about {sys.getrecursionlimit()} levels)") from None  # fmt: skip


def _json_type(value: Any) -> str:
    """The JSON type of a parsed value, as RFC 8259 §3 names them."""
    if isinstance(value, bool):
        return "a boolean"
    names = {dict: "an object", list: "an array", str: "a string", int: "a number", float: "a number"}
    return "null" if value is None else names.get(type(value), type(value).__name__)


def _client(args: argparse.Namespace) -> SpineClient:
    url = service_url(args.url)
    problem = base_url_problem(url)
    if problem is not None:
        option = "--url" if args.url else f"${URL_ENV}"
        raise UsageError(f"{option} is not the service's URL: {problem}")
    return SpineClient(url, args.api_key, timeout=args.request_timeout, retries=args.retries)


def _retries(value: str) -> int:
    """``--retries``: a whole number, 0 or more."""
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, 0 or more, not {value!r}") from None
    if number < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more (0: no retry), not {number}")
    return number


def _wait_seconds(value: str) -> float:
    """``--timeout``: a number of seconds, 0 or more (0: look once, do not wait)."""
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, 0 or more, not {value!r}") from None
    if not (number >= 0 and math.isfinite(number)):
        raise argparse.ArgumentTypeError(f"must be a number of seconds, 0 or more, not {value}")
    return number


def _seconds(value: str) -> float:
    """``--request-timeout``: a number of seconds above 0."""
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds above 0, not {value!r}") from None
    if not (number > 0 and math.isfinite(number)):
        raise argparse.ArgumentTypeError(f"must be a number of seconds above 0, not {value}")
    return number


def _job_exit(job: dict[str, Any]) -> int:
    """Exit 1 for a failed or cancelled job, saying why on stderr (the job's problem and its fields), else 0."""
    status = job.get("status")
    if status not in ("failed", "cancelled"):
        return EXIT_OK
    error = job.get("error") or {}
    _err(f"error: job {job.get('id')} {status}" + (f": {error['detail']}" if error.get("detail") else ""))
    for e in error.get("errors") or []:
        _err(f"  {e.get('path') or '(body)'}: {e.get('msg')}")
    return EXIT_JOB_FAILED


# ------------------------------------------------------------------ commands


def _dicom_payload(args: argparse.Namespace) -> dict[str, Any]:
    """The payload of ``spine submit --pa-dicom`` (landmarks CSV + headers read here, sent as the job's
    ``dicom`` block, so that the job keeps its film as a PACS job does; conflicts to stderr) or of
    ``--study-instance-uid`` (landmarks CSV + UIDs: the service reads the headers)."""
    if args.base == "-" and args.payload == "-":
        raise UsageError("FILE and --base cannot both be - (stdin): give one of them as a file")
    base = _load_json(args.base) if args.base else {}
    if not isinstance(base, dict):
        raise UsageError(f"--base {args.base}: a payload is a JSON object, not {_json_type(base)}")
    for member in ("pa", "lateral", "study"):  # merged with what the CSV and the headers give
        if base.get(member) is not None and not isinstance(base[member], dict):
            raise UsageError(f"--base {args.base}: {member} is a JSON object, not {_json_type(base[member])}")
    source = sys.stdin.buffer if args.payload == "-" else args.payload
    name = "stdin" if args.payload == "-" else args.payload
    if args.study_instance_uid:
        if not args.pa_sop_instance_uid:
            raise UsageError("--study-instance-uid needs --pa-sop-instance-uid")
        try:
            return payload_by_reference(source, args.study_instance_uid, args.pa_sop_instance_uid,
                                        args.lateral_sop_instance_uid, units=args.units, base=base)  # fmt: skip
        except LandmarkCsvError as exc:
            raise UsageError(f"{name}: {exc}") from None
        except OSError as exc:
            raise UsageError(f"cannot read {exc.filename}: {exc.strerror or exc}") from None
    try:
        dicom_input = optional.dicom_input()
    except optional.MissingExtra as exc:
        raise UsageError(str(exc)) from None
    try:
        payload, provenance = dicom_input.payload_from_dicom(source, args.pa_dicom, args.lateral_dicom,
                                                             units=args.units, base=base)  # fmt: skip
    except LandmarkCsvError as exc:
        raise UsageError(f"{name}: {exc}") from None
    except dicom_input.DicomError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot read {exc.filename}: {exc.strerror or exc}") from None
    used = {(r["field"], json.dumps(r["value"])) for r in provenance["study"] if r["used"]}
    for c in provenance["conflicts"]:
        if (c["field"], json.dumps(c["header"])) in used:  # a study value that is the film's (merge.FILM_VALUES)
            _err(f"warning: {c['field']}: the header's {c['attribute']} {c['header']!r} is used, as the film's "
                 f"study has it; the payload's {c['payload']!r} is not")  # fmt: skip
            continue
        _err(f"warning: {c['field']}: the payload's {c['payload']!r} is kept; the header's {c['attribute']} "
             f"says {c['header']!r}")  # fmt: skip
    return {**payload, "dicom": provenance}


def cmd_submit(args: argparse.Namespace) -> int:
    if args.lateral_dicom and not args.pa_dicom:
        raise UsageError("--lateral-dicom needs --pa-dicom")
    if args.pa_dicom and args.study_instance_uid:
        raise UsageError("--pa-dicom and --study-instance-uid exclude each other (a file, or the PACS by UID)")
    csv_mode = bool(args.pa_dicom or args.study_instance_uid)
    if args.base and not csv_mode:
        raise UsageError("--base needs --pa-dicom or --study-instance-uid (without them, FILE is the payload)")
    payload = _dicom_payload(args) if csv_mode else _load_json(args.payload)
    if args.print_payload:
        _print_json(payload)
        return EXIT_OK
    with _client(args) as client:
        job = client.submit(payload, idempotency_key=args.idempotency_key)
        if not (args.wait or args.timeout is not None):
            _print_json(job.model_dump(mode="json", exclude_none=True))
            return EXIT_OK
        try:
            client.wait(job.id, args.timeout)
        except WaitTimeout:
            body = client.get_json(job.id)
            if body.get("status") not in FINAL:  # else it ended since the last look: printed as ended, below
                _print_json(body)
                raise
        except (SpineError, KeyboardInterrupt):  # the job goes on: its id is all a script has to find it
            _err(f"note: job {job.id} was made and goes on without this wait (spine get {job.id})")
            raise
        else:
            body = client.get_json(job.id)
    _print_json(body)
    return _job_exit(body)


def cmd_get(args: argparse.Namespace) -> int:
    if args.sr or args.figure_dcm:
        if args.sr == "-" and args.figure_dcm == "-":
            raise UsageError("--sr and --figure-dcm cannot both be - (stdout): give one of them as a file")
        with _client(args) as client:
            for path, fetch in ((args.sr, client.sr), (args.figure_dcm, client.figure_dicom)):
                if path:
                    data = fetch(args.job_id)
                    if path == "-":
                        sys.stdout.flush()
                        sys.stdout.buffer.write(data)
                        continue
                    try:
                        Path(path).write_bytes(data)
                    except OSError as exc:
                        raise UsageError(f"cannot write {path}: {exc.strerror or exc}") from None
                    _err(f"wrote {path} ({len(data)} bytes)")
        return EXIT_OK
    output = args.format or ("csv" if args.measures else "json")  # --measures alone: CSV, as it always was
    with _client(args) as client:
        body = client.get_json(args.job_id)
    if output == "json" and not args.measures:
        _print_json(body)
        return EXIT_OK
    status = body.get("status")
    if status != "succeeded" or not body.get("result"):
        what = "its measures" if args.measures else "as CSV"
        _err(f"error: job {args.job_id} is {status}: there is no result to write {what}")
        return EXIT_JOB_FAILED if status in ("failed", "cancelled") else EXIT_CONFLICT
    result = body["result"]
    if output == "json":
        _print_json({"job_id": body.get("id"), "measures": tables.measure_records(result)})
    else:
        sys.stdout.write(tables.measures_csv(result) if args.measures else tables.vertebrae_csv(result))
    return EXIT_OK


def cmd_list(args: argparse.Namespace) -> int:
    filters = {"status": args.status, "created_after": args.created_after, "created_before": args.created_before,
               "study_instance_uid": args.study_instance_uid, "accession_number": args.accession_number,
               "patient_id": args.patient_id}  # fmt: skip
    with _client(args) as client:
        if args.all:
            jobs = [j.model_dump(mode="json") for j in client.iter_jobs(**filters)]
            next_cursor = None
        else:
            page = client.list(limit=args.limit, cursor=args.cursor, **filters)
            jobs, next_cursor = [j.model_dump(mode="json") for j in page.jobs], page.next_cursor
    if args.format == "json":
        _print_json({"jobs": jobs, "next_cursor": next_cursor})
        return EXIT_OK
    rows = [tables.list_row(j) for j in jobs]
    if args.format == "csv":
        sys.stdout.write(tables.list_csv(rows))
        return EXIT_OK
    more = f" (more: --cursor {next_cursor})" if next_cursor else ""
    cells = [tables.list_cells(row) for row in rows]
    try:
        optional.print_table(tables.LIST_TABLE_COLUMNS, cells, f"{len(rows)} jobs{more}",
                             width=None if sys.stdout.isatty() else 200)  # fmt: skip
    except SystemExit:  # rich's Console.on_broken_pipe: stdout's reader is gone, stdout already the null device
        return EXIT_BROKEN_PIPE
    return EXIT_OK


def cmd_cancel(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.cancel(args.job_id)
    _print_json(job.model_dump(mode="json", exclude_none=True))
    return EXIT_OK


def _store_line(job_id: str, attempt: dict[str, Any] | None) -> str:
    """``spine store``'s line: the job's last STOW-RS entry in words (the request's, as the service answers
    it: its run's first attempt, due)."""
    if attempt is None:
        return f"job {job_id}: no STOW-RS attempt listed"
    number = attempt.get("attempt")
    if attempt.get("requested_by"):
        due = attempt.get("next_attempt_at") or attempt.get("attempted_at")
        note = f"; {attempt['error']}" if attempt.get("error") else ""
        return (f"job {job_id}: STOW-RS attempt {number} due at {due}, requested by {attempt['requested_by']}"
                f"{note}")  # fmt: skip
    if attempt.get("ok"):
        return f"job {job_id}: STOW-RS attempt {number} stored {len(attempt.get('stored') or [])} instances"
    return f"job {job_id}: STOW-RS attempt {number} failed: {attempt.get('problem_type')}: {attempt.get('error')}"


def cmd_store(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.store_dicom(args.job_id)
    body = job.model_dump(mode="json")
    attempt = (body.get("dicom_stores") or [None])[-1]
    if args.format == "json":
        _print_json({"job_id": body.get("id"), "dicom_store": attempt})
    else:
        sys.stdout.write(_store_line(str(body.get("id")), attempt).translate(_CONTROLS) + "\n")
    return EXIT_OK


def cmd_fhir(args: argparse.Namespace) -> int:
    with _client(args) as client:
        bundle = client.fhir(args.job_id)
    _print_json(bundle)
    return EXIT_OK


def cmd_submit_dir(args: argparse.Namespace) -> int:
    folder = Path(args.directory)
    if not folder.is_dir():
        raise UsageError(f"{folder} is not a folder")
    summary_path = Path(args.summary) if args.summary else folder / "summary.csv"
    files = sorted(p for p in folder.glob("*.json") if p.is_file())
    if not files:
        raise UsageError(f"{folder} has no *.json file")
    try:  # before any job is made: a summary that cannot be written would lose every outcome at the end
        with summary_path.open("a", encoding="utf-8"):
            pass
    except OSError as exc:
        raise UsageError(f"cannot write the summary {summary_path}: {exc.strerror or exc}") from None
    rows: dict[str, dict[str, Any]] = {}
    payloads: list[Any] = []
    names: list[str] = []
    for path in files:
        try:
            payloads.append(_load_json(str(path)))
            names.append(path.name)
        except UsageError as exc:
            rows[path.name] = tables.summary_row(path.name, None, status="rejected",
                                                 problem={"type": "malformed-json", "detail": str(exc)})  # fmt: skip
    pending: dict[str, str] = {}  # job id -> file
    timed_out = False
    try:
        with _client(args) as client, optional.progress(disable=args.no_progress) as progress:
            submitting = progress.add_task("submitting", total=len(payloads))
            for start in range(0, len(payloads), args.batch_size):
                part = payloads[start : start + args.batch_size]
                key = f"{args.run_key}.{start}"
                batch = client.submit_batch(part, idempotency_key=key, chunk=args.batch_size)
                for entry in batch.results:
                    name = names[start + entry.index]
                    if entry.job is not None:
                        pending[str(entry.job.id)] = name
                        rows[name] = tables.summary_row(name, entry.job.model_dump(mode="json"))
                    else:
                        problem = entry.problem.model_dump(mode="json") if entry.problem else None
                        rows[name] = tables.summary_row(name, None, status="rejected", problem=problem)
                progress.advance(submitting, len(part))
            if not args.no_wait:
                waiting = progress.add_task("waiting", total=len(pending))
                deadline = None if args.timeout is None else time.monotonic() + args.timeout
                interval = 0.2
                while pending:
                    for job_id in list(pending):
                        body = client.get_json(job_id, deadline=deadline)
                        if body.get("status") in FINAL:
                            name = pending.pop(job_id)
                            rows[name] = tables.summary_row(name, body)
                            progress.advance(waiting)
                    if not pending:
                        break
                    if deadline is not None and time.monotonic() >= deadline:
                        timed_out = True
                        for job_id, name in pending.items():
                            rows[name]["status"] = "timeout"
                            rows[name]["detail"] = f"still not finished after {args.timeout:g} s (job {job_id})"
                        break
                    time.sleep(interval)
                    interval = min(2.0, interval * 1.5)
    except (SpineError, KeyboardInterrupt):
        if payloads:  # jobs may have been made: the same run key finds them again instead of making more
            _err(f"note: rerun with --run-key {args.run_key} to pick up the jobs this run made, none made twice")
        raise
    ordered = [rows[p.name] for p in files]
    summary_path.write_text(tables.summary_csv(ordered), encoding="utf-8")
    counts: dict[str, int] = {}
    for row in ordered:
        counts[str(row["status"])] = counts.get(str(row["status"]), 0) + 1
    if args.json:  # one JSON document: the counts, the summary's path and one row per file
        json.dump({"counts": dict(sorted(counts.items())), "summary": str(summary_path),
                   "files": [{c: row.get(c) for c in tables.SUMMARY_COLUMNS} for row in ordered]},
                  sys.stdout, indent=2)  # fmt: skip
        sys.stdout.write("\n")
    else:
        sys.stdout.write(", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + f"; summary: {summary_path}\n")
    statuses = set(counts)
    if timed_out:
        return EXIT_TIMEOUT
    if "rejected" in statuses:
        return EXIT_USAGE
    if statuses & {"failed", "cancelled"}:
        return EXIT_JOB_FAILED
    return EXIT_OK


# ------------------------------------------------------------------ parser


def build_parser() -> argparse.ArgumentParser:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--url", default=None, help=f"service URL (default ${URL_ENV}, else {DEFAULT_URL})")
    common.add_argument("--api-key", default=None, metavar="KEY",
                        help=f"API key, sent as a Bearer token (default ${API_KEY_ENV})")  # fmt: skip
    common.add_argument("--retries", type=_retries, default=5, metavar="N",
                        help="retries of a request on network errors, 429, 5xx (0 or more; default 5)")  # fmt: skip
    common.add_argument("--request-timeout", type=_seconds, default=30.0, metavar="S",
                        help="seconds per HTTP request (above 0; default 30)")  # fmt: skip

    parser = argparse.ArgumentParser(
        prog="spine", description="Client of the spine reconstruction service.",
        epilog="exit codes: 0 ok, 1 job failed/cancelled, 2 usage/invalid input, 3 timeout, 4 server/network error, "
        "5 not found, 6 auth refused, 7 conflict with the job's state, 130 interrupted (Ctrl-C), 141 stdout closed "
        "(| head)",
    )  # fmt: skip
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}",
                        help="print the client's version and exit")  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("submit", parents=[common], help="submit a job payload (JSON file, - for stdin), or a "
                       "landmark CSV with --pa-dicom")  # fmt: skip
    p.add_argument("payload", metavar="FILE", help="payload JSON; with --pa-dicom or --study-instance-uid, the "
                   "landmark CSV (level,column,row[,view]); - reads stdin")  # fmt: skip
    p.add_argument("--pa-dicom", default=None, metavar="DCM", help="the PA radiograph's DICOM file: pixel spacing, "
                   "orientation, geometry and study are read from its header here")  # fmt: skip
    p.add_argument("--lateral-dicom", default=None, metavar="DCM", help="the lateral radiograph's DICOM file")
    p.add_argument("--study-instance-uid", default=None, metavar="UID", help="instead of --pa-dicom: the images "
                   "by UID, whose headers the service reads from its PACS (SPINE_DICOMWEB_URL)")  # fmt: skip
    p.add_argument("--pa-sop-instance-uid", default=None, metavar="UID", help="the PA image's SOP Instance UID")
    p.add_argument("--lateral-sop-instance-uid", default=None, metavar="UID", help="the lateral image's")
    p.add_argument("--units", choices=["px", "mm"], default="px", help="units of the CSV's coordinates with "
                   "--pa-dicom or --study-instance-uid (default px: image pixels)")  # fmt: skip
    p.add_argument("--base", default=None, metavar="JSON", help="with a CSV: a payload whose values win "
                   "over the headers' (options, boundary, a spacing typed in); - reads stdin")  # fmt: skip
    p.add_argument("--print-payload", action="store_true", help="print the payload instead of submitting it")
    p.add_argument("--wait", action="store_true", help="wait until the job ends and print it")
    p.add_argument("--timeout", type=_wait_seconds, default=None, metavar="S",
                   help="seconds to wait, 0 or more (implies --wait); exit 3 past it")  # fmt: skip
    p.add_argument("--idempotency-key", default=None, metavar="K",
                   help="reuse to make a retried submission return the same job")  # fmt: skip
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("submit-dir", parents=[common], help="submit every *.json of a folder, wait, write a summary")
    p.add_argument("directory", metavar="DIR")
    p.add_argument("--timeout", type=_wait_seconds, default=3600.0, metavar="S",
                   help="seconds to wait for all jobs, 0 or more (default 3600)")  # fmt: skip
    p.add_argument("--summary", default=None, metavar="CSV", help="summary CSV to write (default DIR/summary.csv)")
    p.add_argument("--batch-size", type=int, default=500, metavar="N",
                   help="payloads per batch request (at most 1000)")  # fmt: skip
    p.add_argument("--no-wait", action="store_true", help="submit only; the summary lists the queued jobs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the outcome as JSON (counts, summary path, a row per file), not one line")  # fmt: skip
    p.add_argument("--run-key", default=None, metavar="K", help="Idempotency-Key prefix: rerun with the same "
                   "key after a crash and no job is made twice (default: random)")  # fmt: skip
    p.set_defaults(func=cmd_submit_dir)

    p = sub.add_parser("get", parents=[common], help="print a job (JSON), or its vertebrae or measures (CSV)")
    p.add_argument("job_id", metavar="ID")
    p.add_argument("--format", choices=["json", "csv"], default=None,
                   help="json: the job (the default), with --measures its measures; csv: the vertebrae, with "
                   "--measures the measures (the default with --measures)")  # fmt: skip
    p.add_argument("--measures", action="store_true", help="the measures instead of the job or the vertebrae")
    p.add_argument("--sr", default=None, metavar="OUT.dcm", help="write the result as a DICOM SR (TID 1500); "
                   "- writes it to stdout")  # fmt: skip
    p.add_argument("--figure-dcm", default=None, metavar="OUT.dcm", help="write the figure as a DICOM "
                   "Secondary Capture; - writes it to stdout")  # fmt: skip
    p.set_defaults(func=cmd_get)

    p = sub.add_parser("list", parents=[common], help="list jobs, newest first")
    statuses = ["queued", "running", *FINAL]
    p.add_argument("--status", action="append", choices=statuses, default=None, metavar="S",
                   help=f"jobs of this status ({', '.join(statuses)}); repeat for several")  # fmt: skip
    p.add_argument("--created-after", default=None, metavar="T", help="ISO 8601")
    p.add_argument("--created-before", default=None, metavar="T", help="ISO 8601")
    p.add_argument("--limit", type=int, default=20, metavar="N", help="jobs per page (default 20)")
    p.add_argument("--cursor", default=None, metavar="C", help="next_cursor of the previous page")
    p.add_argument("--all", action="store_true", help="every matching job, following the cursor")
    p.add_argument("--study-instance-uid", default=None, metavar="UID", help="jobs of this DICOM study")
    p.add_argument("--accession-number", default=None, metavar="A", help="jobs of this accession number")
    p.add_argument("--patient-id", default=None, metavar="P", help="jobs of this patient")
    p.add_argument("--format", choices=["table", "json", "csv"], default="table")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("cancel", parents=[common], help="cancel a queued or running job")
    p.add_argument("job_id", metavar="ID")
    p.set_defaults(func=cmd_cancel)

    p = sub.add_parser("store", parents=[common], help="store a succeeded job's results (SR, figure) in the "
                       "service's PACS again; print the new attempt")  # fmt: skip
    p.add_argument("job_id", metavar="ID")
    p.add_argument("--format", choices=["text", "json"], default="text",
                   help="text: one line (the default); json: the job's id and its last STOW-RS entry")  # fmt: skip
    p.set_defaults(func=cmd_store)

    p = sub.add_parser("fhir", parents=[common], help="print a succeeded job's measures as a FHIR R4 Bundle")
    p.add_argument("job_id", metavar="ID")
    p.set_defaults(func=cmd_fhir)
    return parser


def stdout_closed() -> int:
    """After a ``BrokenPipeError``: stdout's reader is gone (``| head -1``). Points stdout at the null
    device, so that the interpreter's last flush does not fail again, and returns the exit code a shell
    gives a command SIGPIPE ended (Python ignores SIGPIPE, so the write fails instead)."""
    with open(os.devnull, "wb") as devnull:
        os.dup2(devnull.fileno(), sys.stdout.fileno())
    return EXIT_BROKEN_PIPE


def main(argv: Sequence[str] | None = None) -> int:
    try:
        try:
            return _main(list(sys.argv[1:] if argv is None else argv))
        finally:  # here, where a closed pipe is still caught (also after --help)
            sys.stdout.flush()
    except (SpineError, UsageError) as exc:
        _report(exc)
        return exit_code(exc)
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        return stdout_closed()
    except Exception:  # a bug: its traceback for the report, and a code no script reads as a job's outcome
        traceback.print_exc()
        _err("internal error of the client (a bug; please report it with the traceback above)")
        return EXIT_INTERNAL


def _main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "run_key", "unset") is None:
        args.run_key = uuid.uuid4().hex
    if getattr(args, "batch_size", 1) < 1:
        _err("error: --batch-size must be at least 1")
        return EXIT_USAGE
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
