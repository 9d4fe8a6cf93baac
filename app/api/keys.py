"""API keys as a resource: create (the secret shown once), list, revoke (admin only)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Response, status

from app.schemas import ApiKeyCreate, ApiKeyCreated, ApiKeysList
from app.services.public import created_key_public, key_public

from .deps import AdminRole, KeysDep, RegistryDep
from .errors import problem_responses
from .security import generate_key, hash_key

__all__ = ["router"]

router = APIRouter(prefix="/v1/keys", tags=["keys"])

KeyId = Annotated[
    str, Path(max_length=64, description="the key's `id` (from `GET /v1/keys`), not the secret")
]


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    summary="Create an API key",
    responses=problem_responses(401, 403, 413, 422),
)
def create_key(body: ApiKeyCreate, registry: RegistryDep, _role: AdminRole) -> ApiKeyCreated:
    """A new random key with the role; its secret is in this answer only.

    It is in force until revoked, in every API process at once.
    """
    key = generate_key()
    record = registry.create_api_key(
        key_hash=hash_key(key), role=body.role, label=body.label, source="api"
    )
    return created_key_public(record, key=key)


@router.get("", summary="List API keys", responses=problem_responses(401, 403))
def list_keys(registry: RegistryDep, _role: AdminRole) -> ApiKeysList:
    """The keys in force (never their secrets), oldest first."""
    return ApiKeysList(items=[key_public(record) for record in registry.list_api_keys()])


@router.delete(
    "/{key_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    summary="Revoke an API key",
    responses=problem_responses(401, 403, 404, 409),
)
def revoke_key(
    key_id: KeyId,
    registry: RegistryDep,
    keys: KeysDep,
    _role: AdminRole,
) -> Response:
    """Revoke a key: from then on it answers 401 here at once, in other API processes
    within 2 s (they re-read a cached key at least once a second).

    The last admin key in force cannot be revoked (409): create another one first.
    """
    record = registry.revoke_api_key(key_id=key_id)
    keys.forget(record.key_hash)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
