"""Batches of measurements (body of localize/batch) and their answers."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import ConfigDict, Field, WithJsonSchema

from .common import RequestModel, ResponseModel, lazy_examples
from .localize import Localization, localize_example
from .problems import Problem

__all__ = ["MAX_BATCH_ITEMS", "LocalizationBatch", "MeasurementBatch"]

# Measurements per batch request (API.md); more answer 422 naming `body.items`.
MAX_BATCH_ITEMS = 1000

# Each item is checked as a `Measurement` by the handler, one by one, so that a bad item
# becomes a problem in its place instead of failing the whole batch; the document shows it
# as the `Measurement` it must be.
MeasurementItem = Annotated[Any, WithJsonSchema({"$ref": "#/components/schemas/Measurement"})]


def batch_example() -> dict[str, Any]:
    """Two measurements of the paper room: the localize example, and the same solved by `omp`."""
    return {"items": [localize_example(), {**localize_example(), "solver": "omp"}]}


class MeasurementBatch(RequestModel):
    """Up to 1000 measurements of one room, each as the body of a single localize."""

    model_config = ConfigDict(json_schema_extra=lazy_examples(batch_example))

    items: list[MeasurementItem] = Field(
        min_length=1,
        max_length=MAX_BATCH_ITEMS,
        description=f"1 to {MAX_BATCH_ITEMS} `Measurement` objects, answered in this order",
    )


class LocalizationBatch(ResponseModel):
    """The answers to a batch, in the order of its items: each a `Localization`, or the
    problem (with its `status`) that a single localize of that item would have answered."""

    items: list[Localization | Problem]
