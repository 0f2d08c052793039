"""The transaction-level logger model: the SD driver on its card through the DMA's ring and
sector buffer, the front end's counters against the reference filter, resets, power cuts,
the SoC's registers, and its speed.

Expected card contents come from the reference filter and sim/stimulus/system.py's scenarios (the
time each kept frame ends), never from the model.

The tests take the gateware's own memory map (hw.top.Logger); the driver is sw.sdcard's, a
ring flush is written here by hand (level, ring-mode DMA write, release of whole sectors).
"""

import time

import pytest

from maglog.calib.card import read_logs
from maglog.hw.arch import sd as arch_sd
from maglog.hw.arch.frames import COUNTER_NAMES
from maglog.hw.arch.sdram import MT48LC4M32B2
from maglog.hw.dma import DmaSource
from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import DEFAULT_CHANNELS
from maglog.hw.peripherals import Events, Leds
from maglog.hw.soc import csr
from maglog.hw.storage import Storage
from maglog.hw.top import EVENT_NAMES, Logger
from maglog.sim.stimulus import sentences
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.logger import (ACCESS_CYCLES, RING_BYTE_CYCLES, LoggerModel,
                                      RunResult, run_system)
from maglog.sim.models.logger_frontend import RECEIVED_BITS
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus.streams import CESIUM_RATE_HZ, GPS_RATE_HZ, MAG_RATE_HZ, demo_streams
from maglog.sim.stimulus.system import short_scenario
from maglog.sw.app import LoggerApp
from maglog.sw.bus import BusTimeout, PowerCut, RegisterBus
from maglog.sw.fat32 import format_image
from maglog.sw.regmap import RegisterMap
from maglog.sw.sdcard import SdCardDriver, SdNoCard, SdWriteError

SECTOR = arch_sd.BLOCK_BYTES
FIRST_LBA = 8192
CLK = 50e6
KINDS = {ChannelKind.PMAG: Kind.PMAG, ChannelKind.NMEA: Kind.NMEA,
         ChannelKind.CESIUM: Kind.CESIUM}
#: The gateware's memory maps, by channels and clock (a Logger takes a while to build).
_MAPS = {}


def gateware_map(channels=DEFAULT_CHANNELS, clk_freq=CLK):
    key = (tuple(channels), clk_freq)
    if key not in _MAPS:
        _MAPS[key] = Logger(channels, clk_freq=clk_freq).bus.memory_map
    return _MAPS[key]


def make_model(*, blocks=1 << 16, channels=DEFAULT_CHANNELS, clk_freq=CLK, **options):
    return LoggerModel(CardImage(blocks), clk_freq=clk_freq, channels=channels,
                       memory_map=gateware_map(channels, clk_freq), **options)


