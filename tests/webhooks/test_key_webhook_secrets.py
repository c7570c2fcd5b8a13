"""Per-key webhook secrets (Standard Webhooks, HMAC-SHA256 with a secret per API key): `spine keys
create` prints the secret; a client's jobs are signed with its key's secret, not another client's;
`spine keys rotate-webhook-secret` changes it for later deliveries. A real `spine serve` (API and
worker) with no service-wide SPINE_WEBHOOK_SECRET and a webhook receiver on 127.0.0.1; migration
0004 up and down on SQLite (and PostgreSQL)."""

from __future__ import annotations

import re
import uuid
from collections.abc import Iterator

import pytest
from sqlalchemy import inspect
from standardwebhooks import Webhook

from services.core.config import Settings
from services.db.engine import get_engine
from services.db.migrate import downgrade, upgrade
from spine_client import SpineClient
from tests.conftest import spine_cli, spine_payload
from tests.interop_helpers import Received, Receiver, Served, wait_until

SECRET_LINE = r"^whsec_[A-Za-z0-9+/]{43}=$"


@pytest.fixture(scope="module")
def receiver() -> Iterator[Receiver]:
    r = Receiver()
    yield r
    r.close()


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory, receiver: Receiver) -> Iterator[Served]:
    service = Served(tmp_path_factory.mktemp("key-secrets"), SPINE_WEBHOOK_ALLOWED_URLS=receiver.url("/hooks"))
    assert "SPINE_WEBHOOK_SECRET" not in service.env  # no service-wide secret: the keys' own sign
    yield service
    service.stop()


def keys(served: Served, *args: str) -> list[str]:
    """`spine keys <args>` on the served database; its output lines."""
    done = spine_cli("keys", *args, data_dir=served.data_dir)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()


def delivered(served: Served, receiver: Receiver, key: str) -> Received:
    """Submit a job with a callback_url under ``key``; the webhook the receiver got for it."""
    path = f"/hooks/{uuid.uuid4().hex}"
    payload = spine_payload()
    payload["callback_url"] = receiver.url(path)
    with SpineClient(served.url, key, backoff=0.05) as client:
        client.wait(client.submit(payload).id, timeout=60).raise_for_status()
    got: list[Received] = wait_until(lambda: receiver.at(path), 60, f"a webhook at {path}", 0.1)
    return got[0]


def test_each_client_key_signs_its_jobs_webhooks_and_rotation_changes_it(served: Served, receiver: Receiver) -> None:
    out_a = keys(served, "create", "--name", "clinic-a")
    out_b = keys(served, "create", "--name", "clinic-b")
    key_a, secret_a, secret_b = out_a[-1], out_a[-3], out_b[-3]
    assert re.match(SECRET_LINE, secret_a) and re.match(SECRET_LINE, secret_b) and secret_a != secret_b
    assert key_a.startswith("spine_") and key_a.split("_")[1] in out_a[-2]  # the key stays alone, last
    assert keys(served, "webhook-secret", "clinic-a")[-1] == secret_a
    assert keys(served, "webhook-secret", key_a.split("_")[1])[-1] == secret_a

    first = delivered(served, receiver, key_a)
    assert Webhook(secret_a).verify(first.body, first.headers)["type"] == "job.succeeded"
    with pytest.raises(Exception, match="signature"):
        Webhook(secret_b).verify(first.body, first.headers)

    rotated = keys(served, "rotate-webhook-secret", "clinic-a")[-1]
    assert re.match(SECRET_LINE, rotated) and rotated != secret_a
    assert keys(served, "webhook-secret", "clinic-a")[-1] == rotated
    later = delivered(served, receiver, key_a)
    assert Webhook(rotated).verify(later.body, later.headers)["type"] == "job.succeeded"
    with pytest.raises(Exception, match="signature"):
        Webhook(secret_a).verify(later.body, later.headers)


def test_without_any_secret_a_callback_url_is_refused(served: Served, receiver: Receiver) -> None:
    """A job with no owner's key secret and no service-wide secret: webhooks are off for it."""
    from services.db.engine import session_scope
    from services.db.keys import create_key
    from services.db.models import ApiKey

    with session_scope(served.settings) as session:
        row, key = create_key(session, "clinic-c")
        session.get(ApiKey, row.id).webhook_secret = None  # type: ignore[union-attr]  # a key from before 0004
    payload = spine_payload()
    payload["callback_url"] = receiver.url("/hooks/x")
    with SpineClient(served.url, key, backoff=0.05) as client, pytest.raises(Exception, match="no webhook signing"):
        client.submit(payload)


@pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)
def test_migration_0004_goes_down_and_up(db_settings: Settings) -> None:
    def columns() -> set[str]:
        return {c["name"] for c in inspect(get_engine(db_settings)).get_columns("api_keys")}

    assert "webhook_secret" in columns()
    downgrade(db_settings, "0003_keys")
    get_engine(db_settings).dispose()
    assert "webhook_secret" not in columns() and {"id", "name", "key_hash", "revoked_at"} <= columns()
    upgrade(db_settings, quiet=True)
    get_engine(db_settings).dispose()
    assert "webhook_secret" in columns()
