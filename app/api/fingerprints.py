"""Fingerprints of a room: versions, metadata, matrix downloads and rebuilds; jobs."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Path, Response, status
from fastapi.responses import FileResponse

from app.errors import MatrixNotFound
from app.schemas import Fingerprint, FingerprintsList, Job, MatrixName
from app.services.matrices import rebuilding_if_corrupt
from app.services.public import fingerprint_public, job_public

from .deps import AdminRole, AnyRole, JobId, RegistryDep, RoomId
from .errors import ApiProblem, ProblemKind, problem_responses

__all__ = ["JOB_ACCEPTED_HEADERS", "JOB_POLL_AFTER_S", "jobs_router", "router"]

# A 202 names the job to poll (Location) and how long to wait before the first poll.
JOB_POLL_AFTER_S = 1
JOB_ACCEPTED_HEADERS: dict[str, Any] = {
    "Location": {"schema": {"type": "string"}, "description": "the job to poll"},
    "Retry-After": {
        "schema": {"type": "integer"},
        "description": "seconds to wait before polling the job",
    },
}

router = APIRouter(prefix="/v1/rooms/{room_id}/fingerprints", tags=["fingerprints"])
jobs_router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

VersionParam = Annotated[
    str,
    Path(
        pattern=r"^(current|[1-9][0-9]{0,17})$",
        description="a version number, or `current` for the one localization uses now",
        examples=["current", "1"],
    ),
]
_BINARY: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the matrix as a NumPy file of float64",
        "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
        "headers": {"ETag": {"schema": {"type": "string"}, "description": "the file's sha256"}},
    }
}


def _version(value: str) -> int | None:
    return None if value == "current" else int(value)


@router.get("", summary="List fingerprint versions", responses=problem_responses(401, 404))
def list_fingerprints(room_id: RoomId, registry: RegistryDep, _role: AnyRole) -> FingerprintsList:
    """The room's fingerprint versions, newest first."""
    registry.get_room(room_id=room_id)
    records = registry.list_fingerprints(room_id=room_id)
    return FingerprintsList(items=[fingerprint_public(record) for record in records])


@router.post(
    "",
    status_code=status.HTTP_202_ACCEPTED,
    summary="Rebuild the fingerprint",
    responses={
        202: {"headers": JOB_ACCEPTED_HEADERS},
        **problem_responses(401, 403, 404),
    },
)
def rebuild_fingerprint(
    room_id: RoomId, response: Response, registry: RegistryDep, _role: AdminRole
) -> Job:
    """Queue a build of the room's current layout (joins a build already queued or running).

    Poll `Location` (the job) until it `succeeded`.
    """
    job = registry.request_build(room_id=room_id)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    response.headers["Retry-After"] = str(JOB_POLL_AFTER_S)
    return job_public(job)


@router.get(
    "/{version}",
    summary="Read fingerprint metadata",
    responses=problem_responses(401, 404, 409, 422),
)
def get_fingerprint(
    room_id: RoomId, version: VersionParam, registry: RegistryDep, _role: AnyRole
) -> Fingerprint:
    """Metadata of one version: sizes, build time, and each stored matrix's shape and sha256.

    `current` answers 409 while no version is ready.
    """
    return fingerprint_public(registry.get_fingerprint(room_id=room_id, version=_version(version)))


def _matrix_file(
    registry: RegistryDep, room_id: str, version: str, name: str, file_format: str
) -> FileResponse:
    record = registry.get_fingerprint(room_id=room_id, version=_version(version))
    info = record.matrices.get(name)
    if info is None:
        raise MatrixNotFound(
            f"{name} of version {record.version} is not materialised (too "
            "large); H and the LEDs' pilot amplitudes define it exactly",
            field="matrix",
        )
    if info.format != file_format:
        raise ApiProblem(
            409,
            f"{name} of version {record.version} is stored as .{info.format}; "
            f"download {name}.{info.format}",
            kind=ProblemKind.MATRIX_FORMAT,
        )
    with rebuilding_if_corrupt(registry, room_id=room_id):
        path = registry.matrix_path(room_id=room_id, version=record.version, name=name)
    headers = {"ETag": f'"{info.sha256}"', "Cache-Control": "private, max-age=31536000, immutable"}
    return FileResponse(
        path,
        media_type="application/octet-stream",
        headers=headers,
        filename=f"{room_id}-v{record.version}-{name}.{file_format}",
    )


@router.get(
    "/{version}/{matrix}.npy",
    summary="Download a matrix (.npy)",
    response_model=None,
    responses={**_BINARY, **problem_responses(401, 404, 409, 422, 503)},
)
def download_matrix(
    room_id: RoomId,
    version: VersionParam,
    matrix: MatrixName,
    registry: RegistryDep,
    _role: AnyRole,
) -> FileResponse:
    """`H` (M x N), `J` (M x N) or `psi` (M(M+1)/2 x N) as a NumPy `.npy` file of float64.

    409 when the matrix is not materialised (psi of a large room) or H is stored sparse
    (then download `H.npz`, a `scipy.sparse.save_npz` file).
    """
    return _matrix_file(registry, room_id, version, matrix.value, "npy")


@router.get(
    "/{version}/H.npz",
    summary="Download a sparse H (.npz)",
    response_model=None,
    responses={**_BINARY, **problem_responses(401, 404, 409, 422, 503)},
)
def download_sparse_gains(
    room_id: RoomId, version: VersionParam, registry: RegistryDep, _role: AnyRole
) -> FileResponse:
    """H of a large room, stored sparse (`scipy.sparse.load_npz` reads it)."""
    return _matrix_file(registry, room_id, version, "H", "npz")


@jobs_router.get("/{job_id}", summary="Read a job", responses=problem_responses(401, 404))
def get_job(job_id: JobId, registry: RegistryDep, _role: AnyRole) -> Job:
    """A build or calibration job: its status, progress and, once succeeded, the fingerprint
    version (and for a calibration job the calibration id)."""
    return job_public(registry.get_job(job_id=job_id))
