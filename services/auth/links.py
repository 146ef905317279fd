"""Signed download links: a run's recording URL with its filters, an expiry and an HMAC over all
of them (like an S3 presigned URL), for clients that cannot send a header: `rerun URL`, the Rerun
web viewer, a colleague's browser. Changing any parameter, or waiting past `expires`, breaks it."""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import logging
import re
from collections.abc import Iterable
from urllib.parse import quote, urlencode

from core.clock import iso_utc
from core.errors import PermissionDeniedError
from services.auth.keys import SigningKeys

SIGNATURE = "sig"
EXPIRES = "expires"
SIGNED_BY = "by"  # the id of the token that asked for the link: revoking it ends its links too


def _canonical(run_id: str, params: Iterable[tuple[str, str]]) -> bytes:
    """What is signed: the run and every parameter but the signature, sorted, URL-encoded."""
    items = sorted((k, v) for k, v in params if k != SIGNATURE)
    return f"v1\n{run_id}\n{urlencode(items)}".encode()


def _signature(key: bytes, run_id: str, params: Iterable[tuple[str, str]]) -> str:
    return hmac.new(key, _canonical(run_id, params), hashlib.sha256).hexdigest()


def sign(
    keys: SigningKeys, run_id: str, params: list[tuple[str, str]], expires_at: dt.datetime, by: str
) -> list[tuple[str, str]]:
    """`params` (the recording's filters) with the expiry, the issuing token and the signature."""
    signed = [(k, v) for k, v in params if k not in (SIGNATURE, EXPIRES, SIGNED_BY)]
    signed += [(EXPIRES, str(int(expires_at.timestamp()))), (SIGNED_BY, by)]
    signed.append((SIGNATURE, _signature(keys.current.link_key, run_id, signed)))
    return signed


def recording_path(run_id: str, params: list[tuple[str, str]]) -> str:
    return f"/v1/runs/{quote(run_id, safe='')}/recording.rrd?{urlencode(params)}"


def verify(keys: SigningKeys, run_id: str, params: list[tuple[str, str]], now: dt.datetime) -> str:
    """Check a link's signature and expiry (403 naming what is wrong); returns the id of the token
    that signed it, which the caller checks is not revoked."""
    given = [v for k, v in params if k == SIGNATURE]
    expires = [v for k, v in params if k == EXPIRES]
    signed_by = [v for k, v in params if k == SIGNED_BY]
    if len(given) != 1 or len(expires) != 1 or not expires[0].isdigit() or len(signed_by) != 1:
        raise PermissionDeniedError("this link is not a complete signed link: ask for a new one (fleet view RUN)")
    given_bytes = given[0].encode()  # compared as bytes: a non-ASCII str is refused, not an error
    if not any(hmac.compare_digest(given_bytes, _signature(k.link_key, run_id, params).encode()) for k in keys.all):
        raise PermissionDeniedError(
            "this link's signature does not match its run and parameters (changed or cut?): ask for a new one"
        )
    expires_at = dt.datetime.fromtimestamp(int(expires[0]), dt.UTC)
    if expires_at <= now:
        raise PermissionDeniedError(f"this link expired at {iso_utc(expires_at)}: ask for a new one (fleet view RUN)")
    return signed_by[0]


def expires_at(params: list[tuple[str, str]]) -> dt.datetime:
    """When a link that `verify` accepted expires."""
    (expires,) = [v for k, v in params if k == EXPIRES]
    return dt.datetime.fromtimestamp(int(expires), dt.UTC)


_SIGNATURE_IN_URL = re.compile(rf"([?&]{SIGNATURE}=)[^&\s\"]*")


def mask_signature(text: str) -> str:
    """A URL as logs may show it: a link's signature is what opens it, so it is blanked."""
    return _SIGNATURE_IN_URL.sub(r"\1...", text)


class MaskLinkSignatures(logging.Filter):
    """For the access log: requests of signed links are logged without their signature."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and any(isinstance(a, str) and f"{SIGNATURE}=" in a for a in record.args):
            record.args = tuple(mask_signature(a) if isinstance(a, str) else a for a in record.args)
        return True
