"""API keys and roles: the start-up provisioning and the per-process key cache.

Only sha256 hashes of keys are stored; which keys are in force is decided by the registry
(:mod:`app.registry.keys`). At start, :func:`provision_keys` makes the stored environment
keys those of ``VLP_ADMIN_KEYS`` / ``VLP_TERMINAL_KEYS`` (generated keys stop being in force
once any are set). With none set and no admin key in force, it generates one admin and one
terminal key and writes them to ``VLP_DATA_DIR/credentials`` (mode 0600) as ``export``
lines. It prints them once on stderr only when stderr is a terminal: never into a log
record or a redirected stream, which collectors keep (the start-up line names the file).

:class:`KeyCache` answers the per-request question "which role has this key?" from memory
for ``KEY_CACHE_TTL_S`` after it last read the key from the registry, so a key revoked by any
process is refused here at most that long after; ``last_used_at`` is written at most once
per ``LAST_USED_INTERVAL_S`` per key and process.
"""

from __future__ import annotations

import hashlib
import logging
import os
import secrets
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal, TextIO

from app.errors import RegistryError
from app.registry import Registry
from app.settings import MIN_KEY_LENGTH, Settings

__all__ = [
    "CREDENTIALS_FILE",
    "KEY_CACHE_TTL_S",
    "KEY_PREFIX",
    "LAST_USED_INTERVAL_S",
    "MIN_KEY_LENGTH",
    "ROLES",
    "KeyCache",
    "Role",
    "generate_key",
    "hash_key",
    "provision_keys",
]

Role = Literal["admin", "terminal"]
ROLES: tuple[Role, ...] = ("admin", "terminal")
CREDENTIALS_FILE = "credentials"
# A revoked key must answer 401 in every API process within 2 s
# (docs/explanation/reliability.md#keys): 1 s of cache.
KEY_CACHE_TTL_S = 1.0
LAST_USED_INTERVAL_S = 60.0
# What every key the service generates starts with.
KEY_PREFIX = "vlp_"
_MAX_CACHED_KEYS = 4096

_log = logging.getLogger("app.security")


def hash_key(key: str) -> str:
    """The sha256 hex digest under which a key is stored."""
    return hashlib.sha256(key.encode("utf-8")).hexdigest()


def generate_key() -> str:
    """A new random key: ``vlp_`` and 32 random bytes in URL-safe base64 (47 characters).

    The prefix makes a leaked key recognisable, and keeps a key from starting with ``-``
    (one in 64 bare base64 keys did), which a command line such as ``vlp --key KEY`` would
    read as an option.
    """
    return KEY_PREFIX + secrets.token_urlsafe(32)


@dataclass
class _Entry:
    role: Role
    fresh_until: float


