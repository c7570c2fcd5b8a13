"""Which URLs a job may name as ``callback_url``: http(s), no credentials, and matching an
operator-configured allow-list of URL prefixes (``SPINE_WEBHOOK_ALLOWED_URLS``).

The allow-list is what keeps a client from making the service call addresses of the hospital
network it should not reach (server-side request forgery). Prefixes are matched on parsed parts,
never as raw strings: the scheme, the host (exactly, case-insensitively) and the port must be
equal, and the URL's path must be the prefix's path or lie below it at a ``/`` boundary, so
``https://ris.example`` does not admit ``https://ris.example.evil.org`` and ``https://h/hooks`` does
not admit ``https://h/hooks-admin``. Paths with dot segments (``..``, and ``..;x``, which Tomcat and
Spring read as ``..``), encoded dots, slashes and backslashes, or an encoded ``%`` (``%25``: a
double-encoded ``%252e%252e`` decoded twice is ``..``) are refused, so a path cannot climb out of
its prefix. Redirects are never followed on delivery.

Also the form of a webhook signing secret (``decode_secret``): the settings check both when the
service starts, so this module lives in ``services.core`` beside them.
"""

from __future__ import annotations

import base64
import binascii
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from urllib.parse import SplitResult, urlsplit

from spine_engine.errors import FieldError, InvalidInput

SECRET_PREFIX = "whsec_"
MIN_SECRET_BYTES = 16

SCHEMES = ("http", "https")
DEFAULT_PORTS = {"http": 80, "https": 443}
_FORBIDDEN_IN_PATH = re.compile(r"%2e|%2f|%5c|\\", re.IGNORECASE)
_CONTROL = re.compile(r"[\x00-\x20\x7f]")


class WebhooksDisabled(ValueError):
    """The operator allows no webhook destination (empty allow-list) or set no signing secret."""


@dataclass(frozen=True)
class AllowedPrefix:
    """One entry of the allow-list, parsed."""

    scheme: str
    host: str
    port: int
    path: str
    """Path prefix without a trailing slash; "" admits every path of the origin."""

    def admits(self, url: SplitResult) -> bool:
        if url.scheme.lower() != self.scheme or (url.hostname or "").lower() != self.host:
            return False
        if _port(url) != self.port:
            return False
        path = url.path or "/"
        return not self.path or path == self.path or path.startswith(self.path + "/")

    def __str__(self) -> str:
        default = DEFAULT_PORTS[self.scheme] == self.port
        return f"{self.scheme}://{self.host}{'' if default else f':{self.port}'}{self.path or '/'}"


def _port(url: SplitResult) -> int:
    port = url.port  # raises ValueError when out of range or not a number
    return port if port is not None else DEFAULT_PORTS.get(url.scheme.lower(), -1)


def _path_problem(path: str) -> str | None:
    """Why a URL's path could climb out of its allow-listed prefix on some receiver, or None."""
    for segment in path.split("/"):
        name, parameters, _ = segment.partition(";")
        if name in (".", ".."):
            if parameters:
                return (f"the URL's path must not contain dot segments, even with parameters ({segment!r}: "
                        "servers such as Tomcat and Spring read it as '..')")  # fmt: skip
            return "the URL's path must not contain dot segments ('.' or '..')"
    if "%25" in path:
        return ("the URL's path must not contain an encoded '%' (%25): decoded twice, as some servers do, "
                "it could become dot segments or slashes")  # fmt: skip
    if _FORBIDDEN_IN_PATH.search(path):
        return "the URL's path must not contain dot segments, backslashes or encoded dots and slashes (%2e, %2f, %5c)"
    return None


def url_problem(url: str) -> str | None:
    """Why ``url`` can never be a webhook destination (whatever the allow-list), or None."""
    if _CONTROL.search(url):
        return "the URL contains spaces or control characters"
    try:
        parts = urlsplit(url)
        _port(parts)
    except ValueError as exc:
        return f"the URL does not parse: {exc}"
    if parts.scheme.lower() not in SCHEMES:
        return f"the scheme must be http or https, not {parts.scheme or '(none)'!r}"
    if not parts.hostname:
        return "the URL has no host"
    if parts.username is not None or parts.password is not None or "@" in parts.netloc:
        return "the URL must not carry credentials (user:password@)"
    return _path_problem(parts.path)


def parse_allow_list(text: str) -> list[AllowedPrefix]:
    """Parse ``SPINE_WEBHOOK_ALLOWED_URLS`` (comma-separated URL prefixes); raise ``ValueError``."""
    prefixes = []
    for raw in (item.strip() for item in text.split(",")):
        if not raw:
            continue
        reason = url_problem(raw)
        if reason is not None:
            raise ValueError(f"SPINE_WEBHOOK_ALLOWED_URLS entry {raw!r}: {reason}")
        parts = urlsplit(raw)
        if parts.query or parts.fragment:
            raise ValueError(f"SPINE_WEBHOOK_ALLOWED_URLS entry {raw!r}: a prefix has no query or fragment")
        scheme = parts.scheme.lower()
        prefixes.append(AllowedPrefix(scheme, (parts.hostname or "").lower(), _port(parts), parts.path.rstrip("/")))
    return prefixes


@lru_cache(maxsize=16)
def allow_list(text: str) -> tuple[AllowedPrefix, ...]:
    return tuple(parse_allow_list(text))


def destination_problem(url: str, allowed: Sequence[AllowedPrefix]) -> str | None:
    """Why ``url`` may not receive webhooks under ``allowed``, or None when it may."""
    reason = url_problem(url)
    if reason is not None:
        return reason
    if not allowed:
        raise WebhooksDisabled("this service accepts no callback_url: its webhook allow-list is empty")
    parts = urlsplit(url)
    if not any(prefix.admits(parts) for prefix in allowed):
        return "the URL matches none of the webhook destinations this service's operator allows"
    return None


def check_callback_url(url: str | None, allowed_urls: str, secret_configured: bool) -> None:
    """Raise ``InvalidInput`` naming ``callback_url`` when a payload's callback_url is not allowed.

    ``secret_configured``: the service-wide secret is set or the submitting client's API key has a
    webhook secret (``services.webhooks.submission``). Called by the API after the payload validated;
    a payload without callback_url passes.
    """
    if url is None:
        return
    try:
        if not secret_configured:
            raise WebhooksDisabled(
                "this service accepts no callback_url: it has no webhook signing secret for this client"
            )
        reason = destination_problem(str(url), allow_list(allowed_urls))
    except WebhooksDisabled as exc:
        raise InvalidInput([FieldError(("callback_url",), str(exc), "webhooks_disabled")]) from None
    if reason is not None:
        raise InvalidInput([FieldError(("callback_url",), reason, "callback_url_not_allowed")])


def decode_secret(secret: str) -> bytes:
    """The key bytes of a ``whsec_<base64>`` (or bare base64) secret; raise ``ValueError``."""
    text = secret.strip().removeprefix(SECRET_PREFIX)
    try:
        key = base64.b64decode(text + "=" * (-len(text) % 4), validate=True)
    except (binascii.Error, ValueError):
        raise ValueError("a webhook secret is whsec_ followed by base64") from None
    if len(key) < MIN_SECRET_BYTES:
        raise ValueError(f"a webhook secret needs at least {MIN_SECRET_BYTES} bytes of key, this one {len(key)}")
    return key
