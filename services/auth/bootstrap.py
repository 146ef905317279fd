"""Auth at `fleet serve`'s start: refuse an open depot on a public address, open the token
service, and on first start make the admin token (kept in the data dir, 0600; shown once on an
interactive terminal, never in a log)."""

from __future__ import annotations

import logging
import socket
import sys
from pathlib import Path
from typing import TextIO

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
        stale_s=settings.auth_stale_s,
        catalog_wait_s=settings.auth_catalog_wait_s,
    )


def ensure_admin_token(auth: Auth, data_dir: Path) -> IssuedToken | None:
    """On first start (no DATA_DIR/admin.token yet): an admin token, written there (0600) and
    returned to be announced (`announce_admin`). A token there that this depot no longer accepts is
    left alone (it may have been revoked on purpose) and reported."""
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


def announce_admin(admin: IssuedToken | None, data_dir: Path, out: TextIO | None = None) -> None:
    """Say that a first start made the admin token, and where it is. The token itself is shown only
    on an interactive terminal, this once: anything else on stdout (systemd's journal, docker logs,
    a file) is a log that others read and keep, and the token is in the file anyway."""
    if admin is None:
        return
    out = out or sys.stdout
    path = data_dir / ADMIN_TOKEN_FILE
    if out.isatty():
        print(f"fleet: first start: an admin token was made (shown once here, and kept in {path}):", file=out)
        print(admin.token, file=out, flush=True)
        return
    print(
        f"fleet: first start: an admin token was made and written to {path} (mode 0600; it is never printed "
        f"in a log): CLI commands on this machine use it, `cat {path}` shows it",
        file=out,
        flush=True,
    )
