"""SoC peripherals: register access types, button debounce, watchdog expiry, RTC, W1C events,
LED activity stretch, GPS ZDA capture (against a plain-Python ZDA reader)."""

import datetime as dt
import random
import re
import subprocess

import pytest

from maglog.hw.arbiter import TaggedFrameByte
from maglog.hw.peripherals import Button, Events, GpsTime, Leds, Rtc, Watchdog
from maglog.sim.stimulus import sentences
from maglog.sim.backends.amaranth import run_simulation
from maglog.sim.backends.amaranth import CsrBus
from maglog.sw.regmap import RegisterMap

#: A slow system clock, so that milliseconds cost few simulated cycles.
CLK = 100_000
EVENT_NAMES = ("fix", "dma_done", "sd_error", "ring_overflow", "button", "zda")


def simulate(dut, script, *, clk_freq=CLK, background=(), deadline=10.0):
    """Runs ``script(ctx, bus, regs)`` as the firmware; returns what it returns."""
    regs = RegisterMap(dut.bus.memory_map)
    period = 1 / clk_freq
    result = {}

    async def firmware(ctx):
        bus = CsrBus(ctx, dut.bus, clock_period=period)
        result["value"] = await script(ctx, bus, regs)

    run_simulation(dut, [firmware], background=background, name=type(dut).__name__.lower(),
                   deadline=deadline, clock_period=period)
    return result["value"]


async def read(bus, regs, name):
    return regs[name].decode(await bus.read(regs[name].address))


def pulse_log(signal, log):
    """A background testbench appending the cycle index of every cycle ``signal`` is high."""
    async def monitor(ctx):
        cycle = 0
        async for _, _, value in ctx.tick().sample(signal):
            if value:
                log.append(cycle)
            cycle += 1
    return monitor


# --- register access types --------------------------------------------------------------

def all_peripherals():
    return {
        "leds": Leds(CLK),
        "button": Button(CLK),
        "rtc": Rtc(CLK),
        "watchdog": Watchdog(CLK),
        "events": Events(EVENT_NAMES),
        "gps": GpsTime(3),
    }


EXPECTED_ACCESS = {
    ("leds", "value"): "rw",
    ("button", "status"): "r",
    ("rtc", "seconds"): "rw",
    ("rtc", "subsec"): "r",
    ("watchdog", "control"): "rw",
    ("watchdog", "kick"): "w",
    ("watchdog", "status"): "r",
    ("events", "status"): "rw",
    ("gps", "time"): "r",
    ("gps", "date"): "r",
    ("gps", "status"): "r",
}

EXPECTED_FIELDS = {
    ("leds", "value"): {"value": 4},
    ("button", "status"): {"level": 1},
    ("rtc", "seconds"): {"value": 32},
    ("rtc", "subsec"): {"millis": 10},
    ("watchdog", "control"): {"enable": 1, "timeout_ms": 16},
    ("watchdog", "kick"): {"kick": 1},
    ("watchdog", "status"): {"reset_cause": 1},
    ("events", "status"): {name: 1 for name in EVENT_NAMES},
    ("gps", "time"): {"second": 6, "minute": 6, "hour": 5},
    ("gps", "date"): {"day": 5, "month": 4, "year": 12},
    ("gps", "status"): {"valid": 1},
}


def test_every_register_has_its_access_type_fields_and_a_description():
    found = {}
    for window, dut in all_peripherals().items():
        for reg in RegisterMap(dut.bus.memory_map):
            found[(window, reg.name)] = reg.access
            assert {n: f.width for n, f in reg.fields.items()} == EXPECTED_FIELDS[(window,
                                                                                   reg.name)]
            assert reg.doc, f"{window}.{reg.name} has no docstring"
    assert found == EXPECTED_ACCESS


@pytest.mark.parametrize("window", ["button", "rtc", "watchdog", "gps"])
def test_writing_a_read_only_register_changes_nothing(window):
    dut = all_peripherals()[window]
    readonly = [reg for reg in RegisterMap(dut.bus.memory_map) if reg.access == "r"]
    assert readonly

    async def script(ctx, bus, regs):
        changed = []
        for reg in readonly:
            before = await bus.read(reg.address)
            await bus.write(reg.address, 0xFFFF_FFFF)
            after = await bus.read(reg.address)
            if before != after:
                changed.append(reg.name)
        return changed

    assert simulate(dut, script) == []


def test_register_defaults():
    async def script(ctx, bus, regs):
        return await read(bus, regs, "control"), await read(bus, regs, "status")

    control, status = simulate(Watchdog(CLK), script)
    assert control == {"enable": 0, "timeout_ms": 1000}
    assert status == {"reset_cause": 0}


