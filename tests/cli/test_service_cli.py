"""The `spine` command: serve runs API and worker on the embedded default, and Ctrl-C stops both."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.core.config import Settings
from tests.conftest import spine_payload
from tests.stop_cost import collection_cpu_s, stop_cpu_s

pytestmark = pytest.mark.integration


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


KEY = re.compile(r"^(spine_[0-9a-f]{12}_[A-Za-z0-9_-]{43})$", re.M)


class Serve:
    def __init__(self, data_dir: Path, api_key: str | None = None, worker: bool = True):
        self.port = _free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.log = data_dir / f"serve-{self.port}.log"
        env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
        env.update(SPINE_DATA_DIR=str(data_dir), SPINE_WORKER_CONCURRENCY="1")
        with self.log.open("wb") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "services.cli", "serve", "--port", str(self.port),
                 *([] if worker else ["--no-worker"])],
                env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True, cwd=data_dir,
            )  # fmt: skip
        self.client = httpx.Client(base_url=self.base, timeout=10)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if self.client.get("/readyz").status_code == 200 and (not worker or " ready." in self.text()):
                    # the first start of the embedded default prints an admin key, once
                    printed = KEY.search(self.text())
                    self.api_key = api_key or (printed.group(1) if printed else "")
                    assert self.api_key, f"no API key printed at first start:\n{self.text()}"
                    self.client.headers["Authorization"] = f"Bearer {self.api_key}"
                    return
            except httpx.TransportError:
                pass
            assert self.proc.poll() is None, self.text()
            time.sleep(0.2)
        raise AssertionError(f"spine serve did not become ready:\n{self.text()}")

    def text(self) -> str:
        return self.log.read_text(errors="replace")

    def worker_pid(self) -> int:
        match = re.search(r"started worker process (\d+)", self.text())
        assert match, self.text()
        return int(match.group(1))

    def wait(self, job_id: str, timeout: float = 60) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job: dict[str, Any] = self.client.get(f"/v1/jobs/{job_id}").json()
            if job["status"] in ("succeeded", "failed", "cancelled"):
                return job
            time.sleep(0.2)
        raise AssertionError(f"job {job_id} did not finish:\n{self.text()[-3000:]}")

    def interrupt(self) -> float:
        """Ctrl-C, as a terminal sends it; return the CPU seconds `spine serve` itself spent stopping
        (tests/stop_cost.py)."""
        try:
            return stop_cpu_s(self.proc, signal.SIGINT, 40)
        finally:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.client.close()


def test_serve_runs_api_and_worker_and_ctrl_c_stops_both(tmp_path: Path) -> None:
    serve = Serve(tmp_path)
    try:
        worker = serve.worker_pid()
        response = serve.client.post("/v1/jobs", json=spine_payload())
        assert response.status_code == 202
        job = serve.wait(response.json()["id"])
        assert job["status"] == "succeeded", job["error"]
    finally:
        serve.interrupt()
    assert serve.proc.returncode is not None
    deadline = time.monotonic() + 10
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(worker), "the worker child outlived spine serve"
    assert (tmp_path / "spine.db").exists() and (tmp_path / "broker.db").exists()
    # The worker's beat (services.worker.beat) keeps its schedule in memory: no file in the folder it ran in.
    assert not list(tmp_path.glob("celerybeat-schedule*")), sorted(p.name for p in tmp_path.iterdir())

    again = Serve(tmp_path, api_key=serve.api_key, worker=False)  # jobs survive a restart; no key printed again
    assert not KEY.search(again.text())
    try:
        kept = again.client.get(f"/v1/jobs/{job['id']}").json()
        assert kept["status"] == job["status"] and kept["finished_at"] == job["finished_at"]
    finally:
        stopping_s = again.interrupt()
    # Its heap frozen once uvicorn stopped (services.worker.heap), its exit does not walk it: stopping costs
    # less than one collection of this process's heap, which holds every module `spine serve` loads.
    assert stopping_s < collection_cpu_s(), stopping_s


def test_spine_help_lists_the_operator_commands() -> None:
    out = subprocess.run([sys.executable, "-m", "services.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0
    for command in ("serve", "worker", "migrate", "openapi", "loadtest", "bench"):
        assert command in out.stdout


def test_spine_migrate_creates_the_embedded_database(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "DATABASE_URL"}
    env["SPINE_DATA_DIR"] = str(tmp_path / "data")
    subprocess.run([sys.executable, "-m", "services.cli", "migrate"], env=env, check=True, timeout=60,
                   capture_output=True)  # fmt: skip
    assert (tmp_path / "data" / "spine.db").stat().st_size > 0


ROOT = Path(__file__).resolve().parents[2]


def test_readme_starts_with_its_title_then_make_run_and_make_test() -> None:
    """A newcomer reads the title, then the README's first code block: its two commands."""
    lines = [ln for ln in (ROOT / "README.md").read_text().splitlines() if ln.strip()]
    assert lines[0].startswith("# ")
    start = next(i for i, ln in enumerate(lines) if ln.startswith("```"))
    commands = [ln.split("#")[0].strip() for ln in lines[start + 1 : start + 3]]
    assert commands == ["make run", "make test"] and lines[start + 3] == "```"


