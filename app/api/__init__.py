"""The HTTP layer: routers (one per resource), dependencies, errors, security, metrics, docs."""

from fastapi import APIRouter

from . import (
    calibrations,
    epochs,
    fingerprints,
    health,
    keys,
    localize,
    localize_batch,
    pictures,
    rooms,
    simulate,
    tracks,
    view,
)

__all__ = ["api_router"]

api_router = APIRouter()
api_router.include_router(health.router)
# A request is matched against the routes in this order: the hot localize routes come
# before the others (no other route's path matches theirs, and the document sorts its paths,
# so it does not depend on this order).
api_router.include_router(localize.router)
api_router.include_router(localize_batch.router)
api_router.include_router(rooms.router)
api_router.include_router(fingerprints.router)
api_router.include_router(fingerprints.jobs_router)
api_router.include_router(simulate.router)
api_router.include_router(epochs.router)
api_router.include_router(pictures.router)
api_router.include_router(calibrations.router)
api_router.include_router(tracks.router)
api_router.include_router(keys.router)
api_router.include_router(view.router)
