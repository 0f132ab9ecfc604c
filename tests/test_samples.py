"""The study's five prepared samples as shipped (`samples/regenerated/`): issue 5's checks, read
from the files by the code behind `benchmarks/sample_table.py` (`Prepare.finish` on the loaded
state), so that the README's table of these samples is checked on every run.

The layers are read by each course's highest grain (where a plate lowered onto it would rest):
the reading the full-size samples meet (README, "The five prepared samples"; the 99th-percentile
and equal-volume readings of the surface course do not)."""
import pathlib

import pytest

from tcd import config

ROOT = pathlib.Path(__file__).resolve().parents[1]
SAMPLES = sorted((ROOT / "samples" / "regenerated").glob("leutner_seed*_prepared.h5"))


@pytest.fixture(scope="module")
def samples(benchmark_script):
    table = benchmark_script("sample_table")
    scn = config.load_scenario(ROOT / "scenarios" / "leutner_prepare.toml")
    stage = next(s for s in scn.stages if s.kind == "prepare")
    return stage, [table.sample_numbers(scn, path) for path in SAMPLES]


def test_five_samples_are_shipped():
    assert [p.name for p in SAMPLES] == [f"leutner_seed{k}_prepared.h5" for k in range(1, 6)]


def test_counts_follow_the_count_rule(samples):
    stage, rows = samples
    counts = [stage.layer_particle_count(c) for c in stage.courses]
    for s in rows:
        assert s["particles_per_layer"] == counts, s["seed"]
        assert s["particles"] == sum(counts)


def test_size_packing_overlap_containment(samples):
    _, rows = samples
    for s in rows:
        assert s["diameter_mm"] == pytest.approx(150.0) and s["sample_height_mm"] == pytest.approx(120.0)
        assert 0.57 <= s["packing_fraction"] <= 0.61, s["seed"]
        assert s["outside"] == 0 and s["max_overlap_ratio"] < 0.01, s["seed"]
        # read by the grains: the sample is 150 mm by 120 mm within the layers' 2 mm, at a
        # packing still inside the range
        assert 118.0 <= s["highest_grain_top_mm"] <= 120.0 + 0.02, s["seed"]
        assert 0.57 <= s["packing_fraction_below_highest_grain"] <= 0.61, s["seed"]


def test_layers_by_their_highest_grain(samples):
    _, rows = samples
    for s in rows:
        for h in s["course_heights_by_highest_grain_mm"]:
            assert h == pytest.approx(60.0, abs=2.0), s["seed"]
        assert sum(s["course_heights_by_highest_grain_mm"]) == pytest.approx(s["highest_grain_top_mm"],
                                                                             rel=1e-12)
