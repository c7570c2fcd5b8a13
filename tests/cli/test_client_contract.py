"""The client's models are the contract's (``spine_client/contract.py`` generated from openapi.yaml,
which tests/api compare with the app), its imports are a tree without cycles or imports hidden in
functions, its retries follow ``SpineClient.retry_wait``, and an answer that is not the contract's
is an ``UnexpectedResponse`` (the CLI's server exit status), not a traceback."""

from __future__ import annotations

import ast
import http.server
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import httpx
import pytest
import yaml

from benches import clinic, clinic_films
from spine_client import SpineClient, cli, contract, models
from spine_client.errors import ServerError, ServiceUnreachable, UnexpectedResponse
from spine_engine import register
from tools.client_models import generate

ROOT = Path(__file__).resolve().parents[2]
CLIENT = ROOT / "spine_client"
SPEC = yaml.safe_load((ROOT / "openapi.yaml").read_text(encoding="utf-8"))
SCHEMAS: dict[str, Any] = SPEC["components"]["schemas"]


def test_contract_module_is_generated_from_openapi_yaml() -> None:
    assert (CLIENT / "contract.py").read_text(encoding="utf-8") == generate(SPEC), (
        "spine_client/contract.py is not openapi.yaml's: python -m tools.client_models > spine_client/contract.py"
    )


@pytest.mark.parametrize("name", sorted(n for n in SCHEMAS if "properties" in SCHEMAS[n]))
def test_every_schema_has_a_model_with_its_fields_and_required_ones(name: str) -> None:
    schema, model = SCHEMAS[name], getattr(contract, name)
    assert list(model.model_fields) == list(schema["properties"])
    required = {f for f, info in model.model_fields.items() if info.is_required()}
    assert required == set(schema.get("required", []))


def test_enums_are_the_contract_s() -> None:
    assert contract.JobStatus.__args__ == tuple(SCHEMAS["JobStatus"]["enum"])  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="status"):
        contract.Job.model_validate({**_job(), "status": "paused"})


def test_behaviour_models_keep_the_contract_s_fields() -> None:
    pairs = ((models.Job, contract.Job), (models.JobPage, contract.JobPage), (models.BatchEntry, contract.BatchEntry),
             (models.BatchResult, contract.BatchResponse))  # fmt: skip
    for mine, theirs in pairs:
        assert list(mine.model_fields) == list(theirs.model_fields)
    page = models.JobPage.model_validate({"jobs": [_job()], "next_cursor": None})
    assert page.jobs[0].finished is False and page.jobs[0].raise_for_status() is page.jobs[0]


def _job() -> dict[str, Any]:
    return {"id": "00000000-0000-4000-8000-000000000000", "status": "queued", "owner": None,
            "created_at": "2026-01-01T00:00:00Z", "started_at": None, "finished_at": None, "attempts": 0,
            "engine_version": None, "result": None, "error": None}  # fmt: skip


