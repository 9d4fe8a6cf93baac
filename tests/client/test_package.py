"""The public surface of app.client and of the vlp command's module."""

from __future__ import annotations

import inspect
import subprocess
import sys

import app.cli
import app.client


def test_public_names_are_pinned() -> None:
    assert sorted(app.client.__all__) == [
        "APIError",
        "AuthenticationError",
        "ClientError",
        "Conflict",
        "DEFAULT_TIMEOUT_S",
        "Epoch",
        "FieldProblem",
        "InvalidRequest",
        "Job",
        "JobError",
        "JobFailed",
        "JobTimeout",
        "NotFound",
        "PermissionDenied",
        "PreconditionError",
        "ProgressCallback",
        "ServerError",
        "TrackEvent",
        "TransportError",
        "VLPClient",
    ]
    assert sorted(app.cli.__all__) == [
        "EXIT_NO_ANSWER",
        "EXIT_REFUSED",
        "EXIT_USAGE",
        "main",
        "openapi_document",
    ]


def test_every_api_error_is_a_client_error() -> None:
    errors = [
        value
        for value in vars(app.client).values()
        if inspect.isclass(value) and issubclass(value, app.client.APIError)
    ]
    assert len(errors) == 8
    assert all(issubclass(error, app.client.ClientError) for error in errors)


def test_importing_the_command_loads_no_numerics() -> None:
    """`vlp serve` pins the BLAS threads before numpy loads: the module must not load it."""
    code = "import sys, app.cli; print(sorted({'numpy', 'httpx', 'rich'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
