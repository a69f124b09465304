"""The README's speed-against-accuracy charts (issue 28.3): `recipes/charts.py`, called by `recipes/bench_all.py`."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from PIL import Image

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "recipes"))

import charts  # noqa: E402


def test_charts_prefer_a_fresh_benchmark_json_and_stay_small(tmp_path):
    bench = tmp_path / "bench"
    bench.mkdir()
    runs = [{"size": "160x120", "renderer": "exact", "seconds": 4.0, "psnr_vs_frame": 28.0},
            {"size": "160x120", "renderer": "fast", "seconds": 2.0, "psnr_vs_frame": 27.9}]
    (bench / "render.json").write_text(json.dumps({"benchmark": "render", "runs": runs, "environment": {"cpus": 2}}))
    got, source = charts.chart_source(bench, "render")
    assert got == runs and source.startswith("render.json")
    fallback, source = charts.chart_source(bench, "poses")  # no poses.json: the README's figures
    assert fallback and source.startswith("README figures")
    png = charts.render_chart(got, source, tmp_path / "render.png")
    assert png.stat().st_size < charts.MAX_BYTES
    with Image.open(png) as im:
        assert im.size[0] >= 400 and im.mode == "P"  # palette PNG: small enough for the repository
    assert charts.render_chart([{"size": "160x120", "renderer": "exact"}], source, tmp_path / "none.png") is None


def test_bench_all_skip_run_redraws_the_readme_charts(tmp_path):
    out = tmp_path / "charts"
    res = subprocess.run([sys.executable, str(REPO / "recipes" / "bench_all.py"), "--skip-run", "--out",
                          str(tmp_path / "bench"), "--charts", str(out)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert sorted(p.name for p in out.glob("*.png")) == sorted(f"{n}.png" for n in charts.CHARTS)
    readme = (REPO / "README.md").read_text()
    shown = set(re.findall(r"\(docs/charts/(\w+)\.png\)", readme))
    assert shown == set(charts.CHARTS)
    assert all((REPO / "docs" / "charts" / f"{n}.png").stat().st_size < charts.MAX_BYTES for n in shown)