def test_readme_documents_every_setting() -> None:
    readme = (ROOT / "README.md").read_text()
    for name, info in Settings.model_fields.items():
        alias = info.validation_alias
        env = alias.choices[0] if alias is not None else f"SPINE_{name.upper()}"  # type: ignore[union-attr]
        assert f"| `{env}` |" in readme, f"README's settings table lacks {env}"


def test_ci_runs_the_readme_test_command() -> None:
    script = (ROOT / ".ci" / "run").read_text()
    assert "make test" in script and os.access(ROOT / ".ci" / "run", os.X_OK)


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        out += [int(c) for c in task.read_text().split()]
    return out


def test_worker_supervisor_restarts_a_celery_worker_that_stopped_unasked(tmp_path: Path) -> None:
    """`spine worker` runs Celery as a child: a child that dies (here SIGKILL, as after a broker
    fault that ends Celery's loop) is started again; SIGTERM to `spine worker` stops both."""
    if not Path("/proc/self/task").is_dir():
        pytest.skip("needs Linux /proc to find the supervisor's child")
    env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "CELERY_BROKER_URL")}
    env.update(SPINE_DATA_DIR=str(tmp_path / "data"), SPINE_WORKER_CONCURRENCY="1")
    subprocess.run([sys.executable, "-m", "services.cli", "migrate"], env=env, check=True, timeout=60,
                   capture_output=True)  # fmt: skip
    log_path = tmp_path / "worker.log"
    with log_path.open("wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", "worker", "--no-beat"], env=env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
    try:
        def wait_for(predicate: Any, what: str, timeout: float = 60.0) -> None:
            deadline = time.monotonic() + timeout
            while not predicate():
                assert proc.poll() is None, log_path.read_text()[-2000:]
                assert time.monotonic() < deadline, f"{what}; log:\n{log_path.read_text()[-2000:]}"
                time.sleep(0.2)

        wait_for(lambda: log_path.read_text().count(" ready.") >= 1, "the first worker to be ready")
        [first] = _children(proc.pid)
        os.kill(first, signal.SIGKILL)
        wait_for(lambda: log_path.read_text().count(" ready.") >= 2, "a second worker to be ready")
        [second] = _children(proc.pid)
        assert second != first and "stopped unasked" in log_path.read_text()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(40) == 0
        assert not _alive(second)  # stopped and reaped by the supervisor
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def test_the_data_dir_is_one_place_whatever_the_working_directory(tmp_path: Path) -> None:
    """A key made from one folder is seen from another (not a second database)."""
    env = {k: v for k, v in os.environ.items() if k not in ("SPINE_DATA_DIR", "DATABASE_URL", "CELERY_BROKER_URL")}
    env["XDG_DATA_HOME"] = str(tmp_path / "xdg")
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir()
    there.mkdir()
    spine = [sys.executable, "-m", "services.cli", "keys"]
    made = subprocess.run([*spine, "create", "--name", "from-here"], cwd=here, env=env, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert made.returncode == 0, made.stderr
    assert str(tmp_path / "xdg" / "spine" / "spine.db") in made.stdout  # it says where the key went
    listed = subprocess.run([*spine, "list"], cwd=there, env=env, capture_output=True, text=True, timeout=120)
    assert "from-here" in listed.stdout, listed.stdout + listed.stderr
    assert not (here / ".spine").exists() and not (there / ".spine").exists()
    relative = Settings.model_validate({"data_dir": "rel"}).data_dir
    assert relative.is_absolute() and relative == Path.cwd() / "rel"  # made absolute once, at start
