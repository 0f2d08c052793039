"""The default scenario's log calibrates back to its error model (paper A's Table 1)."""

from __future__ import annotations

import numpy as np
from maglog.calib.pipeline import calibrate_card


def test_default_log_recovers_table_1(default_stim, tmp_path):
    """The log the default scenario implies (SystemScenario.recorded_frames), calibrated
    against its cesium channel by PSO + LM: K and c within 4 standard deviations of the
    truth, the offset b = P c within 4 σ, and the residual at the noise floor."""
    path = tmp_path / "LOG00001.TXT"
    path.write_bytes(b"".join(default_stim.system.recorded_frames()))
    run = calibrate_card(path, ref="cesium", method="pso", seed=0)
    truth = default_stim.truth
    k, c = np.array(truth["errors"]["K"]), np.array(truth["errors"]["c"])
    result = run.result
    sigma = result.uncertainties
    assert np.all(np.abs(result.K[np.triu_indices(3)] - k[np.triu_indices(3)]) < 4 * sigma[:6])
    assert np.all(np.abs(result.c - c) < 4 * sigma[6:])
    assert np.abs(result.offset_sensor - truth["errors"]["b"]).max() < 15.0
    floor = truth["noise_floor_nT"]
    summary = run.summary()
    assert summary["rms_before_nT"] > 100 * floor
    assert abs(summary["rms_after_nT"] - floor) < 0.05 * floor
    assert not run.warnings
