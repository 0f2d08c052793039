"""The logger's top: its Verilog ports, the Wishbone bridge onto the CSR map, the record
gate, the DMA's clear, the front end's counters over the bus, and the watchdog's reset.

The top runs at 1 MHz with every channel at 62,500 baud (a bit is 16 clocks), so that a
short frame takes a few thousand cycles and a watchdog millisecond a thousand.
"""

import datetime
import re

import pytest
from amaranth.sim import Simulator

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.hw.top import LOGGER_ID, TOPLEVEL_NAME, Logger, RecordGate, generate_verilog
from maglog.sim.backends.amaranth import feed_stream, run_simulation
from maglog.sim.stimulus.sentences import cesium, gga, pmag1, zda
from maglog.sim.stimulus.uart_line import encode
from maglog.sw.regmap import RegisterMap

CLK_FREQ = 1e6
BAUD = 62500
BIT_CYCLES = CLK_FREQ / BAUD
CHANNELS = [ChannelConfig(ChannelKind.PMAG, BAUD), ChannelConfig(ChannelKind.NMEA, BAUD),
            ChannelConfig(ChannelKind.CESIUM, BAUD)]
CESIUM = 2

#: DESIGN.md's top-level ports: name → width.
PORTS = {
    "clk": 1, "rst": 1, "uart_rx": 3,
    "sd_clk": 1, "sd_cmd_o": 1, "sd_cmd_oe": 1, "sd_cmd_i": 1, "sd_dat_o": 4, "sd_dat_oe": 1,
    "sd_dat_i": 4,
    "sdram_a": 12, "sdram_ba": 2, "sdram_cs_n": 1, "sdram_ras_n": 1, "sdram_cas_n": 1,
    "sdram_we_n": 1, "sdram_cke": 1, "sdram_dqm": 4, "sdram_dq_o": 32, "sdram_dq_oe": 1,
    "sdram_dq_i": 32,
    "led": 4, "button": 1,
    "wb_adr": 7, "wb_dat_w": 32, "wb_dat_r": 32, "wb_sel": 1, "wb_cyc": 1, "wb_stb": 1,
    "wb_we": 1, "wb_ack": 1,
}


class WishboneMaster:
    """Single word reads and writes on the logger's Wishbone slave."""
    def __init__(self, ctx, bus):
        self._ctx, self._bus = ctx, bus

    async def _cycle(self, address, we, value=0):
        ctx, bus = self._ctx, self._bus
        ctx.set(bus.adr, address)
        ctx.set(bus.dat_w, value)
        ctx.set(bus.we, we)
        ctx.set(bus.sel, 1)
        ctx.set(bus.cyc, 1)
        ctx.set(bus.stb, 1)
        for _ in range(16):
            _, _, ack, data = await ctx.tick().sample(bus.ack, bus.dat_r)
            if ack:
                break
        else:
            raise AssertionError(f"no ack from address {address:#x}")
        ctx.set(bus.cyc, 0)
        ctx.set(bus.stb, 0)
        return data

    async def read(self, address):
        return await self._cycle(address, 0)

    async def write(self, address, value):
        await self._cycle(address, 1, value)


class Registers:
    """``regs["window_register"]`` over the logger's map, and field access by name."""
    def __init__(self, logger, bus):
        self.bus = bus
        self.map = RegisterMap(logger.bus.memory_map)

    async def read(self, name, field=None):
        reg = self.map[name]
        word = await self.bus.read(reg.address)
        return word if field is None else reg.decode(word)[field]

    async def write(self, name, **fields):
        reg = self.map[name]
        await self.bus.write(reg.address, reg.encode(**fields))


def make_logger():
    return Logger(CHANNELS, clk_freq=CLK_FREQ, max_frame=100, fifo_depth=128,
                  ring_capacity=4096, debounce_s=0.001)


def run(logger, script, *, lines=None, deadline=0.05):
    """Run ``script(ctx, regs)`` with ``lines``: channel → list of frames to send, each
    after the previous one (a background driver per channel)."""
    result = {}
    queues = lines if lines is not None else {}

    async def firmware(ctx):
        regs = Registers(logger, WishboneMaster(ctx, logger.bus))
        result["value"] = await script(ctx, regs)

    def driver(k):
        async def drive(ctx):
            while True:
                if not queues[k]:
                    await ctx.tick()
                    continue
                trace = encode(queues[k][0], bit_cycles=BIT_CYCLES)
                for level, cycles in trace.segments:
                    ctx.set(logger.uart_rx[k], level)
                    await ctx.tick().repeat(cycles)
                queues[k].pop(0)
        return drive

    run_simulation(logger, [firmware], background=[driver(k) for k in queues],
                   name="top", clock_period=1 / CLK_FREQ, deadline=deadline)
    return result["value"]


async def until_sent(ctx, queue):
    while queue:
        await ctx.tick()
    # The frame's last stop bit is in: let it pass the filter, the gate and the ring.
    await ctx.tick().repeat(int(20 * BIT_CYCLES))


