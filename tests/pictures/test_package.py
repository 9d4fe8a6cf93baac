"""The public surface of app.pictures and its promise not to touch pyplot."""

from __future__ import annotations

import subprocess
import sys

import app.pictures


def test_public_names_are_pinned() -> None:
    assert sorted(app.pictures.__all__) == [
        "CrlbMap",
        "HeatmapKind",
        "SampleGrid",
        "amplitude_crlb_m",
        "coverage_counts",
        "localization_png",
        "room_map_png",
    ]


def test_rendering_never_imports_pyplot() -> None:
    code = (
        "import sys, numpy as np\n"
        "from app.pictures import localization_png, room_map_png\n"
        "from app.vlp.presets import paper_layout\n"
        "room = paper_layout()\n"
        "room_map_png(room, heatmap='crlb', width_px=300)\n"
        "localization_png(room, np.array([[1.0, 1.0]]), np.array([[1.1, 0.9]]), width_px=300)\n"
        "print('matplotlib.pyplot' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "False"
