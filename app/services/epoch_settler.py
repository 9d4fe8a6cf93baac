"""Closing and solving epochs, exactly once across every API process.

:class:`EpochSettler` claims an epoch in the registry (a conditional update that only one
process wins, see :mod:`app.registry.epochs`), sums its terminals' amplitudes, solves on the
epoch's fingerprint version through the same path as localize
(:func:`app.services.localization.localize_terminals`),
labels every estimate with its terminal, updates the room's tracks at the epoch's close time
(unless created with ``track: false``), and records the outcome under its claim.

Windows close in three ways: an explicit ``solve``; a read of an open epoch whose window
has passed (lazily); and the sweeper of each API process (:class:`app.jobs.EpochSweeper`),
which settles due epochs every ``epoch_sweep_seconds``. A process that dies mid-solve leaves
a ``solving`` epoch whose claim (a lease of ``epoch_solve_lease_seconds``) runs out; the next
sweep or read anywhere takes it over, up to ``epoch_max_solve_attempts`` claims.
"""

from __future__ import annotations

import logging
import os
import socket
import uuid
from datetime import timedelta

from app.clock import Clock
from app.errors import RecordNotFound, RegistryError, RegistryUnavailable, VLPError
from app.registry import Registry
from app.registry.records import ClaimedEpoch, EpochRecord
from app.schemas.statuses import EPOCH_FINAL_STATUSES
from app.settings import Settings
from app.telemetry import Metrics
from app.vlp.measurements import Model

from .fingerprint_cache import FingerprintCache
from .localization import censored_terminal_set, localize_terminals
from .tracking import Tracking

__all__ = ["EpochSettler"]

_log = logging.getLogger(__name__)
_SWEEP_BATCH = 32
# Finished epochs are purged at most this often (a write transaction; no need every sweep).
_PURGE_INTERVAL_S = 60.0


class EpochSettler:
    """Settles (expires or solves) the epochs of one API process; thread-safe.

    Windows, claims and the purge schedule follow ``clock`` (the registry's when None).
    """

    def __init__(
        self,
        *,
        registry: Registry,
        cache: FingerprintCache,
        metrics: Metrics,
        settings: Settings,
        clock: Clock | None = None,
        tracking: Tracking | None = None,
    ) -> None:
        self._registry = registry
        self._tracking = tracking
        self._cache = cache
        self._metrics = metrics
        self._settings = settings
        self._clock = registry.clock if clock is None else clock
        self.owner = f"{socket.gethostname()[:30]}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self._next_purge = 0.0

    def settle(self, *, room_id: str, epoch_id: str, force: bool) -> EpochRecord:
        """Solve or expire the epoch if it is due (or ``force``: an explicit ``solve``) and
        nobody else does; the epoch as it is afterwards.

        Raises
        ------
        EpochNotFound, RegistryUnavailable
        """
        record = self._registry.epochs.get(room_id=room_id, epoch_id=epoch_id)
        now = self._clock.now()
        due = record.status == "solving" or (record.status == "open" and record.expires_at <= now)
        if record.status in EPOCH_FINAL_STATUSES or not (force or due):
            return record  # nothing to do: no write transaction for a plain read
        claimed = self._registry.epochs.claim(
            room_id=room_id,
            epoch_id=epoch_id,
            owner=self.owner,
            now=now,
            lease_s=self._settings.epoch_solve_lease_seconds,
            max_attempts=self._settings.epoch_max_solve_attempts,
            force=force,
        )
        if claimed is not None:
            self._conclude(claimed)
        return self._registry.epochs.get(room_id=room_id, epoch_id=epoch_id)

    def sweep(self) -> int:
        """Settle the due epochs (and, once a minute, purge finished ones older than
        ``epoch_retention_seconds``); how many of the due epochs are closed afterwards."""
        settled = 0
        for room_id, epoch_id in self._registry.epochs.due(
            now=self._clock.now(), limit=_SWEEP_BATCH
        ):
            try:
                record = self.settle(room_id=room_id, epoch_id=epoch_id, force=False)
            except RecordNotFound:
                continue  # its room was deleted meanwhile
            settled += record.status != "solving"
        if self._clock.monotonic() >= self._next_purge:
            self._next_purge = self._clock.monotonic() + _PURGE_INTERVAL_S
            retention = timedelta(seconds=self._settings.epoch_retention_seconds)
            self._registry.epochs.purge(finished_before=self._clock.now() - retention)
        return settled

    def _conclude(self, claimed: ClaimedEpoch) -> None:
        record = claimed.record
        if len(claimed.terminal_ids) < record.settings.min_terminals:
            self._finish(claimed, "expired")
            return
        try:
            localization = self._solve(claimed)
        except RegistryUnavailable:
            raise  # the claim runs out and another attempt takes it over
        except (VLPError, RegistryError) as exc:
            self._finish(claimed, "failed", error=str(exc))
            return
        except Exception:
            # An unforeseen error would fail the same way on every attempt: record it once.
            _log.exception("epoch solve crashed", extra={"epoch_id": record.id})
            self._finish(claimed, "failed", error="the solver crashed; see the server log")
            return
        self._finish(claimed, "solved", localization=localization)

    def _solve(self, claimed: ClaimedEpoch) -> dict[str, object]:
        settings = claimed.record.settings
        model: Model = "power" if settings.model == "power" else "correlation"
        localization = localize_terminals(
            self._cache,
            self._metrics,
            room_id=claimed.record.room_id,
            version=settings.fingerprint_version,
            model=model,
            solver=settings.solver,
            targets=settings.targets,
            terminals=censored_terminal_set(
                claimed.terminal_ids, claimed.amplitudes, claimed.detection_floors
            ),
            max_work=self._settings.max_localize_work,
        )
        if settings.track and self._tracking is not None:
            # The epoch's estimates hold at its close: its window's end, or now if solved early.
            closed_at = min(self._clock.now(), claimed.record.expires_at)
            localization = self._tracking.track(
                room_id=claimed.record.room_id, localization=localization, time=closed_at
            )
        return localization.model_dump(mode="json")

    def _finish(
        self,
        claimed: ClaimedEpoch,
        status: str,
        *,
        localization: dict[str, object] | None = None,
        error: str | None = None,
    ) -> None:
        kept = self._registry.epochs.finish(
            claimed=claimed,
            status=status,
            now=self._clock.now(),
            localization=localization,
            error=error,
        )
        if kept:
            self._metrics.epochs.labels(status=status).inc()
        else:
            _log.warning(
                "epoch claim lost before its outcome was stored",
                extra={"epoch_id": claimed.record.id},
            )
