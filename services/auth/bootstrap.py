"""Auth at `fleet serve`'s start: refuse an open depot on a public address, open the token
service, and on first start make the admin token (printed once, kept in the data dir, 0600)."""

from __future__ import annotations

import logging
import socket
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from core.errors import InvalidArgumentError, UnauthenticatedError
from services.auth import ADMIN_TOKEN_FILE
from services.auth.keys import load_signing_keys, write_private
from services.auth.tokens import Auth, IssuedToken
from services.settings import AuthMode, Settings
from services.startup import is_loopback

log = logging.getLogger(__name__)


def check_auth_bind(settings: Settings, hosts: list[str]) -> str | None:
    """Refuse auth off on an address others can reach unless told `--insecure`; returns the warning
    to show at start when auth is off, None when it is on."""
    if settings.auth == AuthMode.ON:
        return None
    public = [h for h in hosts if not is_loopback(h)]
    if public and not settings.insecure:
        raise InvalidArgumentError(
            f"auth is off (FLEET_AUTH=off) but the depot would listen on {', '.join(sorted(set(public)))}, which "
            "other machines reach: anyone could delete runs. Bind 127.0.0.1 (--http-addr, --grpc-addr), turn auth "
            "on, or pass --insecure if this network is trusted"
        )
    where = "on a public address (--insecure)" if public else "on loopback only"
    return f"auth is off, {where}: every request is allowed, with no token"


def open_auth(settings: Settings, catalog: sessionmaker[Session] | None) -> Auth:
    if settings.auth == AuthMode.OFF:
        return Auth(enabled=False, keys=None, catalog=catalog)
    return Auth(
        enabled=True,
        keys=load_signing_keys(settings),
        catalog=catalog,
        public_hosts=settings.public_hosts or None,
        cache_s=settings.auth_cache_s,
    )


def ensure_admin_token(auth: Auth, data_dir: Path) -> IssuedToken | None:
    """On first start (no DATA_DIR/admin.token yet): an admin token, written there (0600) and
    returned to be printed once. A token there that this depot no longer accepts is left alone (it
    may have been revoked on purpose) and reported."""
    if not auth.enabled:
        return None
    path = data_dir / ADMIN_TOKEN_FILE
    if path.exists():
        try:
            auth.authenticate(path.read_text().strip(), "startup")
        except UnauthenticatedError as exc:
            log.warning("%s is not accepted by this depot (%s): delete it and restart for a new one", path, exc)
        return None
    issued = auth.issue(
        subject=f"admin@{socket.gethostname()}",
        scopes=["admin"],
        name="admin token made at first start",
        created_by="fleet serve",
    )
    write_private(path, issued.token + "\n")
    return issued
