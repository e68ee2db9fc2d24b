"""Embedded daemons started with particular flags, for tests of what the flags change."""

from __future__ import annotations

from collections.abc import Iterator

from snail_client.embedded import Services, embedded_services


def daemons_with(tmp_path_factory, *flags: str) -> Iterator[Services]:
    """Both daemons on loopback with ``flags``, sharing a fresh circuit cache."""
    cache = tmp_path_factory.mktemp("cache")
    with embedded_services(env={"SNAIL_CACHE_DIR": str(cache)}, extra_args=flags) as svc:
        yield svc