def _imports(path: Path, modules: Iterable[str]) -> tuple[set[str], list[str]]:
    """(spine_client modules imported at module level, imports inside functions) of one file; ``from
    package import module`` imports the module (the package is its parent, initialised first)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("spine_client"):
            names = {f"{node.module}.{a.name}" for a in node.names}
            top |= (names & set(modules)) or {node.module}
        elif isinstance(node, ast.Import):
            top |= {a.name for a in node.names if a.name.startswith("spine_client")}
    inner = [f"{path.name}:{n.lineno}" for f in ast.walk(tree) if isinstance(f, ast.FunctionDef | ast.AsyncFunctionDef)
             for n in ast.walk(f) if isinstance(n, ast.Import | ast.ImportFrom)]  # fmt: skip
    return top, inner


def test_no_import_cycle_and_none_hidden_in_a_function() -> None:
    files = {".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"): p
             for p in CLIENT.rglob("*.py")}  # fmt: skip
    graph = {name: _imports(path, files)[0] - {name} for name, path in files.items()}
    hidden = [where for name, path in files.items() if name != "spine_client.optional"
              for where in _imports(path, files)[1]]  # fmt: skip
    assert hidden == [], "imports inside functions (only spine_client.optional may: optional dependencies)"

    def reach(start: str, seen: set[str]) -> set[str]:
        for nxt in graph[start] - seen:
            seen.add(nxt)
            reach(nxt, seen)
        return seen

    cycles = sorted(name for name in graph if name in reach(name, set()))
    assert cycles == [], f"modules on an import cycle: {cycles}"


def test_retries_honour_retry_after_then_give_up() -> None:
    calls: list[str] = []
    waits: list[float] = []

    def answer(request: httpx.Request) -> httpx.Response:
        calls.append(request.url.path)
        return httpx.Response(503, headers={"retry-after": "7"}, json={"type": "about:blank", "title": "busy"})

    client = SpineClient("http://spine.test", transport=httpx.MockTransport(answer), retries=2, sleep=waits.append)
    with client, pytest.raises(ServerError):
        client.get_json("00000000-0000-4000-8000-000000000000")
    assert len(calls) == 3 and waits == [7.0, 7.0]


def test_retries_back_off_on_network_errors() -> None:
    waits: list[float] = []

    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("refused", request=request)

    client = SpineClient("http://spine.test", transport=httpx.MockTransport(refuse), retries=3, backoff=1.0,
                         sleep=waits.append)  # fmt: skip
    with client, pytest.raises(ServiceUnreachable):
        client.get_json("x")
    # min(max_backoff, backoff·2^(n-1)) times a jitter in [0.5, 1): 1, 2, 4 s
    assert [0.5 <= w / (2**n) < 1.0 for n, w in enumerate(waits)] == [True] * 3


JOB_ID = "00000000-0000-4000-8000-000000000000"


@pytest.mark.parametrize(("status", "headers", "body"), [
    (200, {"content-type": "text/html"}, b"<html>sign in</html>"),
    (200, {"content-type": "application/json"}, b'{"unexpected": true}'),
    (302, {"location": "https://spine.test/v1/jobs"}, b""),
], ids=["a page", "JSON of another API", "a redirect"])  # fmt: skip
@pytest.mark.parametrize("call", [
    lambda c: c.get(JOB_ID), lambda c: c.get_json(JOB_ID), lambda c: c.list(), lambda c: c.cancel(JOB_ID),
    lambda c: c.submit({}), lambda c: c.fhir(JOB_ID), lambda c: c.figure(JOB_ID), lambda c: c.sr(JOB_ID),
    lambda c: c.store_dicom(JOB_ID),
], ids=["get", "get_json", "list", "cancel", "submit", "fhir", "figure", "sr", "store_dicom"])  # fmt: skip
def test_an_answer_that_is_not_the_contracts_is_an_unexpected_response(
    status: int, headers: dict[str, str], body: bytes, call: Any
) -> None:
    """A URL that is not the service's (a proxy's sign-in page, another API, http sent on to https)
    used to give a traceback (JSONDecodeError: exit 1, a failed job's status) or exit 0 with the
    foreign JSON printed as the job."""
    transport = httpx.MockTransport(lambda request: httpx.Response(status, headers=headers, content=body))
    with SpineClient("http://spine.test", transport=transport, retries=0) as client, \
            pytest.raises(UnexpectedResponse, match=r"spine\.test"):  # fmt: skip
        call(client)


class _NotTheService(http.server.BaseHTTPRequestHandler):
    """Any GET answers 200 with a sign-in page, as a proxy in front of nothing would."""

    def do_GET(self) -> None:
        body = b"<html>sign in</html>"
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *_: Any) -> None:
        pass


def test_the_cli_exits_with_the_server_status_at_a_url_that_is_not_the_services(
    capsys: pytest.CaptureFixture[str],
) -> None:
    server = http.server.HTTPServer(("127.0.0.1", 0), _NotTheService)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}"
        code = cli.main(["get", JOB_ID, "--url", url, "--retries", "0"])
    finally:
        server.shutdown()
        server.server_close()
    assert code == cli.EXIT_SERVER
    assert "answered 200 (text/html), not a Job" in capsys.readouterr().err


def test_a_payload_file_that_is_not_utf8_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It used to end in a traceback (UnicodeDecodeError: exit 1, a failed job's status); read before
    any request, so no service is needed."""
    bad = tmp_path / "payload.json"
    bad.write_bytes(b"\xff\xfe{}")
    assert cli.main(["submit", str(bad), "--url", "http://127.0.0.1:9", "--retries", "0"]) == cli.EXIT_USAGE
    assert "is not UTF-8 text" in capsys.readouterr().err


def test_a_result_naming_what_a_newer_engine_adds_is_kept_not_refused() -> None:
    """``fit.assumed[].name`` and ``fit.unreliable`` grow with the engine; published as extensible enums
    (``spine_engine.models.extensible``), a client generated from today's contract keeps a value it does not
    know. As JSON enums they had the client refuse the whole job (UnexpectedResponse): a result of two films
    without their projection, whose ``projection_unstated`` the previous contract did not list, was."""
    series = clinic_films.simulate_series(clinic.synthetic_truths(1, seed=3)[0], noise_mm=1.0, seed=0)
    payload = clinic_films.build_payload(series, clinic_films.CASES["h"]).model_dump(mode="json", exclude_none=True)
    result = register(payload)
    assert "projection_unstated" in [a["name"] for a in result["fit"]["assumed"]]
    result["fit"]["assumed"].append({"name": "a_prior_of_a_later_engine", "view": None, "reason": "later"})
    result["fit"]["unreliable"].append("a_quantity_of_a_later_engine")
    job = {**_job(), "status": "succeeded", "result": result}
    transport = httpx.MockTransport(lambda request: httpx.Response(200, json=job))
    with SpineClient("http://spine.test", transport=transport, retries=0) as client:
        got = client.get(JOB_ID)
    assert got.result is not None
    assert got.result.fit.assumed[-1].name == "a_prior_of_a_later_engine"
    assert got.result.fit.unreliable[-1] == "a_quantity_of_a_later_engine"
    growing = (SCHEMAS["Assumption"]["properties"]["name"], SCHEMAS["FitReport"]["properties"]["unreliable"]["items"],
               SCHEMAS["Change"]["properties"]["measure"])  # fmt: skip
    for schema in growing:
        assert "enum" not in schema and schema["type"] == "string" and schema["examples"]
