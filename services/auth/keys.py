"""The depot's signing keys: the current one signs tokens and links; earlier ones (key rotation) are
still accepted for checking. Given by setting (the same on every node), else generated at first
start into the data dir with mode 0600."""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from services.settings import Settings

KEY_FILE = "auth.key"
_LINK_CONTEXT = b"fleet-telemetry download link v1"


@dataclass(frozen=True)
class SigningKey:
    secret: bytes

    @property
    def id(self) -> str:
        """A short public name of the key (the JWT header's `kid`): which key signed a token."""
        return hashlib.sha256(b"kid:" + self.secret).hexdigest()[:12]

    @property
    def link_key(self) -> bytes:
        """The key of download links, derived so a link's signature never signs a token."""
        return hmac.new(self.secret, _LINK_CONTEXT, hashlib.sha256).digest()


@dataclass(frozen=True)
class SigningKeys:
    current: SigningKey
    previous: tuple[SigningKey, ...] = ()

    @property
    def all(self) -> tuple[SigningKey, ...]:
        return (self.current, *self.previous)

    def by_id(self, key_id: str | None) -> SigningKey | None:
        return next((k for k in self.all if k.id == key_id), None)


def load_signing_keys(settings: Settings) -> SigningKeys:
    if settings.auth_key is not None:
        current = SigningKey(settings.auth_key.get_secret_value().encode())
    else:
        current = SigningKey(_key_file(settings.data_dir / KEY_FILE))
    previous = tuple(SigningKey(k.get_secret_value().encode()) for k in settings.auth_previous_keys)
    return SigningKeys(current, previous)


def _key_file(path: Path) -> bytes:
    """The key kept in the data dir, created (random, 0600) if there is none yet."""
    try:
        return path.read_bytes().strip()
    except FileNotFoundError:
        pass
    key = secrets.token_urlsafe(48)
    try:
        write_private(path, key + "\n")
    except FileExistsError:  # another process made it first: use theirs
        return path.read_bytes().strip()
    return key.encode()


def write_private(path: Path, text: str) -> None:
    """Create `path` readable by its owner only (never readable by others, not even for a moment);
    refuses to overwrite."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
