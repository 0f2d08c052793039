"""A calibration flight recorded by the firmware on the logger model, then calibrated: the
whole chain of DESIGN.md's data flow on the fast backend — the card the firmware wrote is
judged by fsck.fat, mtools, pyfatfs and calib.card, and `maglog calibrate` reduces it."""

import json

from maglog.cli.main import main
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.logger import run_system
from maglog.sim.stimulus.scenario import make_flight
from maglog.sim.stimulus.system import flight_scenario
from maglog.sw.app import LoggerApp
from maglog.sw.fat32 import format_image

from ..sw.test_fat32 import judge


async def firmware(bus, memory_map, sys_clock_hz):
    await LoggerApp(bus, memory_map, sys_clock_hz=sys_clock_hz).run()


def test_a_flight_the_firmware_recorded_calibrates(tmp_path, fat_tools, external, capsys):
    flight = make_flight(seconds=60)
    scenario = flight_scenario(flight)
    blank = tmp_path / "blank.img"
    format_image(blank, 300 << 20, cluster_bytes=4096, volume_id=0x4D474C47)
    image = CardImage.load(blank)
    result = run_system(scenario, firmware, image)
    assert result.led & 0b0001 == 0                     # LED1 off: recording stopped
    card = tmp_path / "card.img"
    image.save(card)
    frames = scenario.recorded_frames()
    assert len(frames) == len(flight.log().splitlines())
    judge(card, {"LOG00001.TXT": b"".join(frames)}, tmp_path, fat_tools, external)

    out = tmp_path / "report"
    assert main(["calibrate", str(card), "--out", str(out)]) == 0
    params = json.loads((out / "parameters.json").read_text())
    assert params["log"] == "LOG00001.TXT" and params["fit_converged"]
    # A minute of a UAV's +-30 deg does not determine the vertical axis's scale and offset:
    # the verdict says so (issue 24), and success is not claimed.
    assert params["verdict"] == "undetermined" and params["success"] is False
    assert {"k33", "c3"} <= set(params["undetermined"])
    # Every magnetometer sample of the flight made it through the logger; the cesium
    # reference covers all but the edges.
    assert params["samples"] >= len(flight.t) - 5
    # The paper's calibration takes the total-field error from hundreds of nT to a few.
    assert params["rms_before_nT"] > 100 and params["rms_after_nT"] < 10, params
    assert "total-field RMS" in capsys.readouterr().out
