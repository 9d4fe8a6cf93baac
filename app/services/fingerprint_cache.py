"""Per-process cache of loaded fingerprints and prepared solvers.

Fingerprints are cached per (room, version) in an LRU of ``fingerprint_cache_size`` entries
and ``fingerprint_cache_mib`` of arrays; the solvers built from one are kept with it, per
(model, solver name). An entry's size (:func:`held_bytes`: the arrays its fingerprint and
solvers hold, each buffer once) is measured when it is loaded and when a solver is prepared
for it; beyond the budget the least recently used entries are dropped, never the one just
used (a room larger than the budget is still served, alone). One lookup
(:meth:`FingerprintCache.prepare`) answers a localize request with everything it needs: the
fingerprint, the LEDs a calibration masked and the prepared solver; it counts one cache hit
or miss. A room's current version
is re-read from the registry at most every ``version_check_seconds`` of the cache's clock,
so every API process switches to a newly built version within that time (a room with no
ready version is re-read on every request).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from app.clock import Clock
from app.registry import Registry
from app.registry.errors import FingerprintNotReady
from app.telemetry import Metrics
from app.vlp.fingerprints import Fingerprint
from app.vlp.measurements import Model

from .matrices import rebuilding_if_corrupt

if TYPE_CHECKING:
    from app.vlp.solvers import Solver

__all__ = ["FingerprintCache", "PreparedVersion", "held_bytes"]


@dataclass(frozen=True)
class PreparedVersion:
    """One (room, version) ready to solve with one (model, solver): its fingerprint, the
    room LED indices it leaves out (a calibration's mask) and the solver; ``lock``
    serialises the solver's solves."""

    fingerprint: Fingerprint
    masked_leds: tuple[int, ...]
    solver: Solver
    lock: threading.Lock = field(default_factory=threading.Lock, compare=False)


@dataclass
class _Entry:
    fingerprint: Fingerprint
    masked_leds: tuple[int, ...]
    prepared: dict[tuple[Model, str], PreparedVersion] = field(default_factory=dict)
    held_bytes: int = 0


class FingerprintCache:
    """Loaded fingerprints and solvers of one process (thread-safe).

    Version re-reads are timed by ``clock.monotonic()`` (the registry's clock when None).
    """

    def __init__(
        self,
        *,
        registry: Registry,
        size: int,
        version_check_seconds: float,
        metrics: Metrics,
        clock: Clock | None = None,
        max_bytes: int | None = None,
    ) -> None:
        self._registry = registry
        self._size = size
        self._max_bytes = max_bytes
        self._interval = version_check_seconds
        self._metrics = metrics
        self._clock = registry.clock if clock is None else clock
        self._lock = threading.Lock()
        self._versions: dict[str, tuple[int, float]] = {}
        self._entries: OrderedDict[tuple[str, int], _Entry] = OrderedDict()
        self._key_locks: dict[tuple[object, ...], threading.Lock] = {}

    def current_version(self, room_id: str) -> int:
        """The room's current fingerprint version (re-read at most every interval).

        Raises
        ------
        RoomNotFound, FingerprintNotReady
        """
        now = self._clock.monotonic()
        with self._lock:
            cached = self._versions.get(room_id)
        if cached is not None and now - cached[1] < self._interval:
            return cached[0]
        version = self._registry.current_version(room_id=room_id)
        if version is None:
            raise FingerprintNotReady(
                f"room {room_id} has no ready fingerprint yet; poll the room or its build job"
            )
        with self._lock:
            self._versions[room_id] = (version, now)
        return version

    def fingerprint(self, room_id: str, version: int) -> Fingerprint:
        """The fingerprint of (room, version), loaded once and verified by the registry."""
        return self._entry(room_id, version).fingerprint

    def prepare(self, room_id: str, version: int, model: Model, name: str) -> PreparedVersion:
        """Fingerprint, mask and the solver ``name`` for (room, version, model), from one
        cache lookup; the solver is built once."""
        entry = self._entry(room_id, version)
        key = (model, name)
        with self._lock:
            prepared = entry.prepared.get(key)
        if prepared is not None:
            return prepared
        with self._key_lock(("solver", room_id, version, model, name)):
            with self._lock:
                prepared = entry.prepared.get(key)
            if prepared is None:
                solver = _new_solver(name, entry.fingerprint, model)
                prepared = PreparedVersion(entry.fingerprint, entry.masked_leds, solver)
                with self._lock:
                    entry.prepared[key] = prepared
                    solvers = list(entry.prepared.values())
                size = held_bytes(entry.fingerprint, *(p.solver for p in solvers))
                with self._lock:
                    entry.held_bytes = size
                    self._evict((room_id, version))
        return prepared

    @property
    def held_bytes(self) -> int:
        """The arrays the cached entries hold, as last measured (bytes)."""
        with self._lock:
            return sum(entry.held_bytes for entry in self._entries.values())

    def prepared_in_memory(
        self, room_id: str, version: int | None, model: Model, name: str
    ) -> tuple[int, PreparedVersion] | None:
        """The version (``version``, else the room's current one) and its prepared solver
        ``name`` for ``model`` when this cache holds them and need not ask the registry
        (the current version read within the interval); else None, and nothing is read.
        Counts a cache hit when it answers, as :meth:`prepare` does."""
        now = self._clock.monotonic()
        with self._lock:
            if version is None:
                cached = self._versions.get(room_id)
                if cached is None or now - cached[1] >= self._interval:
                    return None
                version = cached[0]
            key = (room_id, version)
            entry = self._entries.get(key)
            prepared = None if entry is None else entry.prepared.get((model, name))
            if prepared is None:
                return None
            self._entries.move_to_end(key)
        self._metrics.cache.labels(result="hit").inc()
        return version, prepared

    def forget(self, room_id: str) -> None:
        """Drop everything cached about a room (after it was replaced or deleted)."""
        with self._lock:
            self._versions.pop(room_id, None)
            for key in [key for key in self._entries if key[0] == room_id]:
                self._drop(key)

    def _entry(self, room_id: str, version: int) -> _Entry:
        key = (room_id, version)
        with self._lock:
            entry = self._entries.get(key)
            if entry is not None:
                self._entries.move_to_end(key)
        if entry is not None:
            self._metrics.cache.labels(result="hit").inc()
            return entry
        with self._key_lock(("fingerprint", room_id, version)):
            with self._lock:
                entry = self._entries.get(key)
            if entry is None:
                self._metrics.cache.labels(result="miss").inc()
                with rebuilding_if_corrupt(self._registry, room_id=room_id):
                    loaded = self._registry.load_version(room_id=room_id, version=version)
                entry = _Entry(
                    loaded.fingerprint,
                    loaded.record.masked_leds,
                    held_bytes=held_bytes(loaded.fingerprint),
                )
                with self._lock:
                    self._entries[key] = entry
                    self._evict(key)
            else:
                self._metrics.cache.labels(result="hit").inc()
        return entry

    def _evict(self, used: tuple[str, int]) -> None:
        # Caller holds self._lock: drop least recently used entries beyond the count and the
        # byte budget, never ``used`` (the entry a request is being answered from).
        while len(self._entries) > 1:
            over_count = len(self._entries) > self._size
            total = sum(entry.held_bytes for entry in self._entries.values())
            over_bytes = self._max_bytes is not None and total > self._max_bytes
            if not (over_count or over_bytes):
                return
            oldest = next(key for key in self._entries if key != used)
            self._drop(oldest)

    def _drop(self, key: tuple[str, int]) -> None:
        # Caller holds self._lock: forget the entry and the load locks of its (room, version).
        del self._entries[key]
        for lock_key in [k for k in self._key_locks if k[1:3] == key]:
            del self._key_locks[lock_key]

    def _key_lock(self, key: tuple[object, ...]) -> threading.Lock:
        with self._lock:
            return self._key_locks.setdefault(key, threading.Lock())


def held_bytes(*roots: object) -> int:
    """Bytes of the arrays reachable from ``roots``, each buffer counted once (views and
    sparse arrays that share index arrays count what they share once).

    Follows builtin containers, numpy arrays, scipy's sparse arrays and the attributes of the
    service's own objects (classes of :mod:`app`), nothing else: a solver's references to
    modules, functions or numba's compiled kernels are not its memory.
    """
    seen: set[int] = set()
    buffers: set[int] = set()
    total = 0
    pending: list[object] = list(roots)
    while pending:
        obj = pending.pop()
        if id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            owner = obj
            while isinstance(owner.base, np.ndarray):
                owner = owner.base
            if id(owner) not in buffers:
                buffers.add(id(owner))
                total += owner.nbytes
        elif isinstance(obj, dict):
            pending.extend(obj.values())
        elif isinstance(obj, list | tuple | set | frozenset):
            pending.extend(obj)
        elif type(obj).__module__.startswith(("app.", "scipy.sparse")):
            pending.extend(getattr(obj, "__dict__", {}).values())
            for cls in type(obj).__mro__:
                for name in getattr(cls, "__slots__", ()):
                    if hasattr(obj, name):
                        pending.append(getattr(obj, name))
    return total


def _new_solver(name: str, fingerprint: Fingerprint, model: Model) -> Solver:
    """The solver ``name`` prepared for ``fingerprint`` and ``model``, its compiled kernels
    loaded first.

    The solvers (and numba, which their kernels load: LLVM and its typing contexts, about
    200 MiB of an API process) are imported here, when a process first prepares a solver,
    not when the app starts: a process that never solves never holds them. The first
    preparation of a process loads every kernel from numba's disk cache
    (:func:`app.vlp.solvers.warm_up`, idempotent), in the worker thread that prepares it,
    so no solve on the event loop waits for a kernel.
    """
    from app.vlp.solvers import make_solver, warm_up

    warm_up()
    return make_solver(name, fingerprint, model)
