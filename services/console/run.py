"""The console's run page(s)."""

from __future__ import annotations

from services.console.web import console_router

router = console_router()
