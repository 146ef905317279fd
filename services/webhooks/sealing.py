"""Webhook secrets kept sealed: encrypted (Fernet: AES-CBC with an HMAC) under a key derived from the
depot's signing key, so the catalog never holds one in clear. Secrets sealed under an earlier
signing key (FLEET_AUTH_PREVIOUS_KEYS) still open after a key rotation."""

from __future__ import annotations

import base64
import secrets
from collections.abc import Callable
from functools import cached_property

from cryptography.fernet import Fernet, InvalidToken, MultiFernet
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from core.errors import ConflictError
from services.auth.keys import SigningKey, SigningKeys

_CONTEXT = b"fleet-telemetry webhook secrets v1"  # a key derived for this use signs nothing else


class SecretBox:
    """Seals and opens secrets with the keys `keys` gives, asked when first needed (with auth off,
    the key file is made only once a webhook is)."""

    def __init__(self, keys: Callable[[], SigningKeys]) -> None:
        self._keys = keys

    @cached_property
    def _fernet(self) -> MultiFernet:
        return MultiFernet([Fernet(_derived(key)) for key in self._keys().all])

    def seal(self, secret: str) -> str:
        return self._fernet.encrypt(secret.encode()).decode()

    def open(self, sealed: str) -> str:
        try:
            return self._fernet.decrypt(sealed.encode()).decode()
        except InvalidToken:
            raise ConflictError(
                "a webhook's secret does not open with this depot's signing keys (was FLEET_AUTH_KEY changed "
                "without listing the old one in FLEET_AUTH_PREVIOUS_KEYS?): remove the webhook and add it again"
            ) from None


def new_secret() -> str:
    """A webhook's HMAC secret: 256 random bits."""
    return "whsec_" + secrets.token_urlsafe(32)


def _derived(key: SigningKey) -> bytes:
    hkdf = HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=_CONTEXT)
    return base64.urlsafe_b64encode(hkdf.derive(key.secret))