class KeyCache:
    """Which role a key has, read from the registry at most once per ``ttl_s`` per key.

    Only keys in force are cached (an unknown key is looked up on every request, so a key
    just created elsewhere works at once). Entries are keyed by the key's sha256 digest; at
    most ``max_entries`` are kept, least recently used dropped first.

    Parameters
    ----------
    registry : Registry
    ttl_s : float, default=KEY_CACHE_TTL_S
        How long an entry answers without asking the registry again.
    touch_interval_s : float, default=LAST_USED_INTERVAL_S
        A key's ``last_used_at`` is written at most this often by this process.
    clock : callable, default=time.monotonic
        Seconds, for both intervals (tests pass a fake one they advance).
    """

    def __init__(
        self,
        *,
        registry: Registry,
        ttl_s: float = KEY_CACHE_TTL_S,
        touch_interval_s: float = LAST_USED_INTERVAL_S,
        max_entries: int = _MAX_CACHED_KEYS,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._registry = registry
        self._ttl_s = ttl_s
        self._touch_interval_s = touch_interval_s
        self._max_entries = max_entries
        self._clock = clock
        self._entries: OrderedDict[str, _Entry] = OrderedDict()
        self._touched: dict[str, float] = {}
        self._lock = threading.Lock()

    def role_for(self, key: str) -> Role | None:
        """The role of ``key`` if it is in force, else None."""
        digest = hash_key(key)
        now = self._clock()
        with self._lock:
            entry = self._entries.get(digest)
            if entry is not None and now < entry.fresh_until:
                self._entries.move_to_end(digest)
                role: Role | None = entry.role
            else:
                role = None
        if role is None:
            role = self._refresh(digest, now)
        if role is not None:
            self._touch(digest, now)
        return role

    def fresh_role(self, key: str) -> Role | None:
        """The role of ``key`` when this cache can answer from memory (read within the TTL,
        ``last_used_at`` not due), else None: then :meth:`role_for` must ask the registry."""
        digest = hash_key(key)
        now = self._clock()
        with self._lock:
            entry = self._entries.get(digest)
            if entry is None or now >= entry.fresh_until:
                return None
            last = self._touched.get(digest)
            if last is None or now - last >= self._touch_interval_s:
                return None
            self._entries.move_to_end(digest)
            return entry.role

    def forget(self, key_hash: str) -> None:
        """Drop a key from this process's cache (after revoking it here)."""
        with self._lock:
            self._entries.pop(key_hash, None)

    def _refresh(self, digest: str, now: float) -> Role | None:
        record = self._registry.get_active_key(key_hash=digest)
        role = next((r for r in ROLES if record is not None and r == record.role), None)
        with self._lock:
            if role is None:
                self._entries.pop(digest, None)
                return None
            self._entries[digest] = _Entry(role=role, fresh_until=now + self._ttl_s)
            self._entries.move_to_end(digest)
            while len(self._entries) > self._max_entries:
                dropped, _ = self._entries.popitem(last=False)
                self._touched.pop(dropped, None)
        return role

    def _touch(self, digest: str, now: float) -> None:
        with self._lock:
            last = self._touched.get(digest)
            if last is not None and now - last < self._touch_interval_s:
                return
            self._touched[digest] = now
        try:
            self._registry.touch_api_key(key_hash=digest, when=datetime.now(UTC))
        except RegistryError:
            # Best effort: a busy or unreachable registry must not fail the request.
            _log.debug("last use of a key not recorded", exc_info=True)


def _write_credentials(path: Path, *, url: str, admin_key: str, terminal_key: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        handle.write(
            "# VLP API keys generated at first start (only their hashes are stored).\n"
            "# `source` this file: the README's walkthroughs and `vlp` read these variables.\n"
            f"export VLP_URL={url}\n"
            f"export ADMIN_KEY={admin_key}\n"
            f"export TERMINAL_KEY={terminal_key}\n"
            'export VLP_ADMIN_KEYS="$ADMIN_KEY"\n'
            'export VLP_TERMINAL_KEYS="$TERMINAL_KEY"\n'
        )
    os.chmod(path, 0o600)


def _upgrade_old_credentials(path: Path, *, registry: Registry, url: str) -> None:
    """Rewrite a credentials file of the first format (plain ``VLP_*_KEYS=`` lines, which
    ``source`` does not export) in the current one, if its keys are still in force."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        return
    if any(line.startswith("export ") for line in lines):
        return
    values = dict(line.split("=", 1) for line in lines if "=" in line and line[:1] != "#")
    admin_key, terminal_key = values.get("VLP_ADMIN_KEYS"), values.get("VLP_TERMINAL_KEYS")
    if not admin_key or not terminal_key:
        return
    if registry.get_active_key(key_hash=hash_key(admin_key)) is None:
        return
    _write_credentials(path, url=url, admin_key=admin_key, terminal_key=terminal_key)
    _log.info("credentials file rewritten with export lines", extra={"credentials": str(path)})


def provision_keys(*, registry: Registry, settings: Settings) -> Path | None:
    """Sync the environment keys and generate the first pair when needed (module docstring).

    Returns
    -------
    Path or None
        The credentials file when generated keys are in force and it is there (the start-up
        line names it), else None.
    """
    configured = [(hash_key(key), "admin") for key in settings.admin_key_list()]
    configured += [(hash_key(key), "terminal") for key in settings.terminal_key_list()]
    revoked, deleted = registry.sync_environment_keys(configured=configured)
    for key_id in revoked:
        _log.warning(
            "a configured key was revoked earlier and stays refused", extra={"key_id": key_id}
        )
    credentials = settings.data_dir / CREDENTIALS_FILE
    if "generated" in deleted:
        credentials.unlink(missing_ok=True)
        _log.info(
            "operator keys are configured: the generated keys are no longer in force",
            extra={"removed": str(credentials)},
        )
    if configured or registry.count_active_admin_keys() > 0:
        _upgrade_old_credentials(credentials, registry=registry, url=settings.public_url)
        return None if configured or not credentials.exists() else credentials
    admin_key, terminal_key = generate_key(), generate_key()
    pair = [(hash_key(admin_key), "admin"), (hash_key(terminal_key), "terminal")]
    if not registry.add_generated_keys_if_no_admin(keys=pair):
        # Another process starting at the same time generated them.
        return credentials if credentials.exists() else None
    _write_credentials(
        credentials, url=settings.public_url, admin_key=admin_key, terminal_key=terminal_key
    )
    _show_generated_keys(sys.stderr, credentials, admin_key=admin_key, terminal_key=terminal_key)
    _log.info("generated an admin and a terminal key", extra={"credentials": str(credentials)})
    return credentials


def _show_generated_keys(
    stream: TextIO, credentials: Path, *, admin_key: str, terminal_key: str
) -> None:
    """Print the generated keys on ``stream`` when it is a terminal, which a person reads;
    anything else (a pipe, a file, a container's log) is collected and kept, so there the
    keys stay in the credentials file alone."""
    if not stream.isatty():
        return
    stream.write(
        "\nNo API keys configured: generated these (shown only now; only their hashes are "
        f"stored).\n  admin key:    {admin_key}\n  terminal key: {terminal_key}\n"
        f"They are also in {credentials} (mode 0600): `source {credentials}`.\n\n"
    )
    stream.flush()
