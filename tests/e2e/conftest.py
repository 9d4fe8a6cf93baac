"""End-to-end fixtures: one README checkout and live server per test module."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from .readme_blocks import Checkout, readme_checkout

__all__ = ["checkout"]


@pytest.fixture(scope="module")
def checkout(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Checkout]:
    """A scratch checkout beside a live server started with no keys, shared by the tests of
    one module: the README's blocks run one after another against one service, as a reader
    runs them. A test that changes the checkout puts it back."""
    with readme_checkout(tmp_path_factory.mktemp("readme") / "checkout") as shared:
        yield shared
