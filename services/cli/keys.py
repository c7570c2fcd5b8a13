"""``spine keys create|list|revoke|webhook-secret|rotate-webhook-secret``: the service's API keys
(services/db/keys.py).

``create`` prints the key's webhook signing secret on a line of its own, then the new key alone on
the last line of its output, once: only the key's SHA-256 digest is stored. The webhook secret is
stored as is (it must be, to sign) and never logged; ``webhook-secret`` prints it again,
``rotate-webhook-secret`` replaces it. ``revoke`` takes a key id, or a client name (every active key of that client).
On the embedded default the database is migrated first, so that a key can be made before the
first ``spine serve``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import urllib.request
from typing import Any

from sqlalchemy.engine import make_url

from services.core.config import Settings, get_settings
from services.db.engine import session_factory
from services.db.keys import (
    BadKeyName,
    count_keys,
    create_key,
    key_for_secret,
    list_keys,
    revoke,
    rotate_webhook_secret,
)
from services.db.migrate import upgrade


def _session(settings: Settings) -> Any:
    if settings.embedded:
        upgrade(settings, quiet=True)
    return session_factory(settings)()


def cmd_create(args: argparse.Namespace) -> int:
    settings = get_settings()
    with _session(settings) as session:
        try:
            row, key = create_key(session, args.name, args.role)
        except BadKeyName as exc:
            print(f"spine keys create: {exc}", file=sys.stderr)
            return 2
    print(f"webhook signing secret of key {row.id} (verify this client's webhooks with it):")
    print(row.webhook_secret)
    where = make_url(settings.sqlalchemy_url).render_as_string(hide_password=True)
    print(f"created API key {row.id} for client {row.name!r} (role {row.role}) in {where}; it is shown only now, "
          "keep it:")  # fmt: skip
    print(key)
    return 0


def cmd_webhook_secret(args: argparse.Namespace) -> int:
    command = "rotate-webhook-secret" if args.rotate else "webhook-secret"
    with _session(get_settings()) as session:
        key = key_for_secret(session, args.key)
        if key is None:
            print(f"spine keys {command}: no key with id {args.key!r} nor active key of client {args.key!r}",
                  file=sys.stderr)  # fmt: skip
            return 1
        secret = rotate_webhook_secret(session, key) if args.rotate else key.webhook_secret
        key_id, name = key.id, key.name
    if secret is None:
        print(f"spine keys webhook-secret: key {key_id} has no webhook secret; make one with "
              f"`spine keys rotate-webhook-secret {key_id}`", file=sys.stderr)  # fmt: skip
        return 1
    state = "new " if args.rotate else ""
    print(f"{state}webhook signing secret of key {key_id} (client {name!r}):")
    print(secret)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    """The keys, as a table or (``--format json``) one JSON array of {id, name, role, created_at,
    revoked_at} (ISO 8601 UTC times, ``revoked_at`` null while active) for scripts."""
    with _session(get_settings()) as session:
        keys = list_keys(session)
    if args.format == "json":
        print(json.dumps([
            {"id": k.id, "name": k.name, "role": k.role, "created_at": k.created_at.isoformat(),
             "revoked_at": k.revoked_at.isoformat() if k.revoked_at else None}
            for k in keys
        ], indent=2))  # fmt: skip
        return 0
    print(f"{'id':<14} {'name':<24} {'role':<7} {'created':<26} revoked")
    for k in keys:
        revoked = k.revoked_at.isoformat(timespec="seconds") if k.revoked_at else "-"
        print(f"{k.id:<14} {k.name:<24} {k.role:<7} {k.created_at.isoformat(timespec='seconds'):<26} {revoked}")
    return 0


def cmd_revoke(args: argparse.Namespace) -> int:
    with _session(get_settings()) as session:
        try:
            revoked = revoke(session, args.key)
        except BadKeyName as exc:
            print(f"spine keys revoke: {exc}", file=sys.stderr)
            return 2
    if not revoked:
        print(f"spine keys revoke: no active key with id or name {args.key!r}", file=sys.stderr)
        return 1
    for k in revoked:
        print(f"revoked API key {k.id} of client {k.name!r}")
    print("API processes refuse it within SPINE_API_KEY_CACHE_S seconds.")
    return 0


def add_keys_parser(sub: Any) -> None:
    """Add ``keys`` and its subcommands to the ``spine`` parser's subparsers."""
    keys = sub.add_parser("keys", help="create, list and revoke API keys; their webhook secrets")
    actions = keys.add_subparsers(dest="keys_command", required=True, metavar="ACTION")
    create = actions.add_parser("create", help="create a key; prints it alone on the last line, once")
    create.add_argument("--name", required=True, help="the client the key belongs to (owner of its jobs)")
    create.add_argument("--role", choices=["admin", "client"], default="client",
                        help="client: sees only its own jobs (default); admin: every job")  # fmt: skip
    create.set_defaults(func=cmd_create)
    listing = actions.add_parser("list", help="list keys (ids, names, roles; never the keys)")
    listing.add_argument("--format", choices=["table", "json"], default="table",
                         help="table (default), or json: [{id, name, role, created_at, revoked_at}]")  # fmt: skip
    listing.set_defaults(func=cmd_list)
    revoke = actions.add_parser("revoke", help="revoke a key by id, or every active key of a client by name")
    revoke.add_argument("key", metavar="ID_OR_NAME")
    revoke.set_defaults(func=cmd_revoke)
    show = actions.add_parser("webhook-secret", help="print a key's webhook signing secret (id, or a client's latest)")
    show.add_argument("key", metavar="ID_OR_NAME")
    show.set_defaults(func=cmd_webhook_secret, rotate=False)
    rotate = actions.add_parser("rotate-webhook-secret", help="give a key a new webhook signing secret; prints it")
    rotate.add_argument("key", metavar="ID_OR_NAME")
    rotate.set_defaults(func=cmd_webhook_secret, rotate=True)


def ensure_first_key(settings: Settings) -> str | None:
    """On first start of the embedded default (no key at all): create an admin key, print it once
    and return it (None when keys exist)."""
    with session_factory(settings)() as session:
        if count_keys(session) > 0:
            return None
        row, key = create_key(session, "admin", "admin")
    print(
        f"spine: created the first API key ({row.id}, client 'admin', role admin). It is shown only this once; "
        "keep it (`spine keys create` makes more):",
        flush=True,
    )
    print(key, flush=True)
    return key


def announce_first_key(key: str, url: str, timeout_s: float = 60.0, settle_s: float = 3.0) -> None:
    """Print the first admin key again, framed, once the service at ``url`` is ready and the worker's
    start-up banner has passed (``settle_s``): where a newcomer sees it, not lost above the banner."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with urllib.request.urlopen(f"{url}/readyz", timeout=2) as answer:
                if answer.status == 200:
                    break
        except OSError:
            pass
        time.sleep(0.5)
    time.sleep(settle_s)
    rule = "=" * 78
    sys.stderr.write(f"\n{rule}\nspine: the first admin API key of this service (shown at this first start only):\n\n"
                     f"    {key}\n\nPaste it in the page's \"API key\" field ({url}/), or send it as "
                     f"`Authorization: Bearer <key>`.\n{rule}\n\n")  # fmt: skip
    sys.stderr.flush()
