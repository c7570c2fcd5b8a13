"""A key name belongs to one role: an admin key is not created under a client's name (nor the
reverse), so it never signs that client's webhooks nor is revoked with its keys; where both roles
already share a name (a database from before), the client's own key signs and a revoke by name is
refused. SQLite and PostgreSQL stores, and `spine keys` on the embedded store."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.core.config import Settings
from services.core.webhook_policy import decode_secret
from services.db.engine import session_scope
from services.db.keys import NameTaken, create_key, key_webhook_secret, new_webhook_secret, revoke
from services.db.models import ApiKey, utcnow
from tests.conftest import spine_cli

BACKENDS = pytest.mark.parametrize("db_settings", ["sqlite", "postgresql"], indirect=True)


@BACKENDS
def test_a_name_is_not_given_to_keys_of_two_roles(db_settings: Settings) -> None:
    with session_scope(db_settings) as session:
        create_key(session, "clinic-b", "client")
        with pytest.raises(NameTaken, match="'clinic-b' is already used by client keys"):
            create_key(session, "clinic-b", "admin")
        create_key(session, "clinic-b", "client")  # a second key of the same role: a rotation
        ops, _ = create_key(session, "ops-b", "admin")
        revoke(session, ops.id)
        with pytest.raises(NameTaken, match="already used by admin keys"):  # revoked keys keep their name
            create_key(session, "ops-b", "client")


@BACKENDS
def test_where_both_roles_share_a_name_the_clients_key_signs_and_revoke_by_name_is_refused(
    db_settings: Settings,
) -> None:
    with session_scope(db_settings) as session:
        client, _ = create_key(session, "clinic-c", "client")
        client_secret = client.webhook_secret
        # an admin key made under the same name before names were kept to one role, later than the client's
        session.add(ApiKey(id="0123456789ab", name="clinic-c", role="admin", key_hash="0" * 64,
                           created_at=utcnow(), webhook_secret=new_webhook_secret()))  # fmt: skip
        session.commit()
        assert client_secret is not None
        assert key_webhook_secret(session, "clinic-c") == decode_secret(client_secret)
        with pytest.raises(NameTaken, match="revoke them by id"):
            revoke(session, "clinic-c")
        assert [k.id for k in revoke(session, "0123456789ab")] == ["0123456789ab"]  # by id: that key only
        assert [k.id for k in revoke(session, "clinic-c")] == [client.id]
        session.add(ApiKey(id="0123456789ac", name="clinic-c", role="admin", key_hash="1" * 64,
                           created_at=utcnow(), webhook_secret=new_webhook_secret()))  # fmt: skip
        session.commit()
        assert key_webhook_secret(session, "clinic-c") is None  # an admin key never signs a client's jobs


def test_spine_keys_create_refuses_a_name_of_the_other_role(tmp_path: Path) -> None:
    assert spine_cli("keys", "create", "--name", "clinic-d", data_dir=tmp_path).returncode == 0
    refused = spine_cli("keys", "create", "--name", "clinic-d", "--role", "admin", data_dir=tmp_path)
    assert refused.returncode == 2 and refused.stdout == ""
    assert refused.stderr.startswith("spine keys create: the name 'clinic-d' is already used by client keys")
    assert "Traceback" not in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
