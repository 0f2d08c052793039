"""sw/app.py when power returns and on cards others prepared: the recording starts at the
button (frames queue in the ring while the file is created), a full card ends its file on a
frame boundary, and a dirty card is repaired at mount (or stays dirty), never closed clean
over damage.
"""

import subprocess

import pytest

from maglog.calib.card import open_card
from maglog.sw.app import AppSettings, FwError, State

from .test_app import (blank_card, firmware, logs, long_scenario, model_of, saved,
                       stream_of)
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
