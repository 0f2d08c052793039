"""sw/app.py when power returns and on cards others prepared: the recording starts at the
button (frames queue in the ring while the file is created), a full card ends its file on a
frame boundary, and a dirty card is repaired at mount (or stays dirty), never closed clean
over damage.
"""

import subprocess

import pytest

from maglog.calib.card import open_card
from maglog.sim.models.card_image import TracingImage
from maglog.sim.models.logger import LoggerModel
from maglog.sw.app import AppSettings, FwError, State

from .test_app import (blank_card, firmware, logs, long_scenario, model_of, saved,
                       stream_of)
from ..system.test_power_cut import Layout
from .test_fat32 import fsck_findings, mtools_env, partition

MiB = 1 << 20


def mcopy_many(fat_tools, image, files, tmp_path):
    """Copy ``files`` (name → bytes) onto ``image`` with one mcopy call (long names kept)."""
    folder = tmp_path / "upload"
    folder.mkdir(exist_ok=True)
    paths = []
    for name, data in files.items():
        path = folder / name
        path.write_bytes(data)
        paths.append(str(path))
    offset, _ = partition(image)
    subprocess.run([fat_tools["mcopy"], "-i", f"{image}@@{offset}", *paths, "::"],
                   check=True, capture_output=True, env=mtools_env(), timeout=120)


# -- The recording starts at the button -------------------------------------------------------

def many_files():
    """150 files with long names (three directory entries each): the root directory takes
    28 clusters of 512 bytes, and creating a LOG file scans it all and grows it."""
    return {f"calibration flight {k:03d} notes.txt": b"flight %d\r\n" % k
            for k in range(150)}


def test_frames_after_the_button_reach_the_file_on_a_card_with_many_files(tmp_path,
                                                                           fat_tools):
    card = blank_card(tmp_path)
    mcopy_many(fat_tools, card, many_files(), tmp_path)
    # The first magnetometer frame 20 ms after the press (the button's debounce is 10 ms).
    scenario = long_scenario(until=1.2, presses=(0.3, 1.0), start=0.32, stop=0.95)
    model = model_of(scenario, card)
    create = []

    async def watch(app, point):
        if point == "loop" and app.file is not None and not create:
            create.append(app.bus.now())

    start, apps = firmware(model, AppSettings(fault=watch))
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.state == State.IDLE and app.error == FwError.NONE
    # Creating the file took longer than the gap between the press and the first frame.
    assert create and create[0] > 0.32 + 0.005, create
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    assert logs(path)["LOG00001.TXT"] == stream_of(scenario.recorded_frames())


# -- Power returns: a dirty card is repaired at mount -----------------------------------------

def test_power_returns_the_dirty_card_is_repaired_before_it_is_closed_clean(tmp_path,
                                                                             fat_tools):
    # Cut the power mid-recording at instants that leave damage (a chain longer than the
    # file, lost clusters, FATs that differ, a stale free count), power up, record again
    # and stop: the card closes clean only over a repaired volume, so fsck finds nothing,
    # and the first file keeps every byte synced before the cut.
    first = long_scenario(until=1.2, presses=(0.3, 1.0), stop=0.95)
    # The repair at power-up reads both FATs (about 0.9 s here); the press comes during it
    # and the recording starts there: its first frames wait in the ring for the file.
    second = long_scenario(until=2.0, presses=(0.3, 1.8), start=0.35, stop=1.75)
    blank = blank_card(tmp_path)
    card = TracingImage.load(blank)
    model = LoggerModel(card, clk_freq=first.clk_freq, channels=first.channels,
                        debounce_s=first.debounce_s)
    model.play(first)
    start, _ = firmware(model)
    model.run(start, until=first.until)
    # Cut just after a FAT write of a flush (FAT 1: the FATs differ, FAT 2: the chain is
    # longer than the file), at six flushes spread over the recording.
    layout = Layout.of(card)
    fat = [index for index, lba in enumerate(card.lbas, 1)
           if layout.fat_start <= lba < layout.data_start]
    cuts = fat[len(fat) // 4::max(1, len(fat) // 8)][:6]
    assert len(cuts) == 6
    damaged = 0
    for cut in cuts:
        model = model_of(first, blank)
        model.cut_power(after_blocks=cut)
        start, _ = firmware(model)
        result = model.run(start, until=first.until)
        assert result.power_cut
        path = saved(result, tmp_path, "cut.img")
        before = fsck_findings(fat_tools["fsck.fat"], path, tmp_path)
        damaged += any(line.startswith(("Reclaimed", "/LOG", "Free cluster summary"))
                       for line in before)
        synced = logs(path).get("LOG00001.TXT")
        # Power up with the same card.
        again = model_of(second, path)
        start, apps = firmware(again)
        after = again.run(start, until=second.until)
        (app,) = apps
        assert app.state == State.IDLE and app.error == FwError.NONE, (cut, app.message)
        final = saved(after, tmp_path, "final.img")
        assert fsck_findings(fat_tools["fsck.fat"], final, tmp_path) == [], (cut, before)
        found = logs(final)
        assert found.get("LOG00001.TXT") == synced, cut
        new = "LOG00002.TXT" if synced is not None else "LOG00001.TXT"
        assert found[new] == stream_of(second.recorded_frames()), cut
    assert damaged == len(cuts)