class Firmware:
    """What a test's firmware needs: the bus, the windows, the SD driver, a hand-written
    ring flush (the DMA in ring mode as the driver's data source)."""
    def __init__(self, model):
        self.model, self.bus = model, model.bus
        self.regs = {window: RegisterMap(model.memory_map, window=window) for window in (
            "sdio", "dma", "frontend", "logger", "leds", "button", "rtc", "watchdog", "gps",
            "events")}
        self.driver = SdCardDriver(self.bus, self.regs["sdio"], self,
                                   sys_clock_hz=model.clk_freq)
        self.lba = FIRST_LBA

    def reg(self, name):
        window, _, register = name.partition(".")
        return self.regs[window][register]

    async def read(self, name, field=None):
        reg = self.reg(name)
        word = await self.bus.read(reg.address)
        return reg.field(field).extract(word) if field else word

    async def write(self, name, **fields):
        reg = self.reg(name)
        await self.bus.write(reg.address, reg.encode(**fields))

    async def arm(self, first, count):
        await self.write("dma.control", start=1, source=DmaSource.RING.value, sectors=count,
                         first=first)

    async def cancel(self):
        await self.write("dma.control", abort=1)

    async def flush(self):
        """Committed ring bytes to the card from ``lba`` on; whole sectors released."""
        level = await self.read("dma.level")
        if level:
            await self.driver.write_from(self.lba, -(-level // SECTOR), self)
            await self.write("dma.release", sectors=level // SECTOR)
            self.lba += level // SECTOR
        return level

    async def read_block(self, lba):
        """A block read through the DMA's sector buffer (bytes low first in each word)."""
        await self.write("dma.control", arm_read=1)
        return await self.driver.read_block(lba)

    async def receive(self, count):
        """The driver's block port: the read has filled the sector buffer once the SD host's
        DAT lines are idle."""
        assert count == SECTOR
        status = self.reg("sdio.status")
        await self.bus.wait_event(status.address, lambda w: not status.field("dat_busy")
                                  .extract(w), timeout=0.5)
        await self.write("dma.buffer_seek", index=0)
        words = [await self.read("dma.buffer_read") for _ in range(SECTOR // 4)]
        return b"".join(w.to_bytes(4, "little") for w in words)

    async def write_buffer_block(self, lba, data):
        """A block written from the DMA's sector buffer."""
        await self.write("dma.buffer_seek", index=0)
        for k in range(0, SECTOR, 4):
            await self.write("dma.buffer_write", word=int.from_bytes(data[k:k + 4], "little"))
        source = self

        class Buffer:
            async def arm(self, first, count):
                await source.write("dma.control", start=1, source=DmaSource.BUFFER.value,
                                   sectors=1)

            async def cancel(self):
                await source.cancel()
        return await self.driver.write_from(lba, 1, Buffer())


def card_bytes(image, first, count):
    return b"".join(image.read_block(first + k) for k in range(count))


def feed_scenario(model, scenario):
    for burst in scenario.bursts:
        model.feed(burst.channel, burst.data, start=burst.start)


def paced_demo(seconds, seed=1):
    """demo_streams' bytes at their own rates: a magnetometer frame every 1/20 s, a cesium
    frame every 1/10 s, a GPS epoch (RMC to ZDA) every second."""
    streams = demo_streams(seconds, seed=seed)
    out = []
    for k, (name, rate) in enumerate((("mag", MAG_RATE_HZ), ("gps", GPS_RATE_HZ),
                                      ("cesium", CESIUM_RATE_HZ))):
        groups = []
        for piece in (b"$" + p for p in streams[name].split(b"$")[1:]):
            if not groups or name != "gps" or piece[3:6] == b"RMC":
                groups.append(b"")
            groups[-1] += piece
        out += [(k, 0.01 + n / rate, group) for n, group in enumerate(groups)]
    return streams, out


def test_driver_flushes_the_ring_to_exactly_the_frames_the_reference_keeps():
    scenario = short_scenario(seed=4)
    model = make_model(channels=scenario.channels, clk_freq=scenario.clk_freq)
    feed_scenario(model, scenario)
    fw = Firmware(model)

    async def main():
        await fw.driver.initialise()
        await fw.write("logger.control", record=1)
        flushes = 0
        while model.now_s < scenario.until:
            await fw.bus.wait(0.02)
            flushes += bool(await fw.flush())
        await fw.write("logger.control", record=0)
        await fw.bus.wait_event(fw.reg("logger.status").address, lambda w: not w & 1,
                                timeout=0.01)
        await fw.flush()
        return flushes, await fw.read("dma.level"), await fw.read("dma.kept")

    flushes, level, kept = model.call(main())
    expected = b"".join(scenario.log_frames(0.0, scenario.until))
    assert flushes >= 3 and kept == len(scenario.log_frames(0.0, scenario.until))
    data = card_bytes(model.image, FIRST_LBA, fw.lba - FIRST_LBA + 1)
    assert data[:len(expected)] == expected
    assert data[len(expected):] == bytes(len(data) - len(expected))   # the padded tail
    assert level == len(expected) % SECTOR
    assert model.card.blocks_written >= fw.lba - FIRST_LBA


def test_a_scenario_recorded_between_two_presses_is_on_the_card():
    scenario = short_scenario(seed=1)
    image = CardImage(1 << 16)
    seen = {}

    async def firmware(bus, memory_map, sys_clock_hz):
        # The application loop in miniature: the button starts and stops a recording, each
        # fix flushes, the stop flushes what is left.
        model = bus._model
        fw = Firmware(model)
        assert memory_map is model.memory_map and sys_clock_hz == scenario.clk_freq
        await fw.driver.initialise()
        status = fw.reg("events.status")
        for record in (1, 0):
            while True:
                events = status.decode(await bus.wait_event(status.address, bool, timeout=1))
                await bus.write(status.address, await bus.read(status.address))
                if events["fix"] and record == 0:
                    await fw.flush()
                if events["button"]:
                    break
            await fw.write("logger.control", record=record)
        await bus.wait_event(fw.reg("logger.status").address, lambda w: not w & 1, timeout=1)
        await fw.flush()
        seen["level"] = await fw.read("dma.level")
        while True:
            await bus.wait(1.0)

    result = run_system(scenario, firmware, image)
    expected = b"".join(scenario.recorded_frames())
    data = card_bytes(image, FIRST_LBA, -(-len(expected) // SECTOR))
    assert data == expected + bytes(len(data) - len(expected))
    assert result.seconds == pytest.approx(scenario.until) and result.led == 0
    assert seen["level"] == len(expected) % SECTOR


def test_front_end_counters_match_the_reference_filter():
    streams, paced = paced_demo(12.0, seed=3)
    model = make_model()
    for channel, start, data in paced:
        model.feed(channel, data, start=start)
    fw = Firmware(model)

    async def main():
        await fw.bus.wait(13.0)
        return [{name: await fw.read(f"frontend.ch{k}_{name}") for name in COUNTER_NAMES}
                for k in range(3)]

    counters = model.call(main())
    for k, name in enumerate(("mag", "gps", "cesium")):
        expected = reference_filter(KINDS[DEFAULT_CHANNELS[k].kind], streams[name]).counters
        assert counters[k] == expected
    assert counters[0]["checksum"] == 1 and counters[1]["not_whitelisted"] > 0
    assert counters[2]["bad_byte"] == 1


def test_record_gate_stores_only_frames_that_begin_while_recording():
    frame = sentences.pmag1(1, 1.0, 2.0, 3.0)
    model = make_model()
    for n in range(10):
        model.feed(0, frame, start=0.01 * (n + 1))
    fw = Firmware(model)
    baud = DEFAULT_CHANNELS[0].baud
    byte_s = 10 / baud

    async def main():
        await fw.bus.wait(0.035)                              # frames 1-3 pass unrecorded
        await fw.write("logger.control", record=1)
        before = await fw.read("dma.level")
        # Frame 4 is received at its last stop bit: it passes the gate into the ring then.
        await fw.bus.wait(0.04 + (len(frame) - 1) * byte_s + RECEIVED_BITS / baud
                          - model.now_s)
        in_frame = await fw.read("logger.status", "in_frame")
        await fw.bus.wait(0.0655 - model.now_s)
        await fw.write("logger.control", record=0)           # frames 4-6 recorded
        await fw.bus.wait(0.1)
        return (before, in_frame, await fw.read("dma.level"), await fw.read("dma.kept"),
                await fw.read("frontend.ch0_kept"), await fw.read("dma.dropped"))

    before, in_frame, level, kept, seen, dropped = model.call(main())
    assert (before, in_frame, level, kept, seen, dropped) == (0, 1, 3 * len(frame), 3, 10, 0)


def test_a_full_ring_drops_whole_frames_and_says_so():
    capacity = 2048
    mag = [sentences.pmag1(n, n * 1.5, -2.0, 3.0) for n in range(60)]
    fit = capacity // len(mag[0]) * len(mag[0])
    # A GPS frame that fills the ring to the last byte is kept; any more is not.
    exact = sentences.nmea_sentence("GPVTG," + "1" * (capacity - fit - 12))
    model = make_model(ring_capacity=capacity)
    for n, frame in enumerate(mag):
        model.feed(0, frame, start=0.05 + 0.005 * n)
    model.feed(1, exact, start=0.4)
    model.feed(1, sentences.vtg(90.0, 10.0), start=0.5)
    fw = Firmware(model)

    async def main():
        await fw.driver.initialise()
        await fw.write("logger.control", record=1)
        await fw.bus.wait(0.7)
        events = await fw.read("events.status")
        await fw.flush()
        return events, await fw.read("dma.kept"), await fw.read("dma.dropped"), \
            await fw.read("dma.high_water")

    events, kept, dropped, high_water = model.call(main())
    fitted = mag[:capacity // len(mag[0])] + [exact]
    assert len(exact) == capacity - fit and sum(map(len, fitted)) == capacity
    assert (kept, dropped, high_water) == (len(fitted), len(mag) + 2 - len(fitted), capacity)
    assert fw.reg("events.status").decode(events)["ring_overflow"] == 1
    stream = b"".join(fitted)
    assert card_bytes(model.image, FIRST_LBA, capacity // SECTOR) == stream


def test_blocks_go_through_the_sector_buffer_both_ways():
    model = make_model()
    fw = Firmware(model)
    block = bytes(range(256)) * 2

    async def main():
        await fw.driver.initialise()
        assert await fw.write_buffer_block(77, block) == 1
        dma_done = fw.reg("events.status").decode(await fw.read("events.status"))["dma_done"]
        model.image.write_block(78, b"\x5a" * SECTOR)           # written by someone else
        return dma_done, await fw.read_block(77), await fw.read_block(78)

    dma_done, first, second = model.call(main())
    assert model.image.read_block(77) == block == first and second == b"\x5a" * SECTOR
    assert dma_done == 1


@pytest.mark.parametrize("card", [dict(high_capacity=False), dict(version=1, high_capacity=False),
                                  dict(pre_erase=False)])
def test_cards_as_they_are_standard_capacity_version_1_no_pre_erase(card):
    model = make_model(**card)
    fw = Firmware(model)
    blocks = [bytes([n + 1]) * SECTOR for n in range(3)]

    async def main():
        info = await fw.driver.initialise()
        for n in range(40):
            model.feed(0, sentences.pmag1(n, 1.0, 2.0, 3.0), start=model.now_s + 0.01 + n * 0.005)
        await fw.write("logger.control", record=1)
        await fw.bus.wait(0.3)
        level = await fw.flush()
        await fw.write_buffer_block(5, blocks[0])
        return info, level, await fw.read_block(5)

    info, level, back = model.call(main())
    assert info.high_capacity == card.get("high_capacity", True)
    assert info.version == card.get("version", 2)
    assert back == blocks[0] == model.image.read_block(5)
    frames = b"".join(sentences.pmag1(n, 1.0, 2.0, 3.0) for n in range(40))
    assert level == len(frames) and card_bytes(model.image, FIRST_LBA, 4)[:level] == frames
    assert fw.driver.pre_erase_supported is card.get("pre_erase", True)


def test_the_response_registers_hold_the_bits_as_the_cmd_engine_does():
    model = make_model()
    fw = Firmware(model)

    async def main():
        info = await fw.driver.initialise()
        status = await fw.driver.card_status()
        return info, status, [await fw.read(f"sdio.response{k}") for k in range(4)]

    info, status, words = model.call(main())
    # R1 of CMD13: start 0, transmission 0, index 13 in bits 45..40, the status in 39..8.
    bits = words[0] | words[1] << 32
    assert bits >> 40 == arch_sd.Command.SEND_STATUS and (bits >> 8) & 0xFFFFFFFF == status
    state = (status & arch_sd.STATUS_STATE_MASK) >> arch_sd.STATUS_STATE_SHIFT
    assert state == arch_sd.CardState.TRAN and status & arch_sd.CardStatus.READY_FOR_DATA
    assert info.high_capacity and info.cid >> 119 == 0x1D      # CID[127:120]: manufacturer


def test_watchdog_expiry_resets_all_but_the_rtc_and_restarts_the_firmware():
    model = make_model()
    boots = []

    async def firmware(bus):
        fw = Firmware(model)
        boots.append((model.now_s, await fw.read("watchdog.status", "reset_cause"),
                      await fw.read("rtc.seconds"), await fw.read("leds.value"),
                      await fw.read("watchdog.control", "enable")))
        if len(boots) == 1:
            await fw.write("rtc.seconds", value=1_700_000_000)
        await fw.write("leds.value", value=0b1001)
        await fw.write("watchdog.control", enable=1, timeout_ms=50)
        for _ in range(3):                                   # kicked: no expiry
            await bus.wait(0.04)
            await fw.write("watchdog.kick", kick=1)
        while True:                                          # hangs: expires 50 ms later
            await bus.wait(0.01)

    result = model.run(firmware, until=0.6)
    assert isinstance(result, RunResult) and result.resets == 3 and not result.power_cut
    assert [b[1] for b in boots] == [0, 1, 1, 1]
    assert [b[3] for b in boots] == [0, 0, 0, 0] and [b[4] for b in boots] == [0, 0, 0, 0]
    # Each boot: 3 kicks 40 ms apart, then 50 ms without one.
    assert boots[1][0] == pytest.approx(0.17, abs=1e-3)
    assert boots[3][2] == 1_700_000_000         # the RTC kept counting through the resets
    assert result.end == pytest.approx(0.6)
    # LED1 and LED4 lit by each boot, dark from each reset.
    assert [v for _, v in result.leds] == [0, 0b1001] * 4
    assert [round(t, 2) for t, v in result.leds if v == 0][1:] == [0.17, 0.34, 0.51]


def test_a_power_cut_after_n_blocks_leaves_exactly_those_blocks():
    model = make_model()
    fw = Firmware(model)
    model.call(fw.driver.initialise())
    for n in range(100):
        model.feed(0, sentences.pmag1(n, 1.0, 2.0, 3.0), start=0.02 + n * 0.005)

    async def firmware(bus):
        await fw.write("logger.control", record=1)
        await bus.wait(0.6)
        level = await fw.read("dma.level")
        assert level > 4 * SECTOR
        model.cut_power(after_blocks=3)
        await fw.driver.write_from(FIRST_LBA, level // SECTOR, fw)
        raise AssertionError("the write went on after the power cut")

    result = model.run(firmware, until=2.0)
    assert result.power_cut and result.blocks_written == 3
    assert [lba for lba, _ in model.image.blocks()] == [FIRST_LBA, FIRST_LBA + 1, FIRST_LBA + 2]
    with pytest.raises(PowerCut):
        model.call(fw.read("logger.id"))


def test_a_power_cut_at_an_instant():
    model = make_model()
    model.cut_power(at=0.06)
    fw = Firmware(model)

    async def firmware(bus):
        await fw.driver.initialise()
        while True:
            await fw.write_buffer_block(100, b"\x11" * SECTOR)

    result = model.run(firmware, until=1.0)
    assert result.power_cut and result.end == pytest.approx(0.06)
    assert 0 < result.blocks_written == model.card.blocks_written


def test_rtc_counts_and_latches_the_milliseconds_on_a_seconds_read():
    model = make_model()
    fw = Firmware(model)

    async def main():
        await fw.write("rtc.seconds", value=1000)
        set_at = model.now_s
        await fw.bus.wait(2.5 - (model.now_s - set_at))
        first = await fw.read("rtc.seconds"), await fw.read("rtc.subsec")
        await fw.bus.wait(0.3)
        latched = await fw.read("rtc.subsec")                # not re-latched without a read
        return first, latched, await fw.read("rtc.seconds"), await fw.read("rtc.subsec")

    (seconds, millis), latched, later, later_millis = model.call(main())
    assert (seconds, millis, latched) == (1002, 500, 500)
    assert (later, later_millis) == (1002, 800)


def test_events_are_set_by_the_hardware_and_cleared_by_writing_one():
    model = make_model()
    when = __import__("datetime").datetime(2026, 11, 24, 13, 45, 7)
    gga = sentences.gga(49507.0, 47.0, 8.0, quality=1)
    model.feed(1, sentences.zda(when) + gga, start=0.01)
    model.feed(1, b"$GPZDA,250000,32,13,2026,00,00*4A\r\n", start=0.3)   # out of range
    model.press_button(0.1, hold=0.05)
    model.press_button(0.3, hold=0.004)                      # a glitch: shorter than 10 ms
    fw = Firmware(model)
    status = fw.reg("events.status")

    async def main():
        await fw.bus.wait(0.2)
        first = status.decode(await fw.read("events.status"))
        time_, date = fw.reg("gps.time").decode(await fw.read("gps.time")), \
            fw.reg("gps.date").decode(await fw.read("gps.date"))
        await fw.write("events.status", fix=1, zda=0)
        after_fix = status.decode(await fw.read("events.status"))
        await fw.bus.write(status.address, 0xFFFFFFFF)
        await fw.bus.wait(0.3)
        return first, time_, date, after_fix, status.decode(await fw.read("events.status"))

    first, time_, date, after_fix, last = model.call(main())
    assert {k for k, v in first.items() if v} == {"fix", "zda", "button"}
    assert (time_["hour"], time_["minute"], time_["second"]) == (13, 45, 7)
    assert (date["day"], date["month"], date["year"]) == (24, 11, 2026)
    assert {k for k, v in after_fix.items() if v} == {"zda", "button"}
    assert not any(last.values())                            # glitch and bad ZDA: nothing


def test_activity_leds_follow_kept_frames_and_the_firmware_bits():
    model = make_model(led_stretch_s=0.05)
    model.feed(0, sentences.pmag1(1, 1.0, 2.0, 3.0), start=0.1)
    model.feed(0, b"$PMAG1,garbage*00\r\n", start=0.3)      # dropped: no activity
    fw = Firmware(model)

    async def main():
        await fw.bus.wait(0.5)
        await fw.write("leds.value", value=0b1000)
        await fw.bus.wait(0.01)

    model.call(main())
    frame = sentences.pmag1(1, 1.0, 2.0, 3.0)
    end_of_frame = 0.1 + ((len(frame) - 1) * 10 + RECEIVED_BITS) / DEFAULT_CHANNELS[0].baud
    (t_on, on), (t_off, off), (t_fix, fix) = model.leds[1:]
    assert (on, off, fix) == (0b0010, 0, 0b1000)
    # Lit as the frame's last byte leaves the channel, after it went through at a byte a
    # clock; dark the stretch later.
    assert t_on == pytest.approx(end_of_frame + len(frame) * RING_BYTE_CYCLES / CLK,
                                 abs=2 / CLK)
    assert t_off - t_on == pytest.approx(0.05, abs=1e-6)


def test_a_removed_card_gets_no_response_and_a_reinserted_one_starts_afresh():
    model = make_model()
    model.remove_card(0.0, reinsert=0.5)
    fw = Firmware(model)

    async def main():
        with pytest.raises(SdNoCard):
            await fw.driver.initialise()
        timeout = fw.reg("sdio.status").decode(await fw.read("sdio.status"))["cmd.timeout"]
        sd_error = await fw.read("events.status", "sd_error")
        await fw.bus.wait(0.5)
        return timeout, sd_error, await fw.driver.initialise()

    timeout, sd_error, info = model.call(main())
    assert timeout == 1 and sd_error == 1 and info.high_capacity


def test_a_card_removed_mid_write_keeps_only_the_blocks_it_had_programmed():
    model = make_model(busy_range=(1e-3, 1e-3))
    fw = Firmware(model)
    done = []

    async def main():
        await fw.driver.initialise()
        removal = model.now_s + 0.0035
        model.remove_card(removal)
        with pytest.raises(SdWriteError) as failure:
            for n in range(10):
                await fw.write_buffer_block(200 + n, bytes([n + 1]) * SECTOR)
                done.append(model.now_s)
        return removal, failure.value

    removal, failure = model.call(main())
    finished = [t for t in done if t < removal]
    # The block being programmed when the card left is lost, though DAT0 (pulled up) told
    # the host its busy had ended.
    assert len(finished) >= 1 and len(finished) == len(done) - 1
    assert [lba for lba, _ in model.image.blocks()] == list(range(200, 200 + len(finished)))
    assert failure.accepted == 0 and "CMD24 got no response" in str(failure)


def test_bad_inputs_are_refused_in_one_line():
    model = make_model()
    with pytest.raises(ValueError, match="Channel must be in 0..2, not 3"):
        model.feed(3, b"$", start=0)
    model.feed(0, b"$PMAG1" * 100, start=1.0)
    with pytest.raises(ValueError, match="overlap"):
        model.feed(0, b"x", start=1.001)
    with pytest.raises(ValueError, match="Ring capacity must be a power of two"):
        make_model(ring_capacity=3000)
    with pytest.raises(ValueError, match="A power cut needs after_blocks or at"):
        model.cut_power()
    with pytest.raises(KeyError, match="No register at word address 0x7f"):
        model.call(model.bus.read(0x7F))


def test_a_register_or_field_the_model_lacks_fails_loudly():
    decoder = csr.Decoder(addr_width=8, data_width=32)
    decoder.add(Storage(MT48LC4M32B2, clk_freq=CLK).bus)
    decoder.add(Leds(CLK).bus, name="lamps")
    with pytest.raises(KeyError, match="no register lamps.value"):
        LoggerModel(CardImage(1 << 12), memory_map=decoder.bus.memory_map)
    decoder = csr.Decoder(addr_width=8, data_width=32)
    decoder.add(Events(EVENT_NAMES + ("brownout",)).bus, name="events")
    model = LoggerModel(CardImage(1 << 12), memory_map=decoder.bus.memory_map)
    with pytest.raises(KeyError, match="lacks field 'brownout' of events.status"):
        model.call(model.bus.read(RegisterMap(decoder.bus.memory_map, window="events")
                                  ["status"].address))


def test_register_accesses_cost_the_bridge_cycles():
    model = make_model()
    fw = Firmware(model)
    model.call(fw.read("logger.id"))
    assert model.now == ACCESS_CYCLES == 4      # strobe, data and ack, the next cycle
    assert model.call(fw.read("logger.id")) == 0x4D474C47


@pytest.mark.parametrize("poll", [1e-5, 1e-3])
def test_wait_event_skips_idle_polls_but_ends_as_polling_every_time_does(poll):
    def waits(fast):
        model = make_model()
        model.press_button(0.2, hold=0.1)
        fw = Firmware(model)
        status = fw.reg("logger.status")
        wait_event = type(model.bus).wait_event if fast else RegisterBus.wait_event
        button = status.field("button")
        ends = []

        async def main():
            word = await wait_event(model.bus, status.address, button.extract, timeout=1.0,
                                    poll=poll)
            ends.append((model.now, word))
            with pytest.raises(BusTimeout, match="release not reached within 0.05 s"):
                await wait_event(model.bus, status.address, lambda w: False, timeout=0.05,
                                 poll=poll, what="release")
            ends.append(model.now)
        model.call(main())
        return ends

    started = time.perf_counter()
    fast = waits(True)
    assert time.perf_counter() - started < 0.5
    assert fast == waits(False)
    assert fast[0][0] / CLK == pytest.approx(0.21, abs=2 * poll + 1e-6)


@pytest.mark.parametrize("offset", range(-1, ACCESS_CYCLES + 2))
@pytest.mark.parametrize("poll", [1 / CLK, 1e-3])
def test_wait_event_skips_to_the_very_poll_that_sees_the_change(offset, poll):
    # The change falls `offset` cycles after the first poll's read starts (before, on and
    # after the instant it samples), and later polls come a period of ACCESS_CYCLES + poll
    # apart: whichever, the skipping wait ends where polling every time ends.
    def waits(fast):
        model = make_model(debounce_s=1e-4)
        model.press_button(1e-4)
        level = round(1e-4 * CLK) + 2 + round(1e-4 * CLK)     # the debounced level rises
        fw = Firmware(model)
        status = fw.reg("logger.status")
        wait_event = type(model.bus).wait_event if fast else RegisterBus.wait_event
        model.call(model.bus.wait((level - offset) / CLK))
        assert model.now == level - offset
        model.call(wait_event(model.bus, status.address, status.field("button").extract,
                              timeout=5e-3, poll=poll))
        return model.now
    assert waits(True) == waits(False)


def _recording_firmware(model, log):
    """An application loop in miniature: init, record, flush at every fix event."""
    async def firmware(bus):
        fw = Firmware(model)
        await fw.driver.initialise()
        await fw.write("logger.control", record=1)
        status = fw.reg("events.status")
        while True:
            await bus.wait_event(status.address, lambda w: status.field("fix").extract(w),
                                 timeout=10.0, poll=1e-3)
            await fw.write("events.status", fix=1)
            log.append(await fw.flush())
    return firmware


def _speed(seconds):
    _, paced = paced_demo(seconds, seed=2)
    model = make_model(blocks=1 << 20)
    for channel, start, data in paced:
        model.feed(channel, data, start=start)
    flushes = []
    started = time.perf_counter()
    result = model.run(_recording_firmware(model, flushes), until=seconds)
    wall = time.perf_counter() - started
    assert result.end == pytest.approx(seconds) and result.resets == 0
    assert len(flushes) >= seconds * GPS_RATE_HZ * 0.9
    assert result.blocks_written >= sum(flushes) / SECTOR
    print(f"\n{seconds:.0f} s simulated in {wall:.2f} s: {seconds / wall:.0f} simulated s per "
          f"wall s ({len(flushes)} flushes, {result.blocks_written} blocks)")
    return seconds / wall


def test_a_minute_of_default_rates_runs_fast():
    assert _speed(60.0) > 20


@pytest.mark.slow
def test_an_hour_of_default_rates_runs_in_minutes_at_most():
    assert _speed(3600.0) > 20


def _channel_of(frame):
    return 0 if frame.startswith(b"$PMAG1,") else 2 if frame[1:2] in b" 1" else 1


@pytest.mark.slow
def test_an_hour_recorded_by_the_application_loop(tmp_path):
    # The firmware itself (sw.app) on a formatted card: a press starts the recording, a
    # press an hour later stops it; the log holds, channel by channel, an unbroken run of
    # the frames the reference filter keeps.
    seconds = 3600.0
    streams, paced = paced_demo(seconds, seed=5)
    path = tmp_path / "card.img"
    format_image(path, 4 << 30)
    model = LoggerModel(CardImage.load(path), memory_map=gateware_map())
    for channel, start, data in paced:
        model.feed(channel, data, start=start)
    model.press_button(0.5, hold=0.2)
    model.press_button(seconds - 0.5, hold=0.2)
    started = time.process_time()
    result = model.run(lambda bus: LoggerApp(bus, model.memory_map, sys_clock_hz=CLK).run(),
                       until=seconds + 1)
    cpu = time.process_time() - started
    print(f"\nthe application loop: {seconds:.0f} s simulated in {cpu:.1f} s of CPU "
          f"({seconds / cpu:.0f} simulated s per CPU s), {result.blocks_written} blocks")
    assert result.resets == 0 and not result.power_cut
    result.image.save(tmp_path / "out.img")
    (name, log), = read_logs(tmp_path / "out.img")
    frames = [b"$" + f for f in log.split(b"$")[1:]]
    assert b"".join(frames) == log
    for k, name in enumerate(("mag", "gps", "cesium")):
        kept = reference_filter(KINDS[DEFAULT_CHANNELS[k].kind], streams[name]).frames
        logged = [f for f in frames if _channel_of(f) == k]
        starts = [i for i in range(len(kept) - len(logged) + 1)
                  if all(kept[i + j] == frame for j, frame in enumerate(logged))]
        assert starts, f"channel {k}: the log is not a run of the kept frames"
        # (The run begins within a second of the start, and ends within one of the stop.)
        assert starts[0] <= 40 and len(kept) - starts[0] - len(logged) <= 40
    assert seconds / cpu > 20
