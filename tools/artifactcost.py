"""CPU per GET of a succeeded job's artifacts (docs/dicom.md, "Conditional GET and the artifact cache"):
the first GET (built), the second (from the API process's ``ArtifactCache``) and a GET whose
``If-None-Match`` matches (304, nothing built), through FastAPI's TestClient on a fresh embedded
SQLite database; ``time.process_time`` (every thread of the process, the test client's included),
median over ``--repeat`` jobs. ``python -m tools.artifactcost [--repeat 5] [--kind sr.dcm ...] [--out FILE]``
(``--out``: the same medians as JSON, with the command that produced them).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

from fastapi.testclient import TestClient
from sqlalchemy import update

from benches.report import write_json
from services.api.app import create_app
from services.core.config import Settings
from services.db.engine import session_factory, session_scope
from services.db.keys import create_key
from services.db.migrate import upgrade
from services.db.models import Job
from spine_engine import register
from tools.hops import payload

KINDS = ["sr.dcm", "figure.dcm", "figure.png", "figure.svg", "fhir"]


def cpu_ms(call: Callable[[], object]) -> float:
    start = time.process_time()
    call()
    return (time.process_time() - start) * 1000


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5, help="jobs per artifact (medians over them)")
    parser.add_argument("--kind", action="append", choices=KINDS, help="artifacts to measure (default: all)")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON to this file")
    args = parser.parse_args(argv)
    kinds = args.kind or KINDS
    artifacts: dict[str, dict[str, float | int]] = {}
    body = payload()
    result = register(body)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp))
        upgrade(settings, quiet=True)
        with session_factory(settings)() as session:
            key = create_key(session, "artifactcost", "client")[1]
        with TestClient(create_app(settings)) as api:
            api.headers["Authorization"] = f"Bearer {key}"
            api.get("/healthz")
            print("| artifact | first GET (built) | second GET (cache) | If-None-Match (304) | bytes |")
            print("| --- | ---: | ---: | ---: | ---: |")
            for kind in kinds:
                rows: dict[str, list[float]] = {"first": [], "second": [], "304": []}
                size = 0
                for _ in range(args.repeat):
                    job_id = api.post("/v1/jobs", json=body).json()["id"]
                    now = datetime.now(UTC)
                    with session_scope(settings) as session:
                        session.execute(update(Job).where(Job.id == uuid.UUID(job_id)).values(
                            status="succeeded", result=result, started_at=now, finished_at=now, attempts=1,
                            engine_version="artifactcost"))  # fmt: skip
                    url = f"/v1/jobs/{job_id}/{kind}"
                    first: list[object] = []
                    rows["first"].append(cpu_ms(lambda: first.append(api.get(url))))  # noqa: B023
                    rows["second"].append(cpu_ms(lambda: api.get(url)))  # noqa: B023
                    etag = first[0].headers["etag"]  # type: ignore[attr-defined]
                    size = len(first[0].content)  # type: ignore[attr-defined]
                    answer: list[int] = []
                    cond = {"If-None-Match": etag}
                    rows["304"].append(cpu_ms(lambda: answer.append(api.get(url, headers=cond).status_code)))  # noqa: B023
                    assert answer == [304]
                first_ms, second_ms, not_modified_ms = (statistics.median(rows[k]) for k in ("first", "second", "304"))
                print(f"| `{kind}` | {first_ms:.1f} ms | {second_ms:.1f} ms | {not_modified_ms:.1f} ms | {size} |")
                artifacts[kind] = {"first_get_cpu_ms": first_ms, "second_get_cpu_ms": second_ms,
                                   "if_none_match_304_cpu_ms": not_modified_ms, "bytes": size,
                                   "repeat": args.repeat}  # fmt: skip
    if args.out:
        command = " ".join(["python -m tools.artifactcost", *(sys.argv[1:] if argv is None else argv)])
        write_json(args.out, {"command": command, "settings": {"repeat": args.repeat, "kinds": kinds},
                              "artifacts": artifacts})  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
