"""sw/app.py: the application loop on the transaction-level model of the logger.

Each run feeds a scenario (sim/stimulus/system.py: serial bursts with their timing, button presses)
to the model, runs the firmware until the scenario's end, and judges the card image:
``fsck.fat -n`` finds nothing, and the LOG files hold exactly the frames the reference
filter keeps over the recording, in order (read back with calib.card).
"""

import subprocess
import sys

import pytest

from maglog.calib.card import open_card, read_logs
from maglog.sim.stimulus import sentences
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.logger import LoggerModel
from maglog.sim.stimulus.system import SystemScenario, Timeline, short_scenario
from maglog.sw.app import (LED_FIX, LED_RECORDING, AppSettings, Blink, FwError, LoggerApp,
                           State)
from maglog.sw.fat32 import format_image
from maglog.sw.regmap import RegisterMap

from .test_fat32 import fsck_findings, mtools, mtype

MiB = 1 << 20


# -- Harness ----------------------------------------------------------------------------------

def blank_card(tmp_path, size=40 * MiB, cluster_bytes=512, files=None, fat_tools=None):
    """A freshly formatted card image (``files``: name → bytes copied on with mtools)."""
    path = tmp_path / "blank.img"
    format_image(path, size, cluster_bytes=cluster_bytes, volume_id=0x1234)
    for name, data in (files or {}).items():
        source = tmp_path / "upload"
        source.write_bytes(data)
        mtools(fat_tools["mcopy"], path, str(source), f"::{name}")
    return path


def model_of(scenario, card_path, **options):
    model = LoggerModel(CardImage.load(card_path), clk_freq=scenario.clk_freq,
                        channels=scenario.channels, debounce_s=scenario.debounce_s,
                        **options)
    model.play(scenario)
    return model


def firmware(model, settings=None):
    """The firmware entry point for :meth:`LoggerModel.run`; every start (after a watchdog
    reset too) appends its :class:`LoggerApp` to the returned list."""
    apps = []

    async def start(bus):
        app = LoggerApp(bus, model.memory_map, sys_clock_hz=model.clk_freq,
                        settings=settings or AppSettings())
        apps.append(app)
        await app.run()

    return start, apps


def fw_status(model):
    """``logger.fw_status`` as the firmware left it, read over the model's bus."""
    register = RegisterMap(model.memory_map, window="logger")["fw_status"]
    return register.decode(model.call(model.bus.read(register.address)))


def saved(result, tmp_path, name="out.img"):
    path = tmp_path / name
    result.image.save(path)
    return path


def logs(path):
    return dict(read_logs(path))


def stream_of(frames):
    return b"".join(frames)


def contiguous_frames(data, frames):
    """The index range ``(i, j)`` with ``data == frames[i:j]`` joined, or None."""
    for i in range(len(frames)):
        joined = b""
        for j in range(i, len(frames)):
            joined += frames[j]
            if joined == data:
                return i, j + 1
            if not data.startswith(joined):
                break
    return None


def led_on_between(leds, bit, start, stop):
    """The LED ``bit`` was on for all of ``start .. stop`` by the LED history."""
    value = 0
    for t, v in leds:
        if t > start:
            break
        value = v
    if not value & bit:
        return False
    return all(v & bit for t, v in leds if start < t < stop)


def long_scenario(*, gps_every=0.2, until=3.0, presses=(0.3, 2.5), start=0.35, stop=2.45,
                  zda_at=0.1):
    """A recording of magnetometer frames every 5 ms and a GGA fix every ``gps_every`` s
    between ``start`` and ``stop``, on the short scenario's lines."""
    base = short_scenario()
    when = base.timestamp
    seconds_of_day = when.hour * 3600 + when.minute * 60 + when.second
    line = Timeline(base.channels)
    line.add(1, zda_at, sentences.zda(when))
    events = []
    t, n = start, 0
    while t < stop:
        events.append((t, 0, sentences.pmag1(n % 100_000, 1000.0 + n, -2000.0, 3000.5)))
        t, n = t + 0.005, n + 1
    t, n = start + 0.0013, 0
    while t < stop:
        events.append((t, 1, sentences.gga(seconds_of_day + n, 47.3769, 8.5417)))
        t, n = t + gps_every, n + 1
    for at, channel, frame in sorted(events):
        line.add(channel, at, frame)
    scenario = SystemScenario(channels=base.channels, clk_freq=base.clk_freq,
                              bursts=line.bursts, presses=list(presses), until=until,
                              timestamp=when)
    scenario.check_quiet(0.015)
    return scenario


