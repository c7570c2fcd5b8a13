"""The client's command line: ``spine submit | submit-dir | get | list | cancel | fhir``.

Exit codes (docs/client.md), for scripts:

    0  success (with --wait / submit-dir: every job succeeded)
    1  a job failed or was cancelled
    2  usage error or invalid input (bad arguments, unreadable JSON, a payload the service refused)
    3  timeout: a job did not finish within --timeout
    4  server or network error (5xx, 429 or no answer, still after the retries)
    5  not found (no such job)
    6  authentication or authorisation refused (401, 403: check --api-key / SPINE_API_KEY)
    7  conflict with the job's state (cancel of a finished job, CSV or FHIR of a job without result,
       an Idempotency-Key reused with another body)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spine_client import optional, tables
from spine_client.client import API_KEY_ENV, DEFAULT_URL, URL_ENV, SpineClient, base_url_problem, service_url
from spine_client.errors import (
    ApiError,
    Conflict,
    Forbidden,
    InvalidRequest,
    NotFound,
    ServiceUnreachable,
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

FINAL = ("succeeded", "failed", "cancelled")


class UsageError(Exception):
    """Bad input on the command line side (exit 2)."""


def exit_code(exc: BaseException) -> int:
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


def _err(message: str) -> None:
    sys.stderr.write(f"spine: {message}\n")


def _report(exc: BaseException) -> None:
    if isinstance(exc, ApiError):
        _err(f"error: {exc}")
        for e in exc.problem.errors or []:
            _err(f"  {e.path or '(body)'}: {e.msg}")
    else:
        _err(f"error: {exc}")


def _print_json(body: Any) -> None:
    sys.stdout.write(json.dumps(body, indent=2, ensure_ascii=False) + "\n")


def _load_json(path: str) -> Any:
    try:
        text = sys.stdin.read() if path == "-" else Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise UsageError(f"cannot read {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise UsageError(f"{path} is not UTF-8 text, as JSON is (RFC 8259 §8.1): byte 0x{exc.object[exc.start]:02x} "
                         f"at offset {exc.start}") from None  # fmt: skip
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise UsageError(f"{path} is not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None


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
    return EXIT_JOB_FAILED if job.get("status") in ("failed", "cancelled") else EXIT_OK


# ------------------------------------------------------------------ commands


def _dicom_payload(args: argparse.Namespace) -> dict[str, Any]:
    """The payload of ``spine submit --pa-dicom`` (landmarks CSV + headers read here, sent as the job's
    ``dicom`` block, so that the job keeps its film as a PACS job does; conflicts to stderr) or of
    ``--study-instance-uid`` (landmarks CSV + UIDs: the service reads the headers)."""
    base = _load_json(args.base) if args.base else {}
    if args.study_instance_uid:
        if not args.pa_sop_instance_uid:
            raise UsageError("--study-instance-uid needs --pa-sop-instance-uid")
        try:
            return payload_by_reference(args.payload, args.study_instance_uid, args.pa_sop_instance_uid,
                                        args.lateral_sop_instance_uid, units=args.units, base=base)  # fmt: skip
        except LandmarkCsvError as exc:
            raise UsageError(f"{args.payload}: {exc}") from None
        except OSError as exc:
            raise UsageError(f"cannot read {exc.filename}: {exc.strerror or exc}") from None
    try:
        dicom_input = optional.dicom_input()
    except optional.MissingExtra as exc:
        raise UsageError(str(exc)) from None
    try:
        payload, provenance = dicom_input.payload_from_dicom(args.payload, args.pa_dicom, args.lateral_dicom,
                                                             units=args.units, base=base)  # fmt: skip
    except LandmarkCsvError as exc:
        raise UsageError(f"{args.payload}: {exc}") from None
    except dicom_input.DicomError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot read {exc.filename}: {exc.strerror or exc}") from None
    for c in provenance["conflicts"]:
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
        except WaitTimeout as exc:
            _print_json(client.get_json(exc.job.id))
            raise
        body = client.get_json(job.id)
    _print_json(body)
    return _job_exit(body)


def cmd_get(args: argparse.Namespace) -> int:
    if args.sr or args.figure_dcm:
        with _client(args) as client:
            for path, fetch in ((args.sr, client.sr), (args.figure_dcm, client.figure_dicom)):
                if path:
                    data = fetch(args.job_id)
                    try:
                        Path(path).write_bytes(data)
                    except OSError as exc:
                        raise UsageError(f"cannot write {path}: {exc.strerror or exc}") from None
                    _err(f"wrote {path} ({len(data)} bytes)")
        return EXIT_OK
    with _client(args) as client:
        body = client.get_json(args.job_id)
    if args.format == "json" and not args.measures:
        _print_json(body)
        return EXIT_OK
    status = body.get("status")
    if status != "succeeded" or not body.get("result"):
        _err(f"error: job {args.job_id} is {status}: there is no result to write as CSV")
        return EXIT_JOB_FAILED if status in ("failed", "cancelled") else EXIT_CONFLICT
    result = body["result"]
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
    rows = [tables.summary_row("", j) for j in jobs]
    for row, job in zip(rows, jobs, strict=True):
        row.update(created_at=job["created_at"], finished_at=job.get("finished_at"))
    columns = ["job_id", "status", "created_at", "finished_at", "major_cobb_deg", "major_upper", "major_lower",
               "problem_type"]  # fmt: skip
    if args.format == "csv":
        sys.stdout.write(tables._csv(columns, rows))
        return EXIT_OK
    more = f" (more: --cursor {next_cursor})" if next_cursor else ""
    cells = [[("" if row.get(c) is None else f"{row[c]:.1f}" if isinstance(row[c], float) else str(row[c]))
              for c in columns] for row in rows]  # fmt: skip
    optional.print_table(columns, cells, f"{len(rows)} jobs{more}", width=None if sys.stdout.isatty() else 200)
    return EXIT_OK


def cmd_cancel(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.cancel(args.job_id)
    _print_json(job.model_dump(mode="json", exclude_none=True))
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
    with _client(args) as client, optional.progress(disable=args.no_progress) as progress:
        submitting = progress.add_task("submitting", total=len(payloads))
        for start in range(0, len(payloads), args.batch_size):
            part = payloads[start : start + args.batch_size]
            batch = client.submit_batch(part, idempotency_key=f"{args.run_key}.{start}", chunk=args.batch_size)
            for entry in batch.results:
                name = names[start + entry.index]
                if entry.job is not None:
                    pending[str(entry.job.id)] = name
                    rows[name] = tables.summary_row(name, entry.job.model_dump(mode="json"))
                else:
                    problem = entry.problem.model_dump(mode="json") if entry.problem else None
                    rows[name] = tables.summary_row(name, None, status="rejected", problem=problem)
            progress.advance(submitting, len(part))
        timed_out = False
        if not args.no_wait:
            waiting = progress.add_task("waiting", total=len(pending))
            deadline = None if args.timeout is None else time.monotonic() + args.timeout
            interval = 0.2
            while pending:
                for job_id in list(pending):
                    body = client.get_json(job_id)
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
    common.add_argument("--api-key", default=None, help=f"API key, sent as a Bearer token (default ${API_KEY_ENV})")
    common.add_argument("--retries", type=_retries, default=5,
                        help="retries of a request on network errors, 429, 5xx (0 or more)")  # fmt: skip
    common.add_argument("--request-timeout", type=_seconds, default=30.0, help="seconds per HTTP request (above 0)")

    parser = argparse.ArgumentParser(
        prog="spine", description="Client of the spine reconstruction service.",
        epilog="exit codes: 0 ok, 1 job failed/cancelled, 2 usage/invalid input, 3 timeout, 4 server/network error, "
        "5 not found, 6 auth refused, 7 conflict with the job's state",
    )  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("submit", parents=[common], help="submit a job payload (JSON file, - for stdin), or a "
                       "landmark CSV with --pa-dicom")  # fmt: skip
    p.add_argument("payload", metavar="FILE", help="payload JSON; with --pa-dicom, the landmark CSV "
                   "(level,column,row[,view])")  # fmt: skip
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
                   "over the headers' (options, boundary, a spacing typed in)")  # fmt: skip
    p.add_argument("--print-payload", action="store_true", help="print the payload instead of submitting it")
    p.add_argument("--wait", action="store_true", help="wait until the job ends and print it")
    p.add_argument("--timeout", type=float, default=None, help="seconds to wait (implies --wait); exit 3 past it")
    p.add_argument("--idempotency-key", default=None, help="reuse to make a retried submission return the same job")
    p.set_defaults(func=cmd_submit)

    p = sub.add_parser("submit-dir", parents=[common], help="submit every *.json of a folder, wait, write a summary")
    p.add_argument("directory")
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds to wait for all jobs (default 3600)")
    p.add_argument("--summary", default=None, help="summary CSV to write (default DIRECTORY/summary.csv)")
    p.add_argument("--batch-size", type=int, default=500, help="payloads per batch request (at most 1000)")
    p.add_argument("--no-wait", action="store_true", help="submit only; the summary lists the queued jobs")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    p.add_argument("--json", action="store_true",
                   help="print the outcome as JSON (counts, summary path, a row per file), not one line")  # fmt: skip
    p.add_argument("--run-key", default=None, help="Idempotency-Key prefix: rerun with the same key after a crash "
                   "and no job is made twice (default: random)")  # fmt: skip
    p.set_defaults(func=cmd_submit_dir)

    p = sub.add_parser("get", parents=[common], help="print a job (JSON), or its vertebrae or measures (CSV)")
    p.add_argument("job_id")
    p.add_argument("--format", choices=["json", "csv"], default="json")
    p.add_argument("--measures", action="store_true", help="CSV of the measures instead of the vertebrae")
    p.add_argument("--sr", default=None, metavar="OUT.dcm", help="write the result as a DICOM SR (TID 1500)")
    p.add_argument("--figure-dcm", default=None, metavar="OUT.dcm", help="write the figure as a DICOM "
                   "Secondary Capture")  # fmt: skip
    p.set_defaults(func=cmd_get)

    p = sub.add_parser("list", parents=[common], help="list jobs, newest first")
    p.add_argument("--status", action="append", choices=["queued", "running", *FINAL], default=None)
    p.add_argument("--created-after", default=None, help="ISO 8601")
    p.add_argument("--created-before", default=None, help="ISO 8601")
    p.add_argument("--limit", type=int, default=20)
    p.add_argument("--cursor", default=None, help="next_cursor of the previous page")
    p.add_argument("--all", action="store_true", help="every matching job, following the cursor")
    p.add_argument("--study-instance-uid", default=None, help="jobs of this DICOM study")
    p.add_argument("--accession-number", default=None, help="jobs of this accession number")
    p.add_argument("--patient-id", default=None, help="jobs of this patient")
    p.add_argument("--format", choices=["table", "json", "csv"], default="table")
    p.set_defaults(func=cmd_list)

    p = sub.add_parser("cancel", parents=[common], help="cancel a queued or running job")
    p.add_argument("job_id")
    p.set_defaults(func=cmd_cancel)

    p = sub.add_parser("fhir", parents=[common], help="print a succeeded job's measures as a FHIR R4 Bundle")
    p.add_argument("job_id")
    p.set_defaults(func=cmd_fhir)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    if getattr(args, "format", None) == "json" and getattr(args, "measures", False):
        args.format = "csv"
    if getattr(args, "run_key", "unset") is None:
        args.run_key = uuid.uuid4().hex
    if getattr(args, "batch_size", 1) < 1:
        _err("error: --batch-size must be at least 1")
        return EXIT_USAGE
    try:
        return int(args.func(args))
    except (SpineError, UsageError) as exc:
        _report(exc)
        return exit_code(exc)
    except ServiceUnreachable as exc:  # pragma: no cover - a SpineError, kept explicit for readers
        _report(exc)
        return EXIT_SERVER
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
