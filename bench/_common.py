"""What both benchmarks share: the machine record, solver discovery, CSV and doc sections."""

from __future__ import annotations

import csv
import datetime as dt
import importlib
import os
import pkgutil
import platform
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np
import scipy
from threadpoolctl import threadpool_info

import app.vlp.solvers as solvers_pkg

__all__ = [
    "REPO_ROOT",
    "load_solvers",
    "machine_markdown",
    "machine_record",
    "replace_section",
    "write_csv",
]

REPO_ROOT = Path(__file__).resolve().parent.parent


def load_solvers() -> list[str]:
    """Import every module of :mod:`app.vlp.solvers` (so each registers) and list the names.

    Returns
    -------
    names : list of str
        Registered solver names, the default first.
    """
    for module in pkgutil.iter_modules(solvers_pkg.__path__):
        importlib.import_module(f"{solvers_pkg.__name__}.{module.name}")
    return solvers_pkg.solver_names()


def _cpu_model() -> str:
    try:
        text = Path("/proc/cpuinfo").read_text(encoding="utf-8")
    except OSError:
        return platform.processor() or "unknown"
    for line in text.splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def machine_record() -> dict[str, str]:
    """Date, CPU, cores, library versions and BLAS set-up of this run."""
    blas = [
        f"{info.get('internal_api')} {info.get('version')} "
        f"({info.get('architecture')}, {info.get('num_threads')} threads)"
        for info in threadpool_info()
        if info.get("user_api") == "blas"
    ]
    return {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "cpu": _cpu_model(),
        "cores": str(os.cpu_count() or 1),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "blas": "; ".join(blas) or "unknown",
        "OPENBLAS_CORETYPE": os.environ.get("OPENBLAS_CORETYPE", "(unset)"),
    }


def machine_markdown(record: Mapping[str, str]) -> str:
    """The machine record as a markdown bullet list."""
    return "\n".join(f"- {key}: `{value}`" for key, value in record.items())


def measured_section(heading: str, lead: str, table: str) -> str:
    """A generated docs section: ``heading``, the paragraph ``lead`` (the command and what
    it measured), the machine it ran on and when (:func:`machine_record`), then ``table``."""
    return "\n".join(
        [heading, "", lead, "", "Machine:", "", machine_markdown(machine_record()), "", table, ""]
    )


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> None:
    """Write ``rows`` under ``header`` to ``path`` (parents created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(header)
        writer.writerows(rows)


def replace_section(path: Path, tag: str, body: str, *, preamble: str) -> None:
    """Put ``body`` between ``<!-- tag:start -->`` and ``<!-- tag:end -->`` in ``path``.

    Text outside the markers (hand-written discussion, other people's sections) is kept.
    A missing file starts as ``preamble``; missing markers are appended at the end.
    """
    start, end = f"<!-- {tag}:start -->", f"<!-- {tag}:end -->"
    text = path.read_text(encoding="utf-8") if path.exists() else preamble
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text and end in text:
        head, rest = text.split(start, 1)
        tail = rest.split(end, 1)[1]
        text = head + block + tail
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