# -- Recording --------------------------------------------------------------------------------

def test_short_recording(tmp_path, fat_tools):
    scenario = short_scenario()
    model = model_of(scenario, blank_card(tmp_path))
    start, apps = firmware(model)
    result = model.run(start, until=scenario.until)
    assert result.resets == 0 and not result.power_cut
    (app,) = apps
    assert app.flushes >= 4                 # four GGA fixes, then the final flush
    assert app.state == State.IDLE and app.error == FwError.NONE and app.file is None
    assert fw_status(model) == {"state": State.IDLE, "error": FwError.NONE, "file": 0}
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    assert logs(path) == {"LOG00001.TXT": stream_of(scenario.recorded_frames())}
    with open_card(path) as card:
        # The RTC was set from the ZDA before the recording: file times are its time.
        assert card.stat("LOG00001.TXT").mtime == scenario.timestamp.replace(tzinfo=None)
    first, second = scenario.presses
    assert led_on_between(result.leds, LED_RECORDING, first + 0.02, second - 0.001)
    assert not led_on_between(result.leds, LED_RECORDING, second + 0.02, scenario.until)
    assert led_on_between(result.leds, LED_FIX, 0.13, 0.2)      # GGA fixes every 20 ms


def test_short_recording_on_an_sdhc_card(tmp_path, fat_tools):
    # 2200 MiB formatted as the SD Association does (32 KiB clusters).
    scenario = short_scenario(seed=5)
    model = model_of(scenario, blank_card(tmp_path, size=2200 * MiB, cluster_bytes=None))
    start, _ = firmware(model)
    path = saved(model.run(start, until=scenario.until), tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    assert logs(path) == {"LOG00001.TXT": stream_of(scenario.recorded_frames())}


def test_flush_on_high_water_without_fixes(tmp_path, fat_tools):
    # No GGA at all: the ring (4 KiB) fills past half and is flushed without a fix event;
    # nothing is dropped.
    scenario = long_scenario(gps_every=100.0, until=1.2, presses=(0.3, 1.0), stop=0.95)
    model = model_of(scenario, blank_card(tmp_path), ring_capacity=4096)
    start, apps = firmware(model, AppSettings(ring_bytes=4096, high_water_fraction=0.5))
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.flushes > 3 and app.overflows == 0
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    assert logs(path) == {"LOG00001.TXT": stream_of(scenario.recorded_frames())}


def test_existing_files_are_kept_and_numbers_go_on(tmp_path, fat_tools, external):
    files = {"LOG00003.TXT": b"$old log\r\n" * 50, "NOTES.TXT": b"calibration at noon\n",
             "DATA.BIN": bytes(range(256)) * 40}
    card = blank_card(tmp_path, files=files, fat_tools=fat_tools)
    scenario = short_scenario(seed=2)
    model = model_of(scenario, card)
    start, _ = firmware(model)
    path = saved(model.run(start, until=scenario.until), tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    assert logs(path) == {"LOG00003.TXT": files["LOG00003.TXT"],
                          "LOG00004.TXT": stream_of(scenario.recorded_frames())}
    for name, data in files.items():
        assert mtype(external, path, name) == data


# -- Card problems ----------------------------------------------------------------------------

def test_card_full_closes_the_file_cleanly(tmp_path, fat_tools):
    # The run ends before the second press (a press in FULL mounts the card again).
    scenario = long_scenario(until=1.1, presses=(0.3, 1.2), stop=0.95)
    recorded = stream_of(scenario.recorded_frames())
    card = blank_card(tmp_path)
    # Fill the card but for three clusters (1536 bytes): the recording does not fit.
    with open_card(card) as reader:
        free = (reader.boot.cluster_count - 1) * 512
    room = 3 * 512
    assert len(recorded) > room
    card = blank_card(tmp_path, files={"FILLER.BIN": bytes(free - room)}, fat_tools=fat_tools)
    model = model_of(scenario, card)
    start, apps = firmware(model)
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.state == State.FULL and app.error == FwError.CARD_FULL
    assert fw_status(model) == {"state": State.FULL, "error": FwError.CARD_FULL, "file": 0}
    assert "card is full" in app.message
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []    # clean, consistent
    # The file ends at the last whole frame that fitted, not in the frame the cluster cut.
    whole = recorded[:recorded.rindex(b"\n", 0, room) + 1]
    assert room - 100 < len(whole) < room
    assert logs(path) == {"LOG00001.TXT": whole}
    # LED1 blinks slowly (the card-full pattern) once the recording stopped.
    after = [v & LED_RECORDING for t, v in result.leds if t > 0.9]
    assert 0 in after and LED_RECORDING in after


def test_refuses_a_card_that_is_not_fat32(tmp_path, fat_tools):
    path = tmp_path / "fat16.img"
    path.write_bytes(b"")
    with open(path, "r+b") as f:
        f.truncate(40 * MiB)
    subprocess.run([fat_tools["mkfs.fat"], "-F", "16", str(path)], check=True,
                   capture_output=True)
    before = path.read_bytes()
    scenario = short_scenario()
    model = model_of(scenario, path)
    start, apps = firmware(model)
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.state == State.INIT and app.error == FwError.NOT_FAT32
    assert fw_status(model)["error"] == FwError.NOT_FAT32
    assert "without a partition table" in app.message
    assert saved(result, tmp_path).read_bytes() == before          # nothing written
    pattern = app.settings.patterns[FwError.NOT_FAT32]
    assert any(v & pattern.mask == pattern.mask for _, v in result.leds)


def test_a_card_inserted_later_is_mounted(tmp_path, fat_tools):
    scenario = long_scenario(until=3.2, presses=(2.2, 3.0), start=2.25, stop=2.95, zda_at=2.1)
    model = model_of(scenario, blank_card(tmp_path))
    model.remove_card(0.0, reinsert=1.5)
    start, apps = firmware(model)
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.state == State.IDLE and app.error == FwError.NONE
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    assert logs(path) == {"LOG00001.TXT": stream_of(scenario.recorded_frames())}
    # Before the card came, the no-card pattern (LED2 blinking) showed.
    assert any(v & 2 for t, v in result.leds if t < 1.5)


def test_card_removed_and_reinserted_mid_recording(tmp_path, fat_tools):
    # The card mounts again about a second after its return (a retry a second) and its
    # repair (the volume is dirty) reads both FATs: about 0.9 s on this card.
    scenario = long_scenario(until=4.0, presses=(0.3, 3.8), stop=3.75)
    model = model_of(scenario, blank_card(tmp_path))
    model.remove_card(1.0, reinsert=1.3)
    start, apps = firmware(model)
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.state == State.IDLE
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    found = logs(path)
    assert sorted(found) == ["LOG00001.TXT", "LOG00002.TXT"]
    frames = scenario.recorded_frames()
    # The first file holds the frames of its last sync, from the first on; the second a
    # run of frames up to the last before the stop.
    first = contiguous_frames(found["LOG00001.TXT"], frames)
    second = contiguous_frames(found["LOG00002.TXT"], frames)
    assert first is not None and first[0] == 0 and first[1] > 0
    assert second is not None and second[1] == len(frames) and second[0] > first[1]


# -- Watchdog and overflow --------------------------------------------------------------------

def test_watchdog_reset_resumes_in_a_new_file(tmp_path, fat_tools):
    scenario = long_scenario(until=3.0, presses=(0.3, 2.8), stop=2.75)
    hung = []

    async def hang_at_third_flush(app, point):
        # A firmware bug: the loop stops kicking the watchdog (once).
        if point == "flush" and app.flushes == 2 and not hung:
            hung.append((app.bus.now(), app.file.size))
            while True:
                await app.bus.wait(0.01)

    model = model_of(scenario, blank_card(tmp_path))
    settings = AppSettings(watchdog_timeout_ms=200, fault=hang_at_third_flush)
    start, apps = firmware(model, settings)
    result = model.run(start, until=scenario.until)
    assert result.resets == 1 and len(apps) == 2 and len(hung) == 1
    assert apps[1].state == State.IDLE
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    found = logs(path)
    assert sorted(found) == ["LOG00001.TXT", "LOG00002.TXT"]
    frames = scenario.recorded_frames()
    synced = hung[0][1]
    # Nothing synced is lost: the first file is what its two flushes synced.
    assert found["LOG00001.TXT"] == stream_of(frames)[:synced] and synced > 0
    second = contiguous_frames(found["LOG00002.TXT"], frames)
    assert second is not None and second[1] == len(frames)


def test_ring_overflow_is_reported_and_recording_goes_on(tmp_path, fat_tools):
    # A 1 KiB ring and a fix once a second: the magnetometer overflows it between flushes.
    scenario = long_scenario(gps_every=1.0, until=2.8, presses=(0.3, 2.5), stop=2.45)
    model = model_of(scenario, blank_card(tmp_path), ring_capacity=1024)
    register = RegisterMap(model.memory_map, window="logger")["fw_status"]
    seen = []

    async def watch(app, point):
        # What a debugger would read in fw_status, every pass of the loop.
        if point == "loop":
            status = register.decode(await app.bus.read(register.address))
            if status not in seen:
                seen.append(status)

    start, apps = firmware(model, AppSettings(ring_bytes=1024, high_water_fraction=1.0,
                                              fault=watch))
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.overflows > 0 and app.state == State.IDLE
    # fw_status showed the overflow, with the file being written, while recording.
    assert {"state": State.RECORDING, "error": FwError.RING_OVERFLOW, "file": 1} in seen
    assert fw_status(model) == {"state": State.IDLE, "error": FwError.NONE, "file": 0}
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    kept = logs(path)["LOG00001.TXT"]
    frames = scenario.recorded_frames()
    # Whole frames only, in order, fewer than were sent, and the last ones are there.
    rest, missing = kept, 0
    for frame in frames:
        if rest.startswith(frame):
            rest = rest[len(frame):]
        else:
            missing += 1
    assert rest == b"" and 0 < len(kept) < len(stream_of(frames))
    # The frames missing are those the ring dropped.
    assert app.dropped == missing > 0
    # Frames of the recording's last half second, long after the first overflow, are there.
    assert any(frame in kept for frame in frames[-100:])
    # While recording after the overflow LED1 blinked (the overflow pattern).
    during = [v & LED_RECORDING for t, v in result.leds
              if scenario.presses[0] + 1.2 < t < scenario.presses[1]]
    assert 0 in during and LED_RECORDING in during


# -- Settings ---------------------------------------------------------------------------------

def test_settings_refuse_nonsense():
    with pytest.raises(ValueError, match=r"^poll_s must be a positive number of seconds, "
                                         r"not 0$"):
        AppSettings(poll_s=0)
    with pytest.raises(ValueError, match=r"^high_water_fraction must be in \(0, 1\], "
                                         r"not 1.5$"):
        AppSettings(high_water_fraction=1.5)
    with pytest.raises(ValueError, match=r"^watchdog_timeout_ms must be a positive integer, "
                                         r"not 0.5$"):
        AppSettings(watchdog_timeout_ms=0.5)


def test_blink_pattern():
    blink = Blink(mask=3, period_s=1.0, on_s=0.25)
    assert [blink.lit(t) for t in (0.0, 0.2, 0.3, 1.1, 1.9)] == [True, True, False, True,
                                                                   False]


def test_a_failed_data_write_leaves_the_file_as_its_last_sync(tmp_path, fat_tools,
                                                              monkeypatch):
    # The third flush's ring write fails after its first block went to the card: the file
    # must keep the size of the second flush (no metadata may point at the blocks that did
    # not), the loop initialises the card again and resumes in a new file.
    from maglog.sw import storage as sw_storage
    from maglog.sw.sdcard import SdWriteError

    real = sw_storage.DmaStorage.write_ring
    calls = []

    async def failing(self, lba, first, count):
        calls.append(lba)
        if len(calls) == 3:
            await real(self, lba, first, 1)
            raise SdWriteError(f"writing block {lba + 1} failed: injected", 1)
        return await real(self, lba, first, count)

    monkeypatch.setattr(sw_storage.DmaStorage, "write_ring", failing)
    scenario = long_scenario(until=3.0, presses=(0.3, 2.8), stop=2.75)
    model = model_of(scenario, blank_card(tmp_path))
    sizes = []

    async def watch(app, point):
        if point == "flush":
            sizes.append(app.file.size)

    start, apps = firmware(model, AppSettings(fault=watch))
    result = model.run(start, until=scenario.until)
    (app,) = apps
    assert app.state == State.IDLE and app.error == FwError.NONE
    path = saved(result, tmp_path)
    assert fsck_findings(fat_tools["fsck.fat"], path, tmp_path) == []
    found = logs(path)
    frames = scenario.recorded_frames()
    assert sizes[2] > 0 and found["LOG00001.TXT"] == stream_of(frames)[:sizes[2]]
    second = contiguous_frames(found["LOG00002.TXT"], frames)
    assert second is not None and second[1] == len(frames)


# -- Power cuts -------------------------------------------------------------------------------

def test_power_cuts_during_a_recording_leave_a_recoverable_card(tmp_path, fat_tools):
    # Cut the power after every few blocks the card stores during a recording: fsck finds at
    # most what a cut during a sync may leave (see test_fat32), and the log file holds a
    # prefix of the recorded frames.
    from .test_fat32 import _RECOVERABLE

    scenario = long_scenario(until=1.2, presses=(0.3, 1.0), stop=0.95)
    blank = blank_card(tmp_path)
    stream = stream_of(scenario.recorded_frames())
    model = model_of(scenario, blank)
    start, _ = firmware(model)
    total = model.run(start, until=scenario.until).blocks_written
    assert total > 20
    kept = []
    for cut in range(1, total, max(1, total // 12)):
        model = model_of(scenario, blank)
        model.cut_power(after_blocks=cut)
        start, _ = firmware(model)
        result = model.run(start, until=scenario.until)
        assert result.power_cut and result.blocks_written == cut
        path = saved(result, tmp_path, f"cut{cut}.img")
        findings = fsck_findings(fat_tools["fsck.fat"], path, tmp_path)
        assert [line for line in findings if not _RECOVERABLE.match(line)] == [], cut
        data = logs(path).get("LOG00001.TXT", b"")
        assert stream.startswith(data), cut
        kept.append(len(data))
    assert kept[0] == 0 and any(0 < n < len(stream) for n in kept)   # before, during the log


def test_the_firmware_imports_no_gateware():
    # Only hw/arch (constants) and, through sw.regmap's map reader, Amaranth's shapes.
    code = ("import sys, maglog.sw.app; print(' '.join(sorted(m for m in sys.modules if "
            "m.startswith('maglog.hw.') and not m.startswith('maglog.hw.arch'))))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True, timeout=60)
    assert result.stdout.strip() == ""
