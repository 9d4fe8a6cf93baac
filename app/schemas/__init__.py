"""Public request and answer bodies of the HTTP API (pydantic)."""

from .calibrations import (
    Calibration,
    CalibrationCreate,
    CalibrationsList,
    LedCalibration,
    SurveyRow,
)
from .epochs import Epoch, EpochCreate, EpochMeasurement, EpochStatus
from .fingerprints import Fingerprint, FingerprintsList, Job, JobResult, MatrixMeta, MatrixName
from .keys import ApiKey, ApiKeyCreate, ApiKeyCreated, ApiKeysList
from .localize import (
    SOLVER_NAMES,
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

__all__ = [
    "SOLVER_NAMES",
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
    "LocalizationPlot",
    "MatrixMeta",
    "MatrixName",
    "Measurement",
    "ModelName",
    "PlotPoint",
    "Problem",
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
    "TruthTarget",
]
