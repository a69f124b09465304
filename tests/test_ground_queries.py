"""The grounding benchmark's query sets (recipes/ground_queries.yaml) are well formed: every present query names a
simulated object, each set is big enough to score (issue 60: >= 60 development queries, a third of them absent;
held-out sets of 45), and no query stands twice in a set, so a figure counts what it says."""

from __future__ import annotations

import sys
from pathlib import Path

RECIPES = Path(__file__).resolve().parents[1] / "recipes"
sys.path.insert(0, str(RECIPES))

import bench_ground  # noqa: E402


def test_query_sets_are_well_formed():
    from interreal.synth import SynthConfig, build_scene

    objects = set(build_scene(SynthConfig(parts=10, frames=2, width=32, height=24)).object_names)
    sets = bench_ground.query_sets()
    assert list(sets)[0] == "dev" and len(sets) >= 8
    for name, (present, absent) in sets.items():
        assert set(present) == objects, name
        queries = [q for qs in present.values() for q in qs] + absent
        assert len(queries) == len(set(queries)), name
        assert len(queries) >= (60 if name == "dev" else 45) and len(absent) >= len(queries) / 3 - 1, name
