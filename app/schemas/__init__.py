"""Public request and answer bodies of the HTTP API (pydantic)."""

from .epochs import Epoch, EpochCreate, EpochMeasurement, EpochStatus
from .fingerprints import Fingerprint, FingerprintsList, Job, JobResult, MatrixMeta, MatrixName
from .localize import (
    SOLVER_NAMES,
    Estimate,
    Localization,
    Measurement,
    ModelName,
    SolverName,
    TerminalAmplitudes,
)
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
)
from .simulate import Simulation, SimulationRequest, TruthTarget

__all__ = [
    "SOLVER_NAMES",
    "Epoch",
    "EpochCreate",
    "EpochMeasurement",
    "EpochStatus",
    "Estimate",
    "FieldError",
    "Fingerprint",
    "FingerprintState",
    "FingerprintsList",
    "GridSpec",
    "Job",
    "JobResult",
    "LedSpec",
    "Localization",
    "MatrixMeta",
    "MatrixName",
    "Measurement",
    "ModelName",
    "Problem",
    "ReceiverSpec",
    "Room",
    "RoomBox",
    "RoomLayout",
    "RoomsPage",
    "Simulation",
    "SimulationRequest",
    "SolverName",
    "TerminalAmplitudes",
    "TruthTarget",
]