# --- Verilog ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def verilog_text():
    return generate_verilog()


def test_verilog_module_has_exactly_the_design_ports(verilog_text):
    header = re.search(rf"^module {TOPLEVEL_NAME}\(([^)]*)\);", verilog_text, re.M)
    assert header, f"no module {TOPLEVEL_NAME}"
    names = [name.strip() for name in header.group(1).split(",")]
    assert sorted(names) == sorted(PORTS)
    body = verilog_text[header.end():verilog_text.index("endmodule", header.end())]
    for name, width in PORTS.items():
        declared = re.search(rf"^\s*(input|output) (?:\[(\d+):0\] )?{name};", body, re.M)
        assert declared, name
        assert int(declared.group(2) or 0) + 1 == width, name


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="Channel count must be a positive integer, not 0"):
        RecordGate(0)


# --- the record gate on its own ---------------------------------------------------------

def gate_run(frames, record_at):
    """Frames (channel 0) through a RecordGate whose ``record`` follows ``record_at(k)``
    for the k-th byte offered; the frames that come out, and ``in_frame`` per byte."""
    gate = RecordGate(1)
    payloads = [{"data": b, "last": n == len(f) - 1, "channel": 0}
                for f in frames for n, b in enumerate(f)]
    out, seen, in_frame = [], [], []

    async def source(ctx):
        for k, payload in enumerate(payloads):
            ctx.set(gate.record, record_at(k))
            ctx.set(gate.i.payload, payload)
            ctx.set(gate.i.valid, 1)
            while True:
                _, _, ready, busy = await ctx.tick().sample(gate.i.ready, gate.in_frame)
                if ready:
                    in_frame.append(busy)
                    break
        ctx.set(gate.i.valid, 0)
        await ctx.tick().repeat(4)

    async def sink(ctx):
        toggle = 0
        while True:
            toggle ^= 1                       # backpressure every other cycle
            ctx.set(gate.o.ready, toggle)
            _, _, valid, payload = await ctx.tick().sample(gate.o.valid, gate.o.payload)
            if valid and toggle:
                seen.append(payload.data)
                if payload.last:
                    out.append(bytes(seen))
                    seen.clear()

    run_simulation(gate, [source], background=[sink], name="gate", deadline=1e-3)
    return out, in_frame


FRAMES = [b"$A1\r\n", b"$B22\r\n", b"$C333\r\n"]


def test_gate_drains_frames_while_not_recording():
    out, in_frame = gate_run(FRAMES, lambda k: 0)
    assert out == [] and not any(in_frame)


def test_gate_acts_at_frame_boundaries():
    a, b, c = map(len, FRAMES)
    # record rises in the middle of the first frame and falls in the middle of the second:
    # the first is drained whole, the second stored whole, the third drained.
    out, in_frame = gate_run(FRAMES, lambda k: 2 <= k < a + 2)
    assert out == [FRAMES[1]]
    # in_frame: high after the second frame's first byte up to its last.
    assert in_frame == [0] * (a + 1) + [1] * (b - 1) + [0] * c


# --- the whole top in the simulator ------------------------------------------------------

def test_wishbone_reads_the_id_and_writes_a_register():
    logger = make_logger()

    async def script(ctx, regs):
        magic = await regs.read("logger_id", "magic")
        await regs.write("logger_fw_status", state=5, error=0x81, file=99999)
        fw = await regs.read("logger_fw_status")
        return magic, regs.map["logger_fw_status"].decode(fw)

    magic, fw = run(logger, script)
    assert magic == LOGGER_ID == 0x4D474C47
    assert fw == {"state": 5, "error": 0x81, "file": 99999}


def test_frames_reach_the_ring_only_while_recording_and_clear_empties_it():
    logger = make_logger()
    frames = [cesium(49895.131 + k, 1249) for k in range(3)]
    queue = []

    async def script(ctx, regs):
        await ctx.tick().until(logger.storage.sdram_ready)
        # Two frames while not recording: the front end keeps them, the gate drains them.
        queue.extend(frames[:2])
        await until_sent(ctx, queue)
        before = {name: await regs.read(f"dma_{name}")
                  for name in ("kept", "dropped", "level")}
        fe_kept = await regs.read(f"frontend_ch{CESIUM}_kept")
        await regs.write("logger_control", record=1)
        queue.append(frames[2])
        await until_sent(ctx, queue)
        after = {name: await regs.read(f"dma_{name}") for name in ("kept", "dropped", "level")}
        fe_after = {name: await regs.read(f"frontend_ch{CESIUM}_{name}")
                    for name in ("kept", "checksum", "overflow")}
        status = await regs.read("logger_status")
        # Stop, then empty the ring as the firmware does before a new file.
        await regs.write("logger_control", record=0)
        await regs.write("dma_control", clear=1)
        cleared = {name: await regs.read(f"dma_{name}") for name in ("kept", "level")}
        return before, fe_kept, after, fe_after, regs.map["logger_status"].decode(status), \
            cleared

    before, fe_kept, after, fe_after, status, cleared = run(
        logger, script, lines={CESIUM: queue})
    assert before == {"kept": 0, "dropped": 0, "level": 0}
    assert fe_kept == 2
    assert after == {"kept": 1, "dropped": 0, "level": len(frames[2])}
    assert fe_after == {"kept": 3, "checksum": 0, "overflow": 0}
    assert status == {"in_frame": 0, "sdram_ready": 1, "button": 0}
    assert cleared == {"kept": 1, "level": 0}


