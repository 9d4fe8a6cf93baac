"""What the remote commands print: JSON for scripts, rich tables and progress bars for people."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

if TYPE_CHECKING:
    from rich.console import Console
    from rich.table import Table

    from app.client import APIError, Job

__all__ = ["Output"]


def _plain(value: Any) -> Any:
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, list):
        return [_plain(item) for item in value]
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    return value


class Output:
    """Where a command's results go.

    Parameters
    ----------
    as_json : bool
        Print one JSON document on stdout (nothing else) and no progress bars.
    """

    def __init__(self, *, as_json: bool) -> None:
        from rich.console import Console

        self.as_json = as_json
        self.console: Console = Console(file=sys.stdout, soft_wrap=True)
        self.errors: Console = Console(file=sys.stderr, soft_wrap=True)

    def result(self, value: Any, render: Callable[[Any], None] | None = None) -> None:
        """Print a result: as JSON with ``--json``, else with ``render`` (default: JSON too)."""
        if self.as_json or render is None:
            print(json.dumps(_plain(value), indent=2))
        else:
            render(value)

    def table(self, title: str, columns: list[str], rows: list[list[Any]]) -> None:
        """A rich table on stdout."""
        from rich.table import Table

        table: Table = Table(title=title)
        for index, column in enumerate(columns):
            # The first column is an id people copy: never cut it short.
            table.add_column(column, no_wrap=index == 0)
        for row in rows:
            table.add_row(*(str(cell) for cell in row))
        self.console.print(table)

    def problem(self, error: APIError) -> None:
        """Report an error answer: the problem JSON with ``--json``, and a summary on stderr."""
        if self.as_json:
            print(json.dumps(error.problem or {"status": error.status, "title": error.title}))
        self.errors.print(f"[bold red]error[/]: {error}", markup=True, highlight=False)
        for field in error.errors:
            self.errors.print(f"  {field.field}: {field.message}", markup=False)

    def note(self, message: str) -> None:
        """A progress note for people on stderr (stdout stays the result's)."""
        self.errors.print(message, markup=False, highlight=False)

    def failure(self, message: str) -> None:
        """Report a failure that has no problem body (no answer, job failed)."""
        self.errors.print(f"[bold red]error[/]: {message}", markup=True, highlight=False)

    @contextmanager
    def job_progress(self, description: str) -> Iterator[Callable[[Job], None]]:
        """A progress bar (stderr) fed by a ``wait_for_job`` callback; silent with ``--json``."""
        if self.as_json:
            yield lambda _job: None
            return
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn

        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TaskProgressColumn(),
            TextColumn("{task.fields[status]}"),
            console=self.errors,
            transient=False,
        ) as progress:
            task = progress.add_task(description, total=1.0, status="queued")

            def update(job: Job) -> None:
                progress.update(task, completed=job.progress, status=job.status)

            yield update
