"""What a bias looks like in the residual (calib.bias): a lag, slow structure along the
track; on real-kind flights (``realkind``), through the API, the pipeline and the CLI."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from maglog.calib import bias
from maglog.calib.bias import check_residual, undo_lag
from maglog.calib.scalar import apply_scalar, calibrate_scalar
from maglog.cli.main import main

sys.path.insert(0, str(Path(__file__).parent))
import realkind  # noqa: E402


def checked(flight):
    result = calibrate_scalar(flight.b, flight.r)
    vectors = apply_scalar(result.K, result.c, flight.b)
    return check_residual(flight.t, vectors, flight.r, result.kept), result


#: A compensation flight's manoeuvres with a good installation (3 nT of interference):
#: the kind of flight where a lag matters.
MANOEUVRES = dict(manoeuvres=True, noise_nT=3.0)


@pytest.mark.parametrize("kind", ["survey", "manoeuvres"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_clean_flights_raise_no_warning(kind, seed):
    flight = realkind.flight(seed=seed, **({} if kind == "survey" else MANOEUVRES))
    check, _ = checked(flight)
    assert check.warnings == []
    assert abs(check.lag_vector_z) < bias.LAG_Z and abs(check.lag_reference_z) < bias.LAG_Z
    assert check.slow_rms_nT < 2 * check.slow_expected_nT


@pytest.mark.parametrize("lag_ms", [50, 100, 200])
def test_a_lagging_magnetometer_is_found(lag_ms):
    flight = realkind.flight(seed=1, lag_s=lag_ms / 1e3, lag_on="magnetometer", **MANOEUVRES)
    check, _ = checked(flight)
    assert len(check.warnings) == 1, check.warnings
    assert "the magnetometer's axes lag the field by about" in check.warnings[0]
    assert "--mag-lag" in check.warnings[0]
    assert check.lag_vector_z >= bias.LAG_Z
    # The estimate is a little short: the fit absorbs part of the lag's shape.
    assert 0.7 * lag_ms <= 1e3 * check.lag_vector_s <= 1.1 * lag_ms


def test_a_lagging_reference_is_found():
    # A reference that changes fast (narrow anomalies under a low flight) 200 ms late.
    kind = dict(seed=1, anomaly_nT=100.0, anomaly_width_m=(60.0, 150.0), **MANOEUVRES)
    check, _ = checked(realkind.flight(lag_s=0.2, **kind))
    assert len(check.warnings) == 1, check.warnings
    assert "the reference lags the magnetometer by about" in check.warnings[0]
    assert 100 <= 1e3 * check.lag_reference_s <= 220
    clean, _ = checked(realkind.flight(**kind))
    assert clean.warnings == []


def test_a_constant_reference_over_anomalies_is_found():
    flight = realkind.flight(seed=0, anomaly_nT=100.0, constant_reference=True)
    check, result = checked(flight)
    assert len(check.warnings) == 1, check.warnings
    assert "the residual holds slow structure along the track" in check.warnings[0]
    assert check.slow_rms_nT > bias.SMOOTH_RATIO * check.slow_expected_nT
    # The same flight against a reference that sees the anomalies: no warning.
    seen, _ = checked(realkind.flight(seed=0, anomaly_nT=100.0))
    assert seen.warnings == []


def test_undoing_a_lag_restores_the_flight():
    rate = 10.0
    t = np.arange(2000) / rate
    x = np.column_stack([np.sin(0.7 * t), np.cos(0.3 * t), np.sin(1.1 * t + 1)]) * 1000
    lagged = np.column_stack([realkind.first_order_lag(x[:, i], rate, 0.1) for i in range(3)])
    error_before = np.max(np.abs(lagged - x)[50:-50])
    error_after = np.max(np.abs(undo_lag(lagged, t, 0.1) - x)[50:-50])
    assert error_after < 0.02 * error_before
    assert np.array_equal(undo_lag(x, t, 0.0), x)


def test_short_or_timeless_residuals_say_nothing():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(50, 3)) * 30_000
    r = np.linalg.norm(u, axis=1)
    assert check_residual(np.arange(50.0), u, r).warnings == []
    t = np.arange(500.0)
    t[10] = t[9]                    # a time that does not increase: no lag can be judged
    u = rng.normal(size=(500, 3)) * 30_000
    assert check_residual(t, u, np.linalg.norm(u, axis=1)).warnings == []


@pytest.mark.parametrize("value,message", [(-0.01, "0 to 2000 ms"), (3.0, "0 to 2000 ms"),
                                           (float("nan"), "0 to 2000 ms"),
                                           ("x", "a number of seconds")])
def test_check_lag_refuses(value, message):
    with pytest.raises(ValueError, match=message):
        bias.check_lag(value)


def test_the_pipeline_warns_and_the_option_undoes_the_lag(tmp_path, capsys):
    flight = realkind.flight(seed=1, lag_s=0.1, lag_on="magnetometer", **MANOEUVRES)
    log = tmp_path / "LOG00001.TXT"
    log.write_bytes(flight.log())
    assert main(["calibrate", str(log), "--out", str(tmp_path / "r1")]) == 0
    printed = capsys.readouterr().out
    assert "warning: the residual follows the square of the field vector's rate" in printed
    summary = json.loads((tmp_path / "r1" / "parameters.json").read_text())
    lag = [w for w in summary["warnings"] if "--mag-lag" in w]
    assert len(lag) == 1
    assert "lag" in (tmp_path / "r1" / "report.md").read_text()
    estimate = lag[0].split("--mag-lag ")[1].split(")")[0]
    assert main(["calibrate", str(log), "--mag-lag", "100", "--out",
                 str(tmp_path / "r2")]) == 0
    undone = json.loads((tmp_path / "r2" / "parameters.json").read_text())
    assert not any("--mag-lag" in w for w in undone["warnings"])
    assert any("lags undone before the fit: magnetometer 100 ms" in w
               for w in undone["warnings"])
    assert undone["rms_after_nT"] < 0.6 * summary["rms_after_nT"]
    assert 70 <= float(estimate) <= 110


def test_the_option_is_checked(tmp_path, capsys):
    log = tmp_path / "LOG00001.TXT"
    log.write_bytes(realkind.flight(seed=1, n=200).log())
    with pytest.raises(SystemExit) as exit:
        main(["calibrate", str(log), "--ref-lag", "-5", "--out", str(tmp_path / "r")])
    assert exit.value.code == 2
    assert "--ref-lag: expected a number in [0, 2000]" in capsys.readouterr().err


@pytest.mark.slow
def test_false_alarm_and_detection_rates():
    """Over 50 seeds each (about 30 s): no warning on clean flights (the survey kind, the
    manoeuvre kind, the survey kind over +-100 nT anomalies its reference sees); every
    magnetometer lag of 50-200 ms on the manoeuvre flight found; a reference 200 ms late
    over narrow anomalies, and a constant reference over +-100 nT anomalies, nearly always.
    Measured at issue 24: 0/150 false alarms; lags 150/150; reference lag 49/50; constant
    reference 45/50 (the five missed: the fit absorbed the anomalies into K and c, ~55 nT of
    calibrated-field error that the residual cannot show)."""
    seeds = range(50)

    def warned(what, **kind):
        return sum(any(what in w for w in checked(realkind.flight(seed=s, **kind))[0].warnings)
                   for s in seeds)

    false = (warned("") + warned("", **MANOEUVRES) + warned("", anomaly_nT=100.0))
    lags = sum(warned("lag the field", lag_s=lag, lag_on="magnetometer", **MANOEUVRES)
               for lag in (0.05, 0.1, 0.2))
    late = warned("reference lags", lag_s=0.2, anomaly_nT=100.0,
                  anomaly_width_m=(60.0, 150.0), **MANOEUVRES)
    slow = warned("slow structure", anomaly_nT=100.0, constant_reference=True)
    assert false == 0 and lags >= 147 and late >= 45 and slow >= 43, (false, lags, late,
                                                                         slow)
