"""The batch path (calib/batch.py): four seeds of a short survey flown through the logger
(model backend: real card images) and reduced on a local Dask cluster of two workers, then
the same four cards reduced serially in this process: the maps and samples are identical
(digests of the float64 arrays), and so are the figures."""

import pytest

from maglog.calib.batch import run_batch, survey_job
from maglog.sim.stimulus.config import default_scenario_path

pytestmark = pytest.mark.slow


def short_toml(folder):
    text = default_scenario_path().with_name("survey.toml").read_text()
    for old, new in (("legs = 8", "legs = 4"), ("leg_length_m = 300.0", "leg_length_m = 200.0"),
                     ("tie_lines = 3", "tie_lines = 2")):
        assert old in text
        text = text.replace(old, new)
    path = folder / "short-survey.toml"
    path.write_text(text)
    return path


def test_dask_gives_the_serial_maps(tmp_path):
    scenario = short_toml(tmp_path)
    options = {"compare_deinterf": False}
    jobs = [{"scenario": str(scenario), "seed": seed, "out": str(tmp_path / f"seed-{seed}"),
             "options": options} for seed in (1, 2, 3, 4)]
    dask_records = run_batch(jobs, workers=2)
    assert all(r["ok"] for r in dask_records), [r["error"] for r in dask_records]
    digests = {r["digest"] for r in dask_records}
    assert len(digests) == 4                      # four different flights
    for record in dask_records:
        folder = tmp_path / record["name"]
        serial = survey_job({"card": str(folder / "card.img"), "out": str(folder / "serial"),
                             "options": dict(options, truth=str(folder / "truth.json"),
                                             base_station=str(folder / "base.csv"))})
        assert serial["ok"], serial["error"]
        assert serial["digest"] == record["digest"]
        for key in ("compensation", "levelling", "peak", "truth", "grid"):
            assert serial["figures"][key] == record["figures"][key], key
        assert record["figures"]["truth"]["peak"]["amplitude_ratio"] == pytest.approx(
            1.0, abs=0.15)