@pytest.mark.parametrize("make, message", [
    (lambda: Rtc(999), r"^Clock frequency must be at least 1 kHz to count milliseconds, not 999$"),
    (lambda: Watchdog(500.0), r"at least 1 kHz.*not 500\.0$"),
    (lambda: Leds(0), r"^Clock frequency must be a positive number, not 0$"),
    (lambda: Button(CLK, debounce_s=-1), r"^Debounce time must be a positive number of "
                                         r"seconds, not -1$"),
    (lambda: Leds(CLK, stretch_s="x"), r"not 'x'$"),
    (lambda: Events(()), r"distinct identifiers, not \(\)$"),
    (lambda: Events(("a", "a")), r"not \('a', 'a'\)$"),
    (lambda: GpsTime(3, channel=3), r"^Channel must be an integer in 0\.\.2, not 3$"),
    (lambda: GpsTime(0), r"^Channel count must be a positive integer, not 0$"),
])
def test_bad_parameters_are_refused_in_one_line(make, message):
    with pytest.raises(ValueError, match=message):
        make()


# --- button -----------------------------------------------------------------------------

def bounce(rng, ms, final):
    """``(level, seconds)`` segments of random bounce for about ``ms`` before the input
    settles at ``final``: the last segment is at the other level, each shorter than 1.5 ms."""
    segments, level, left = [], int(not final), ms / 1000
    while left > 0 or level != final:
        length = rng.uniform(0.02e-3, 1.5e-3)
        segments.append((level, length))
        level = int(not level)
        left -= length
    return segments


#: Cycles from a settled input to the press pulse (in this bench's cycle count): 10 ms of
#: stable input at CLK counted in whole milliseconds (up to one more), plus the two
#: synchroniser stages.
DEBOUNCE_DELAY = range(round(0.01 * CLK) + 3, round(0.011 * CLK) + 3)


def run_button(segments, *, debounce_s=0.01):
    """Drives ``button`` through ``(level, seconds)`` segments; returns the cycles of each
    ``press`` pulse, each edge of ``level`` as (cycle, value), and the segments' start cycles."""
    dut = Button(CLK, debounce_s=debounce_s)
    presses, levels, starts = [], [], []

    async def script(ctx, bus, regs):
        cycle = 0
        for level, seconds in segments:
            starts.append(cycle)
            ctx.set(dut.button, level)
            cycles = round(seconds * CLK)
            if cycles:
                await ctx.tick().repeat(cycles)
            cycle += cycles
        return await read(bus, regs, "status")

    async def monitor(ctx):
        cycle, last = 0, 0
        async for _, _, press, level in ctx.tick().sample(dut.press, dut.level):
            if press:
                presses.append(cycle)
            if level != last:
                levels.append((cycle, level))
                last = level
            cycle += 1

    status = simulate(dut, script, background=[monitor])
    return presses, levels, starts, status


@pytest.mark.parametrize("seed", range(3))
def test_bouncy_press_and_release_is_exactly_one_press(seed):
    rng = random.Random(seed)
    hold, after = 0.040, 0.030
    segments = bounce(rng, 5, 1) + [(1, hold)] + bounce(rng, 5, 0) + [(0, after)]
    presses, levels, starts, status = run_button(segments)
    assert len(presses) == 1
    assert [value for _, value in levels] == [1, 0]
    # The level follows once the input has been stable for 10 ms, after the synchroniser.
    stable_high = starts[segments.index((1, hold))]
    assert presses[0] - stable_high in DEBOUNCE_DELAY
    assert levels[0][0] == presses[0]        # press pulses as the level rises
    assert status == {"level": 0}


def test_glitches_shorter_than_debounce_are_ignored():
    # A 9.9 ms glitch while released, then a real press, a 9.9 ms drop-out while held.
    segments = [(0, 0.005), (1, 0.0099), (0, 0.020), (1, 0.030), (0, 0.0099), (1, 0.020)]
    presses, levels, starts, status = run_button(segments)
    assert len(presses) == 1
    assert presses[0] - starts[3] in DEBOUNCE_DELAY
    assert [value for _, value in levels] == [1]
    assert status == {"level": 1}


# --- watchdog ---------------------------------------------------------------------------

def run_watchdog(script):
    dut = Watchdog(CLK)
    fires = []
    result = simulate(dut, lambda ctx, bus, regs: script(ctx, bus, regs, fires),
                      background=[pulse_log(dut.fire, fires)])
    return result, fires


MS = CLK // 1000      # cycles per millisecond


def test_watchdog_fires_once_after_the_timeout_without_kicks():
    async def script(ctx, bus, regs, fires):
        await bus.write(regs["control"].address, regs["control"].encode(enable=1, timeout_ms=5))
        enabled = bus.now() * CLK
        await bus.wait(0.004)
        early = list(fires)
        await bus.wait(0.030)
        return (enabled, early, await read(bus, regs, "control"),
                await read(bus, regs, "status"))

    (enabled, early, control, status), fires = run_watchdog(script)
    assert early == []
    assert len(fires) == 1
    # Whole milliseconds of a free-running count: 5 to 6 of them.
    assert 5 * MS <= fires[0] - enabled <= 6 * MS + 3
    assert control == {"enable": 0, "timeout_ms": 5}
    assert status == {"reset_cause": 1}


