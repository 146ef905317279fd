"""Catalog fixtures (`catalog_url`, `engine`, `session`, ...) live in tests/conftest.py."""
