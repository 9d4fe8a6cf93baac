"""Tracking of moving terminals: a standing / walking mixture filter per track, gated
association of anonymous fixes, and the tracks' lifecycle, over batches of arrays.

No web or database imports; time is always passed in (seconds), never read from a clock.
"""

from __future__ import annotations

from .filter import (
    N_MODELS,
    TrackBank,
    Update,
    combined,
    estimates,
    predict,
    start_tracks,
    update,
)
from .metrics import Gospa, gospa
from .settings import TrackerSettings
from .tracker import (
    CONFIRMED,
    LOST,
    STATUS_NAMES,
    TENTATIVE,
    Rivals,
    Step,
    Tracks,
    age_tracks,
    associate,
    joined,
    step_anonymous,
    step_labelled,
)

__all__ = [
    "CONFIRMED",
    "LOST",
    "N_MODELS",
    "STATUS_NAMES",
    "TENTATIVE",
    "Gospa",
    "Rivals",
    "Step",
    "TrackBank",
    "TrackerSettings",
    "Tracks",
    "Update",
    "age_tracks",
    "associate",
    "combined",
    "estimates",
    "gospa",
    "joined",
    "predict",
    "start_tracks",
    "step_anonymous",
    "step_labelled",
    "update",
]
