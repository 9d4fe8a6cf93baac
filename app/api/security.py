"""API keys and roles.

Only sha256 hashes of keys are stored. Keys configured in ``VLP_ADMIN_KEYS`` /
``VLP_TERMINAL_KEYS`` are hashed into the registry at start; with none configured and an
empty key table, one admin and one terminal key are generated, logged once and written to
``VLP_DATA_DIR/credentials`` (mode 0600).
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import os
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from app.registry import Registry
from app.settings import Settings

__all__ = ["CREDENTIALS_FILE", "ROLES", "KeyRing", "Role", "hash_key", "provision_keys"]

Role = Literal["admin", "terminal"]
ROLES: tuple[Role, ...] = ("admin", "terminal")
CREDENTIALS_FILE = "credentials"

_log = logging.getLogger("app.security")


def hash_key(key: str) -> str:
    """The sha256 hex digest under which a key is stored."""
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


@dataclass
class KeyRing:
    """Key hashes known to this process, checked in constant time before the registry."""

    entries: list[tuple[str, Role]] = field(default_factory=list)

    def add(self, key: str, role: Role) -> None:
        """Remember a key (by hash) with its role."""
        self.entries.append((hash_key(key), role))

    def role_for(self, key: str, registry: Registry) -> Role | None:
        """The role of ``key``, or None when nobody knows it.

        Every in-memory hash is compared with :func:`hmac.compare_digest` (no early exit);
        keys added by another process are looked up in the registry by hash.
        """
        digest = hash_key(key)
        found: Role | None = None
        for known, role in self.entries:
            if hmac.compare_digest(known, digest) and found is None:
                found = role
        if found is not None:
            return found
        stored = registry.role_for_key_hash(key_hash=digest)
        return next((role for role in ROLES if role == stored), None)


def _write_credentials(path: Path, admin_key: str, terminal_key: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        handle.write(
            "# VLP API keys generated at first start; only their hashes are stored.\n"
            f"VLP_ADMIN_KEYS={admin_key}\nVLP_TERMINAL_KEYS={terminal_key}\n"
        )
    os.chmod(path, 0o600)


def provision_keys(*, registry: Registry, settings: Settings) -> KeyRing:
    """Store the configured keys' hashes, or generate the first pair (see module docstring)."""
    ring = KeyRing()
    configured: list[tuple[str, Role]] = [(key, "admin") for key in settings.admin_key_list()]
    configured += [(key, "terminal") for key in settings.terminal_key_list()]
    if not configured and registry.count_api_keys() == 0:
        configured = [(secrets.token_urlsafe(32), "admin"), (secrets.token_urlsafe(32), "terminal")]
        path = settings.data_dir / CREDENTIALS_FILE
        _write_credentials(path, configured[0][0], configured[1][0])
        _log.warning(
            "no API keys configured: generated an admin key %s and a terminal key %s "
            "(printed once; also written to %s, mode 0600)",
            configured[0][0],
            configured[1][0],
            path,
        )
    for key, role in configured:
        registry.add_api_key(key_hash=hash_key(key), role=role, label=f"{role} key")
        ring.add(key, role)
    return ring