def test_after_firing_the_watchdog_counts_afresh_when_enabled_again():
    async def script(ctx, bus, regs, fires):
        control = regs["control"]
        await bus.write(control.address, control.encode(enable=1, timeout_ms=3))
        await bus.wait(0.010)
        await bus.write(control.address, control.encode(enable=1, timeout_ms=4))
        again = bus.now() * CLK
        await bus.wait(0.010)
        return again, await read(bus, regs, "status")

    (again, status), fires = run_watchdog(script)
    assert len(fires) == 2
    assert 4 * MS <= fires[1] - again <= 5 * MS + 3
    assert status == {"reset_cause": 1}


def test_kicks_keep_the_watchdog_quiet_and_it_fires_after_the_last():
    async def script(ctx, bus, regs, fires):
        await bus.write(regs["control"].address, regs["control"].encode(enable=1, timeout_ms=5))
        for _ in range(10):
            await bus.wait(0.0045)
            await bus.write(regs["kick"].address, regs["kick"].encode(kick=1))
        last_kick = bus.now() * CLK
        quiet = list(fires)
        await bus.wait(0.010)
        return last_kick, quiet, await read(bus, regs, "status")

    (last_kick, quiet, status), fires = run_watchdog(script)
    assert quiet == []
    assert len(fires) == 1
    assert 5 * MS - 2 <= fires[0] - last_kick <= 6 * MS + 3
    assert status == {"reset_cause": 1}


def test_a_kick_of_zero_does_not_restart_the_count():
    async def script(ctx, bus, regs, fires):
        await bus.write(regs["control"].address, regs["control"].encode(enable=1, timeout_ms=5))
        start = bus.now() * CLK
        await bus.wait(0.003)
        await bus.write(regs["kick"].address, regs["kick"].encode(kick=0))
        await bus.wait(0.005)
        return start

    start, fires = run_watchdog(script)
    assert len(fires) == 1 and fires[0] - start <= 6 * MS + 3


def test_a_disabled_watchdog_never_fires():
    async def script(ctx, bus, regs, fires):
        await bus.write(regs["control"].address, regs["control"].encode(enable=0, timeout_ms=1))
        await bus.wait(0.020)
        await bus.write(regs["control"].address, regs["control"].encode(enable=0, timeout_ms=0))
        await bus.wait(0.005)
        # Enabled, then disabled before the timeout.
        await bus.write(regs["control"].address, regs["control"].encode(enable=1, timeout_ms=3))
        await bus.wait(0.002)
        await bus.write(regs["control"].address, regs["control"].encode(enable=0, timeout_ms=3))
        await bus.wait(0.020)
        return await read(bus, regs, "status")

    status, fires = run_watchdog(script)
    assert fires == []
    assert status == {"reset_cause": 0}


# --- RTC --------------------------------------------------------------------------------

RTC_CLK = 10_000           # 10 clocks per millisecond: seconds cost little