def test_watchdog_resets_the_body_but_not_the_rtc():
    logger = make_logger()

    async def script(ctx, regs):
        await regs.write("rtc_seconds", value=1_700_000_000)
        await regs.write("logger_control", record=1)
        await regs.write("leds_value", value=0b1001)
        await regs.write("frontend_ch1_divisor", value=7)
        set_up = (await regs.read("logger_control", "record"),
                  await regs.read("frontend_ch1_divisor", "value"))
        await regs.write("watchdog_control", enable=1, timeout_ms=2)
        await ctx.tick().until(logger.watchdog.fire)
        await ctx.tick().repeat(1500)
        return {
            "set_up": set_up,
            "record": await regs.read("logger_control", "record"),
            "divisor": await regs.read("frontend_ch1_divisor", "value"),
            "leds": await regs.read("leds_value", "value"),
            "seconds": await regs.read("rtc_seconds", "value"),
            "millis": await regs.read("rtc_subsec", "millis"),
            "cause": await regs.read("watchdog_status", "reset_cause"),
            "enable": await regs.read("watchdog_control", "enable"),
            "id": await regs.read("logger_id", "magic"),
        }

    seen = run(logger, script)
    assert seen["set_up"] == (1, 7)
    # The body is back at reset: the record switch, the divisors, the LEDs.
    assert (seen["record"], seen["divisor"], seen["leds"]) == (0, 0, 0)
    # The RTC kept its time and counted on through the reset (2 ms to the expiry, then 1.5).
    assert seen["seconds"] == 1_700_000_000
    assert seen["millis"] >= 3
    assert seen["cause"] == 1 and seen["enable"] == 0
    assert seen["id"] == LOGGER_ID


def test_events_leds_and_gps_time():
    logger = make_logger()
    when = datetime.datetime(2026, 11, 24, 13, 45, 56)
    lines = {0: [], 1: []}

    async def script(ctx, regs):
        await ctx.tick().until(logger.storage.sdram_ready)
        events = await regs.read("events_status")
        # A button press (held 2 ms, debounced in 1 ms), a PMAG frame on channel 0, a GGA
        # with a fix and a ZDA on channel 1.
        ctx.set(logger.button, 1)
        lines[0].append(pmag1(1, 1.0, 2.0, 3.0))
        # (the GGA first: longer than the PMAG frame, it is not in when that one is)
        lines[1].extend([gga(13 * 3600 + 45 * 60 + 57, 48.1, 11.5), zda(when)])
        await ctx.tick().repeat(2000)
        pressed = await regs.read("logger_status", "button")
        ctx.set(logger.button, 0)
        await until_sent(ctx, lines[0])
        led_ch0 = ctx.get(logger.led)
        await until_sent(ctx, lines[1])
        led_both = ctx.get(logger.led)
        await regs.write("leds_value", value=0b1001)
        led_fw = ctx.get(logger.led)
        raised = regs.map["events_status"].decode(await regs.read("events_status"))
        gps = {**regs.map["gps_time"].decode(await regs.read("gps_time")),
               **regs.map["gps_date"].decode(await regs.read("gps_date"))}
        # Write one to clear: `fix` and `zda` cleared, `button` left.
        await regs.write("events_status", fix=1, zda=1)
        left = regs.map["events_status"].decode(await regs.read("events_status"))
        return events, pressed, led_ch0, led_both, led_fw, raised, gps, left

    events, pressed, led_ch0, led_both, led_fw, raised, gps, left = run(
        logger, script, lines=lines)
    assert events == 0 and pressed == 1
    # LED2 lights for channel 0's kept frame, LED3 for channel 1's; LED1 and LED4 follow
    # the firmware only.
    assert led_ch0 & 0b0110 == 0b0010
    assert led_both == 0b0110
    assert led_fw == 0b1111
    assert raised == {"fix": 1, "dma_done": 0, "sd_error": 0, "ring_overflow": 0,
                      "button": 1, "zda": 1}
    assert gps == {"hour": 13, "minute": 45, "second": 56, "day": 24, "month": 11,
                   "year": 2026}
    assert left == {"fix": 0, "dma_done": 0, "sd_error": 0, "ring_overflow": 0,
                    "button": 1, "zda": 0}
