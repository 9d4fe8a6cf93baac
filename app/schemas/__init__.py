"""Public request and answer bodies of the HTTP API (pydantic)."""

from .batch import MAX_BATCH_ITEMS, LocalizationBatch, MeasurementBatch
from .calibrations import (
    Calibration,
    CalibrationCreate,
    CalibrationsList,
    LedCalibration,
    SurveyRow,
)
from .epochs import Epoch, EpochCreate, EpochMeasurement
from .fingerprints import Fingerprint, FingerprintsList, Job, JobResult, MatrixMeta, MatrixName
from .keys import ApiKey, ApiKeyCreate, ApiKeyCreated, ApiKeysList
from .localize import (
    Estimate,
    Fit,
    Localization,
    Measurement,
    ModelName,
    SolverName,
    TerminalAmplitudes,
)
from .pictures import LocalizationPlot, PlotPoint
from .problems import FieldError, Problem
from .rooms import (
    FingerprintState,
    GridSpec,
    LedSpec,
    ReceiverSpec,
    Room,
    RoomBox,
    RoomLayout,
    RoomsPage,
    SurfaceReflectance,
)
from .simulate import Simulation, SimulationRequest, TruthTarget
from .statuses import EpochStatus
from .tracking import (
    AccuracyMap,
    RawFix,
    Track,
    TrackedState,
    TrackingSettings,
    TrackingSettingsUpdate,
    TrackPoint,
    TrackPointsPage,
    TrackRemoved,
    TracksPage,
    TrackStatus,
)

__all__ = [
    "MAX_BATCH_ITEMS",
    "AccuracyMap",
    "ApiKey",
    "ApiKeyCreate",
    "ApiKeyCreated",
    "ApiKeysList",
    "Calibration",
    "CalibrationCreate",
    "CalibrationsList",
    "Epoch",
    "EpochCreate",
    "EpochMeasurement",
    "EpochStatus",
    "Estimate",
    "FieldError",
    "Fingerprint",
    "FingerprintState",
    "FingerprintsList",
    "Fit",
    "GridSpec",
    "Job",
    "JobResult",
    "LedCalibration",
    "LedSpec",
    "Localization",
    "LocalizationBatch",
    "LocalizationPlot",
    "MatrixMeta",
    "MatrixName",
    "Measurement",
    "MeasurementBatch",
    "ModelName",
    "PlotPoint",
    "Problem",
    "RawFix",
    "ReceiverSpec",
    "Room",
    "RoomBox",
    "RoomLayout",
    "RoomsPage",
    "Simulation",
    "SimulationRequest",
    "SolverName",
    "SurfaceReflectance",
    "SurveyRow",
    "TerminalAmplitudes",
    "Track",
    "TrackPoint",
    "TrackPointsPage",
    "TrackRemoved",
    "TrackStatus",
    "TrackedState",
    "TrackingSettings",
    "TrackingSettingsUpdate",
    "TracksPage",
    "TruthTarget",
]