def test_rtc_counts_seconds_and_latches_milliseconds_at_the_seconds_read():
    dut = Rtc(RTC_CLK)
    per_ms = RTC_CLK // 1000

    async def script(ctx, bus, regs):
        await bus.write(regs["seconds"].address, 1_700_000_000)
        # The write takes effect at the first of bus.write's two edges (the edge ending the
        # bus strobe); a read samples the count as it is before its edge.
        written = bus.now()
        await bus.wait(2.5)
        seconds = (await read(bus, regs, "seconds"))["value"]
        elapsed = round((bus.now() - written) * RTC_CLK)    # edges counted from zero
        subsec = (await read(bus, regs, "subsec"))["millis"]
        await bus.wait(0.3)
        # Not read again: subsec still holds what the seconds read latched.
        later = (await read(bus, regs, "subsec"))["millis"]
        return seconds, subsec, later, elapsed

    seconds, subsec, later, elapsed = simulate(dut, script, clk_freq=RTC_CLK)
    millis = elapsed // per_ms
    assert (seconds, subsec) == (1_700_000_000 + millis // 1000, millis % 1000)
    assert 2 < millis / 1000 < 3
    assert later == subsec


def test_rtc_write_zeroes_the_milliseconds():
    dut = Rtc(RTC_CLK)

    async def script(ctx, bus, regs):
        await bus.write(regs["seconds"].address, 5)
        await bus.wait(0.7317)
        await read(bus, regs, "seconds")
        before = (await read(bus, regs, "subsec"))["millis"]
        await bus.write(regs["seconds"].address, 77)
        seconds = (await read(bus, regs, "seconds"))["value"]
        after = (await read(bus, regs, "subsec"))["millis"]
        return before, seconds, after

    before, seconds, after = simulate(dut, script, clk_freq=RTC_CLK)
    assert before == 731
    assert (seconds, after) == (77, 0)


@pytest.mark.parametrize("start", [0xFF, 0x1FFFF, 0xFF_FFFF, 0x80FF_FFFE, 0xFFFF_FFFF])
def test_rtc_seconds_carry_across_their_bytes(start):
    dut = Rtc(RTC_CLK)

    async def script(ctx, bus, regs):
        await bus.write(regs["seconds"].address, start)
        found = []
        for _ in range(2):
            await bus.wait(1.0)
            found.append((await read(bus, regs, "seconds"))["value"])
        return found

    assert simulate(dut, script, clk_freq=RTC_CLK) == [(start + 1) % (1 << 32),
                                                       (start + 2) % (1 << 32)]


def test_rtc_millisecond_is_the_rounded_clock_count():
    # At 1.5 kHz a millisecond is round(1.5) = 2 clocks: 1000 ms take 2000 clocks.
    dut = Rtc(1_500)

    async def script(ctx, bus, regs):
        await bus.write(regs["seconds"].address, 0)
        await ctx.tick().repeat(1998)    # (the write took effect at bus.write's first edge)
        first = await read(bus, regs, "seconds")
        second = await read(bus, regs, "seconds")
        return first["value"], second["value"], (await read(bus, regs, "subsec"))["millis"]

    assert simulate(dut, script, clk_freq=1_500) == (0, 1, 0)


# --- events -----------------------------------------------------------------------------

def test_events_are_set_by_pulses_and_cleared_by_writing_one():
    dut = Events(EVENT_NAMES)

    async def script(ctx, bus, regs):
        status = regs["status"]
        seen = []
        for name in ("dma_done", "zda"):
            ctx.set(dut.sources, 1 << EVENT_NAMES.index(name))
            await ctx.tick()
        ctx.set(dut.sources, 0)
        seen.append(await read(bus, regs, "status"))
        await bus.write(status.address, status.encode(dma_done=1, fix=1))
        seen.append(await read(bus, regs, "status"))
        await bus.write(status.address, status.encode(zda=0))     # 0 leaves a bit alone
        seen.append(await read(bus, regs, "status"))
        await bus.write(status.address, status.encode(zda=1))
        seen.append(await read(bus, regs, "status"))
        return seen

    seen = simulate(dut, script)
    empty = dict.fromkeys(EVENT_NAMES, 0)
    assert seen == [{**empty, "dma_done": 1, "zda": 1}, {**empty, "zda": 1},
                    {**empty, "zda": 1}, empty]


def clear_with_pulse(offset=None, *, extra_ticks=0):
    """Sets event `fix`, writes 1 to clear it (the bus strobe sampled at edge 0) while the
    event pulses again at edge ``offset`` (or not at all); ``extra_ticks`` cycles after
    edge 0, the status is read. Returns the `fix` bit read."""
    dut = Events(EVENT_NAMES)
    bit = 1 << EVENT_NAMES.index("fix")

    async def script(ctx, bus, regs):
        status = regs["status"]
        ctx.set(dut.sources, bit)
        await ctx.tick()
        ctx.set(dut.bus.addr, status.address)
        ctx.set(dut.bus.w_data, status.encode(fix=1))
        for edge in range(-3, extra_ticks + 1):
            ctx.set(dut.bus.w_stb, edge == 0)
            ctx.set(dut.sources, bit if edge == offset else 0)
            await ctx.tick()
        ctx.set(dut.bus.w_stb, 0)
        ctx.set(dut.sources, 0)
        # (The read's strobe is sampled one edge later: it sees the bit after the last edge.)
        return (await read(bus, regs, "status"))["fix"]

    return simulate(dut, script)


def test_an_event_in_the_cycle_of_its_clear_is_kept():
    """A pulse before the clear takes effect is cleared; one at the same edge or later
    survives: the event is never lost."""
    # The edge at which a bare clear takes effect (the bit reads 0 from it on).
    bits = [clear_with_pulse(extra_ticks=k) for k in range(4)]
    assert 0 in bits
    clear_edge = bits.index(0)
    assert bits[clear_edge:] == [0] * (len(bits) - clear_edge)
    outcomes = {offset: clear_with_pulse(offset, extra_ticks=4) for offset in range(-3, 5)}
    assert outcomes == {o: int(o >= clear_edge) for o in outcomes}


# --- LEDs -------------------------------------------------------------------------------

def test_led_value_and_activity_stretch():
    dut = Leds(CLK, stretch_s=0.002)          # 2 ms, counted in whole milliseconds
    ms = CLK // 1000

    async def script(ctx, bus, regs):
        seen = {}
        await bus.write(regs["value"].address, regs["value"].encode(value=0b1001))
        seen["value"] = ctx.get(dut.led)
        ctx.set(dut.activity, 0b01)
        await ctx.tick()
        ctx.set(dut.activity, 0)
        lit = 0
        async for _, _, led in ctx.tick().sample(dut.led):
            if not led & 0b0010:
                break
            assert led & 0b0100 == 0
            lit += 1
        seen["lit"] = lit
        # A second pulse while lit restarts the stretch: 1.5 ms after the first, the LED is
        # still lit 2 ms later (3.5 ms after the first pulse, which alone lights it 3 ms at
        # most), and dark 3 ms after the second.
        ctx.set(dut.activity, 0b10)
        await ctx.tick()
        ctx.set(dut.activity, 0)
        await ctx.tick().repeat(3 * ms // 2)
        ctx.set(dut.activity, 0b10)
        await ctx.tick()
        ctx.set(dut.activity, 0)
        await ctx.tick().repeat(2 * ms - 1)
        seen["restarted"] = ctx.get(dut.led)
        await ctx.tick().repeat(ms + 1)
        seen["dark"] = ctx.get(dut.led)
        # value[1] lights LED2 without activity.
        await bus.write(regs["value"].address, regs["value"].encode(value=0b0110))
        seen["firmware"] = ctx.get(dut.led)
        return seen

    seen = simulate(dut, script)
    assert seen["value"] == 0b1001
    # 2 ms (rounded to whole milliseconds of a free-running count) up to 1 ms more.
    assert 2 * ms <= seen["lit"] <= 3 * ms
    assert seen["restarted"] == 0b1101
    assert seen["dark"] == 0b1001
    assert seen["firmware"] == 0b0110


# --- GPS time ---------------------------------------------------------------------------

GPS_CHANNEL = 1
N_CHANNELS = 3
ZDA_RE = re.compile(rb"\$[A-Z]{2}ZDA,(\d\d)(\d\d)(\d\d)(?:\.\d*)?,(\d\d),(\d\d),(\d{4}),.+",
                    re.DOTALL)


def reference_zda(frame):
    """What a kept frame of the GPS channel leaves in the registers, or None if nothing."""
    match = ZDA_RE.fullmatch(frame)
    if match is None:
        return None
    hour, minute, second, day, month, year = (int(g) for g in match.groups())
    if hour < 24 and minute < 60 and second < 60 and 1 <= day <= 31 and 1 <= month <= 12 \
            and year < 4096:
        return {"hour": hour, "minute": minute, "second": second,
                "day": day, "month": month, "year": year}
    return None


def zda_body(text):
    return sentences.nmea_sentence(text)


def run_gps(frames, *, seed=0):
    """Feeds ``(channel, frame)`` pairs on the watched stream with random stall cycles (valid
    without ready, ready without valid, garbage payloads); after each frame reads the
    registers. Returns the list of ``(time, date, status)`` and the ``zda`` pulse cycles."""
    dut = GpsTime(N_CHANNELS, channel=GPS_CHANNEL)
    layout = TaggedFrameByte(N_CHANNELS)
    rng = random.Random(seed)
    pulses, after = [], []

    async def script(ctx, bus, regs):
        for channel, frame in frames:
            for k, byte in enumerate(frame):
                while rng.random() < 0.3:
                    # A cycle in which no byte passes: the tap must not take it.
                    valid = rng.random() < 0.5
                    ctx.set(dut.i.valid, valid)
                    ctx.set(dut.i.ready, not valid)
                    ctx.set(dut.i.payload, layout.const({
                        "data": rng.choice(b"$GPZDA,0123456789.*\r\n"), "last": rng.random() < 0.5,
                        "channel": GPS_CHANNEL}))
                    await ctx.tick()
                ctx.set(dut.i.valid, 1)
                ctx.set(dut.i.ready, 1)
                ctx.set(dut.i.payload, layout.const({
                    "data": byte, "last": k == len(frame) - 1, "channel": channel}))
                await ctx.tick()
            ctx.set(dut.i.valid, 0)
            after.append(tuple([await read(bus, regs, name) for name in ("time", "date",
                                                                         "status")]))
        return after

    simulate(dut, script, background=[pulse_log(dut.zda, pulses)])
    return after, pulses


def expected_registers(frames):
    """The reference's register contents after each frame, and the number of captures."""
    time = {"second": 0, "minute": 0, "hour": 0}
    date = {"day": 0, "month": 0, "year": 0}
    status = {"valid": 0}
    out, captures = [], 0
    for channel, frame in frames:
        parsed = reference_zda(frame) if channel == GPS_CHANNEL else None
        if parsed is not None:
            time = {k: parsed[k] for k in time}
            date = {k: parsed[k] for k in date}
            status = {"valid": 1}
            captures += 1
        out.append((time, date, status))
    return out, captures


def check_gps(frames, *, seed=0):
    after, pulses = run_gps(frames, seed=seed)
    expected, captures = expected_registers(frames)
    assert after == expected
    assert len(pulses) == captures
    return expected


def test_good_zda_of_any_talker_is_captured():
    frames = [
        (GPS_CHANNEL, sentences.zda(dt.datetime(2024, 3, 9, 23, 59, 58, 250000))),
        (GPS_CHANNEL, sentences.zda(dt.datetime(1999, 12, 31, 0, 0, 1), talker="GN")),
        (GPS_CHANNEL, zda_body("GPZDA,081500,01,01,2030,,")),        # no decimals
        (GPS_CHANNEL, zda_body("GLZDA,081501.,02,01,2030,00,00")),   # `.` with no digits
    ]
    expected = check_gps(frames)
    assert expected[0][0] == {"second": 58, "minute": 59, "hour": 23}
    assert expected[0][1] == {"day": 9, "month": 3, "year": 2024}
    assert expected[1][1] == {"day": 31, "month": 12, "year": 1999}
    assert expected[-1] == ({"second": 1, "minute": 15, "hour": 8},
                            {"day": 2, "month": 1, "year": 2030}, {"valid": 1})


BAD_ZDA = [
    "GPZDA,240000.00,01,01,2024,00,00",     # hour 24
    "GPZDA,126000.00,01,01,2024,00,00",     # minute 60
    "GPZDA,120060.00,01,01,2024,00,00",     # second 60 (a leap second)
    "GPZDA,120000.00,00,01,2024,00,00",     # day 0
    "GPZDA,120000.00,32,01,2024,00,00",     # day 32
    "GPZDA,120000.00,15,13,2024,00,00",     # month 13
    "GPZDA,120000.00,15,00,2024,00,00",     # month 0
    "GPZDA,120000.00,15,06,4096,00,00",     # year beyond 12 bits
    "GPZDA,,15,06,2024,00,00",              # empty time (no fix yet)
    "GPZDA,120000.00,,,,00,00",             # empty date
    "GPZDA,12000.00,15,06,2024,00,00",      # five time digits
    "GPZDA,1200000,15,06,2024,00,00",       # seven time digits
    "GPZDA,12a000.00,15,06,2024,00,00",     # a letter for a digit
    "GPZDA,120000.0a,15,06,2024,00,00",     # a letter in the decimals
    "GPZDA,120000..0,15,06,2024,00,00",     # two periods
    "GPZDA,120000.00,1,06,2024,00,00",      # one-digit day
    "GPZDA,120000.00,15,6,2024,00,00",      # one-digit month
    "GPZDA,120000.00,15,06,24,00,00",       # two-digit year
    "GPZDA,120000.00,15,06,20245,00,00",    # five-digit year
    "GPZDA,120000.00,15,06,2024",           # the frame ends in the year field
    "GPZDB,120000.00,15,06,2024,00,00",     # another formatter
    "G1ZDA,120000.00,15,06,2024,00,00",     # not a talker letter
    "GPZDA;120000.00,15,06,2024,00,00",     # no comma after the address
]


def test_bad_zda_fields_leave_the_registers_unchanged():
    good = (GPS_CHANNEL, sentences.zda(dt.datetime(2021, 7, 4, 10, 20, 30)))
    frames = [good] + [(GPS_CHANNEL, zda_body(text)) for text in BAD_ZDA]
    assert all(reference_zda(frame) is None for _, frame in frames[1:])
    expected = check_gps(frames)
    assert all(regs == expected[0] for regs in expected)
    # The frame ending at the year's comma.
    check_gps([good, (GPS_CHANNEL, b"$GPZDA,120000.00,15,06,2024,")])


def test_other_channels_and_sentences_are_ignored():
    when = dt.datetime(2022, 2, 2, 2, 2, 2)
    frames = [
        (0, sentences.zda(when)),
        (2, sentences.zda(when)),
        (GPS_CHANNEL, sentences.rmc(when, 52.1, 4.3)),
        (GPS_CHANNEL, sentences.gga(7322.0, 52.1, 4.3)),
        (GPS_CHANNEL, sentences.vtg(12.0, 3.0)),
        (GPS_CHANNEL, b"$ 49895.131,1249\r\n"),
        (GPS_CHANNEL, b"ZDA\r\n"),
    ]
    expected = check_gps(frames)
    assert expected[-1][2] == {"valid": 0}
    # A good ZDA right after an ignored frame of another channel is still read from its `$`.
    check_gps([(0, b"$GPZDA,1"), (GPS_CHANNEL, sentences.zda(when))])


@pytest.mark.parametrize("seed", range(3))
def test_mutated_zda_frames_match_the_reference(seed):
    rng = random.Random(seed)
    frames = []
    for _ in range(40):
        when = dt.datetime(rng.randrange(1980, 2100), rng.randrange(1, 13), rng.randrange(1, 29),
                           rng.randrange(24), rng.randrange(60), rng.randrange(60))
        frame = bytearray(sentences.zda(when, talker=rng.choice(["GP", "GN", "GL"])))
        for _ in range(rng.choice([0, 1, 1, 2])):
            position = rng.randrange(len(frame) - 2)
            frame[position] = rng.choice(b"0123456789,.9ZA$ ")
        frames.append((rng.choice([GPS_CHANNEL, GPS_CHANNEL, GPS_CHANNEL, 0]), bytes(frame)))
    expected, captures = expected_registers(frames)
    assert 5 < captures < len(frames)        # both kinds of frame are in the mix
    check_gps(frames, seed=seed)


# -- the generated Verilog on Icarus ------------------------------------------------------------

GPS_ICARUS_BENCH = """
`timescale 1ns/1ps
module bench;
  reg clk = 0, rst = 1, valid = 0, last = 0;
  reg [7:0] data = 0;
  reg [7:0] frame [0:{last_index}];
  reg [1:0] addr = 0;
  reg r_stb = 0;
  wire [31:0] r_data;
  wire zda;
  integer k, pulses = 0;
  gps dut(.clk(clk), .rst(rst), .i__valid(valid), .i__ready(1'b1),
          .i__payload({{{channel_bits}'d{channel}, last, data}}), .zda(zda),
          .bus__addr(addr), .bus__r_stb(r_stb), .bus__w_stb(1'b0), .bus__w_data(32'd0),
          .bus__r_data(r_data));
  always #5 clk = ~clk;
  always @(posedge clk) if (zda) pulses = pulses + 1;
  initial begin
    $readmemh("{frame_file}", frame);
    repeat (2) @(negedge clk);
    rst = 0;
    for (k = 0; k <= {last_index}; k = k + 1) begin
      @(negedge clk);
      valid = 1; data = frame[k]; last = k == {last_index};
    end
    @(negedge clk);
    valid = 0;
    for (k = 0; k < 3; k = k + 1) begin
      addr = k; r_stb = 1;
      @(negedge clk);
      $display("register %0d %h", k, r_data);    // the cycle after the strobe
      r_stb = 0;
    end
    $display("pulses %0d", pulses);
    $finish;
  end
endmodule
"""


def test_on_icarus_a_zda_is_captured(external, tmp_path):
    # Yosys's time-0 kick of a combinational block is a register initialised in its
    # declaration, which Icarus -g2012 (cocotb's flags) sets without an event: a block runs
    # only once one of its inputs changes. The date fields' widths, looked up in an Array by
    # `field` (0 from power-up until the first date field ends), stayed x there, so every
    # ZDA was dropped at its first date digit and the logger's RTC was never set.
    from amaranth.back import verilog
    tools = external.tools("iverilog", "vvp", why="the GpsTime's Verilog is run on Icarus")
    dut = GpsTime(N_CHANNELS, channel=GPS_CHANNEL)
    frame = sentences.zda(dt.datetime(2026, 11, 24, 12, 34, 56))
    (tmp_path / "gps.v").write_text(verilog.convert(dut, name="gps"))
    (tmp_path / "frame.hex").write_text("\n".join(f"{b:02x}" for b in frame) + "\n")
    (tmp_path / "bench.v").write_text(GPS_ICARUS_BENCH.format(
        last_index=len(frame) - 1, channel=GPS_CHANNEL,
        channel_bits=TaggedFrameByte(N_CHANNELS).size - 9,
        frame_file=tmp_path / "frame.hex"))
    subprocess.run([tools["iverilog"], "-g2012", "-o", str(tmp_path / "bench.vvp"), "-s", "bench",
                    str(tmp_path / "bench.v"), str(tmp_path / "gps.v")], check=True)
    run = subprocess.run([tools["vvp"], "-n", str(tmp_path / "bench.vvp")], check=True,
                         capture_output=True, text=True)
    words = dict(re.findall(r"register (\d) (\S+)", run.stdout))
    regs = RegisterMap(dut.bus.memory_map)
    assert regs["time"].decode(int(words["0"], 16)) == {"hour": 12, "minute": 34, "second": 56}
    assert regs["date"].decode(int(words["1"], 16)) == {"day": 24, "month": 11, "year": 2026}
    assert regs["status"].decode(int(words["2"], 16)) == {"valid": 1}
    assert "pulses 1" in run.stdout


# -- the shared millisecond tick ---------------------------------------------------------------

def test_rtc_tick_pulses_every_millisecond_and_a_seconds_write_restarts_it():
    dut = Rtc(RTC_CLK)
    per_ms = RTC_CLK // 1000
    ticks = []

    async def script(ctx, bus, regs):
        await bus.wait(0.0053)
        await bus.write(regs["seconds"].address, 9)
        written = round(bus.now() * RTC_CLK) - 1           # the edge the write took effect
        await bus.wait(0.0031)
        return written

    written = simulate(dut, script, clk_freq=RTC_CLK, background=[pulse_log(dut.tick, ticks)])
    before = [t for t in ticks if t < written]
    after = [t for t in ticks if t >= written]
    assert len(before) == 5 and len(after) == 3
    assert {b - a for a, b in zip(before, before[1:])} == {per_ms}
    assert before[0] == per_ms - 1
    # The write starts the millisecond again: the next tick is a whole millisecond later.
    assert [t - written for t in after] == [per_ms - 1, 2 * per_ms - 1, 3 * per_ms - 1]


def drive_tick(dut, period, *, start=0):
    """A background testbench pulsing ``dut.tick`` every ``period`` cycles from ``start``."""
    async def ticker(ctx):
        cycle = 0
        async for _ in ctx.tick():
            cycle += 1
            ctx.set(dut.tick, cycle >= start and (cycle - start) % period == 0)
    return ticker


def test_a_watchdog_with_a_shared_tick_counts_the_ticks():
    period = 7                      # cycles between the shared ticks
    dut = Watchdog(CLK, shared_tick=True)
    fires = []

    async def script(ctx, bus, regs):
        control = regs["control"]
        await bus.write(control.address, control.encode(enable=1, timeout_ms=4))
        enabled = bus.now() * CLK
        await ctx.tick().repeat(200)       # no tick yet: nothing counts
        quiet = list(fires)
        await ctx.tick().repeat(100)
        return enabled, quiet

    (enabled, quiet) = simulate(dut, script, background=[
        pulse_log(dut.fire, fires), drive_tick(dut, period, start=210)])
    assert quiet == []
    assert len(fires) == 1
    # The fifth tick finds the count run out (4 whole ticks, the first possibly at once).
    assert fires[0] == 210 + 4 * period + 1


def test_leds_and_button_with_a_shared_tick_count_the_ticks():
    period = 5
    leds = Leds(CLK, stretch_s=0.003, shared_tick=True)    # 3 ticks, up to one more
    lit = []

    async def led_script(ctx, bus, regs):
        ctx.set(leds.activity, 0b10)
        await ctx.tick()
        ctx.set(leds.activity, 0)
        await ctx.tick().repeat(100)
        return None

    simulate(leds, led_script, background=[pulse_log(leds.led[2], lit),
                                            drive_tick(leds, period)])
    assert lit == list(range(1, len(lit) + 1))
    assert 3 * period <= len(lit) <= 4 * period

    button = Button(CLK, debounce_s=0.002, shared_tick=True)
    presses = []

    async def button_script(ctx, bus, regs):
        ctx.set(button.button, 1)
        await ctx.tick().repeat(100)
        return (await read(bus, regs, "status"))["level"]

    level = simulate(button, button_script, background=[pulse_log(button.press, presses),
                                                        drive_tick(button, period)])
    assert level == 1 and len(presses) == 1
    assert 2 + 2 * period < presses[0] <= 2 + 3 * period + 1


# -- the word bridge ---------------------------------------------------------------------------

def test_word_bridge_refuses_registers_wider_than_a_word():
    from maglog.hw.soc import WordBridge
    from maglog.hw.soc import csr

    class Wide(csr.Register, access="r"):
        value: csr.Field(csr.action.R, 40)

    regs = csr.Builder(addr_width=2, data_width=32, granularity=8)
    regs.add("wide", Wide())
    with pytest.raises(ValueError, match=r"^Register wide takes 2 bus words; WordBridge takes "
                                         r"one-word registers only$"):
        WordBridge(regs.as_memory_map())


def test_word_bridge_drives_read_data_in_the_cycle_after_the_strobe_only():
    """The CSR decoder ORs its windows' read data: a window must read zero when idle."""
    dut = Watchdog(CLK)

    async def script(ctx, bus, regs):
        control = regs["control"].address
        seen = []
        ctx.set(dut.bus.addr, control)
        for r_stb in (0, 1, 0, 0):
            ctx.set(dut.bus.r_stb, r_stb)
            await ctx.tick()
            seen.append(ctx.get(dut.bus.r_data))
        ctx.set(dut.bus.r_stb, 0)
        return seen

    timeout_bits = RegisterMap(dut.bus.memory_map)["control"].encode(
        timeout_ms=1000)
    assert simulate(dut, script) == [0, timeout_bits, 0, 0]
