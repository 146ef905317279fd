"""Whether a client's text can be kept by every catalog the depot runs on."""

from __future__ import annotations


def storable(text: str) -> bool:
    """Whether every catalog can keep `text`: no NUL (Postgres refuses it in text) and valid UTF-8
    (JSON escapes can carry a lone surrogate, which no database encodes)."""
    if "\x00" in text:
        return False
    try:
        text.encode()
    except UnicodeEncodeError:
        return False
    return True
