"""Which files of ``services/`` one job passes through, hop by hop (docs/architecture.md).

Runs in process on a fresh embedded database: POST /v1/jobs (API), the worker's run of the job
(claim, fit, finish), GET /v1/jobs/{id} (API). For each hop it prints the ``services/`` files
whose functions ran (by ``sys.setprofile``), so the count is measured, not drawn by hand.
``python -m tools.hops [--out FILE]`` (``--out``: the same lists as JSON).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from services.api.app import create_app
from services.cli.keys import ensure_first_key
from services.core.config import Settings
from services.db.engine import session_factory
from services.db.keys import create_key
from services.db.migrate import upgrade
from services.worker.tasks import execute_job

ROOT = Path(__file__).resolve().parents[1]
SERVICES = str(ROOT / "services")


def files_run(action: Callable[[], Any]) -> tuple[Any, list[str]]:
    """Run ``action``; return its value and the services/ files whose code ran meanwhile."""
    seen: set[str] = set()

    def profile(frame: Any, event: str, _arg: Any) -> None:
        if event == "call":
            name = frame.f_code.co_filename
            if name.startswith(SERVICES):
                seen.add(str(Path(name).relative_to(ROOT)))

    sys.setprofile(profile)
    threading.setprofile(profile)  # the API runs in new threads (a fresh TestClient's portal and pool)
    try:
        value = action()
    finally:
        sys.setprofile(None)
        threading.setprofile(None)  # type: ignore[arg-type]
    return value, sorted(seen)


def payload() -> dict[str, Any]:
    levels = [f"T{i}" for i in range(1, 13)] + [f"L{i}" for i in range(1, 6)]
    identity = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]
    marks = [{"level": lv, "point": [100.0 + 15.0 * (i / 16) * (1 - i / 16) * 4, 50.0 + 420.0 * i / 16]}
             for i, lv in enumerate(levels)]  # fmt: skip
    return {"pa": {"landmarks": marks},
            "boundary": {"T1": {"position": [0.0, 0.0, 0.0], "directors": identity},
                         "L5": {"position": [0.0, 0.0, -420.0], "directors": identity}}}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="also write the files of each hop as JSON to this file")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp))
        upgrade(settings, quiet=True)
        ensure_first_key(settings)
        with session_factory(settings)() as session:
            key = create_key(session, "hops", "client")[1]
        app = create_app(settings)
        headers = {"Authorization": f"Bearer {key}"}
        with TestClient(app, headers=headers) as warm:  # first-call work (imports, caches) is not a hop
            warm_id = warm.post("/v1/jobs", json=payload()).json()["id"]
            warm.get(f"/v1/jobs/{warm_id}")
        # A fresh client per hop: its threads are new, so the profile sees the API's code.
        response, post = files_run(lambda: TestClient(app, headers=headers).post("/v1/jobs", json=payload()))
        job_id = uuid.UUID(response.json()["id"])
        outcome, run = files_run(lambda: execute_job(settings, job_id))
        _, get = files_run(lambda: TestClient(app, headers=headers).get(f"/v1/jobs/{job_id}"))
    hops = {"POST /v1/jobs": post, f"worker run ({outcome})": run, "GET /v1/jobs/{id}": get}
    for name, files in hops.items():
        print(f"{name}: {len(files)} files")
        for f in files:
            print(f"  {f}")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        counts = {name: len(files) for name, files in hops.items()}
        args.out.write_text(json.dumps({"files": counts, "hops": hops}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
