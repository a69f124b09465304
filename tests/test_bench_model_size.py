"""The model-size sweep's bookkeeping: where the knee is and whether the auto size sits at it (no training)."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "recipes"))

import bench_model_size as B  # noqa: E402


def _run(data: str, capacity: float, params: int, psnr: float) -> dict:
    return {"data": data, "capacity": capacity, "params": params, "psnr": psnr, "auto": capacity == 1.0}


def test_knee_is_the_smallest_model_within_half_a_db_of_the_best():
    runs = [_run("small", 0.25, 300_000, 24.0), _run("small", 0.5, 1_200_000, 26.8), _run("small", 1.0, 4_500_000, 27.1),
            _run("small", 2.0, 18_000_000, 27.0),
            _run("large", 0.25, 300_000, 20.0), _run("large", 0.5, 1_200_000, 22.0), _run("large", 1.0, 4_500_000, 24.0),
            _run("large", 2.0, 18_000_000, 24.3)]
    k = {row["data"]: row for row in B.knees(runs)}
    assert k["small"]["knee_capacity"] == 0.5 and k["small"]["best_capacity"] == 1.0
    assert k["small"]["auto_at_knee"] is False and k["small"]["auto_over_knee"] == 3.75
    assert k["small"]["auto_gap_db"] == 0.0
    assert k["large"]["knee_capacity"] == 1.0 and k["large"]["auto_at_knee"] is True
    assert k["large"]["auto_gap_db"] == 0.3


def test_knees_skip_rooms_without_results():
    runs = [_run("medium", 1.0, 4_500_000, 25.0), {"data": "large", "capacity": 1.0, "params": 10, "psnr": None,
                                                   "auto": True}]
    rows = B.knees(runs)
    assert [r["data"] for r in rows] == ["medium"] and rows[0]["auto_at_knee"] is True
