"""cocotb bench for the serial front end's generated Verilog.

Run by :class:`maglog.sim.runners.frontend.FrontEndBench` through ``cocotb_tools.runner``; the
stimulus comes in as a JSON file named by ``$MAGLOG_STIMULUS`` and the result goes out to
``$MAGLOG_RESULT``. Serial lines are driven by cocotbext-uart's ``UartSource`` (a bus
functional model written by someone else) for plain byte streams, or segment by segment
for line faults; frames are checked in order against the expected ones, per channel.
Python runs per bit and per output byte, never per clock cycle while the lines are idle.
"""

import json
import logging
import os
import random

import cocotb
from cocotb.clock import Clock
from cocotb.handle import Immediate
from cocotb.simtime import get_sim_time
from cocotb.triggers import ReadOnly, RisingEdge, Timer
from cocotbext.uart import UartSource

from .amaranth import CLOCK_NS


class _LineBit:
    """One bit of the packed ``uart_rx`` vector, with the handle interface UartSource uses.

    Every write re-drives the whole vector from a shared shadow, so two sources that change
    their bits in the same time step cannot undo each other.
    """
    def __init__(self, vector, shadow, index):
        self._vector = vector
        self._shadow = shadow
        self._index = index
        self._path = f"{vector._path}[{index}]"

    def _drive(self, level, immediate):
        if level:
            self._shadow[0] |= 1 << self._index
        else:
            self._shadow[0] &= ~(1 << self._index)
        if immediate:
            self._vector.value = Immediate(self._shadow[0])
        else:
            self._vector.value = self._shadow[0]

    def setimmediatevalue(self, level):
        self._drive(int(level), True)

    @property
    def value(self):
        return (self._shadow[0] >> self._index) & 1

    @value.setter
    def value(self, level):
        self._drive(int(level), False)


class FrameMonitor:
    """Collects frames from the merged output stream and checks them in order per channel."""
    def __init__(self, dut, expected):
        self._dut = dut
        self.frames = []                       # (channel, bytes) in arrival order
        self.mismatches = []
        self._expected = [list(map(bytes.fromhex, e)) if e is not None else None
                          for e in expected]
        self._seen = [0] * len(expected)
        self._current = bytearray()

    def _check(self, channel, frame):
        expected = self._expected[channel]
        if expected is None:
            return
        index = self._seen[channel]
        self._seen[channel] += 1
        if index >= len(expected):
            self.mismatches.append(f"channel {channel}: unexpected extra frame {frame!r}")
        elif expected[index] != frame:
            self.mismatches.append(f"channel {channel} frame {index}: got {frame!r}, "
                                   f"expected {expected[index]!r}")

    def missing(self):
        return [f"channel {k}: {len(e) - self._seen[k]} expected frames never arrived"
                for k, e in enumerate(self._expected)
                if e is not None and self._seen[k] < len(e)]

    def _take(self, payload):
        data_bits = 8
        self._current.append(payload & 0xFF)
        if (payload >> data_bits) & 1:
            channel = payload >> (data_bits + 1)
            frame = bytes(self._current)
            self._current.clear()
            self.frames.append((channel, frame))
            self._check(channel, frame)

    async def run(self, pauses=None):
        """Take bytes as they come; ``pauses`` (an iterator of bools) holds ``o__ready`` low
        on the cycles it yields True while a byte is offered. Asleep while nothing is."""
        dut = self._dut
        await RisingEdge(dut.clk)
        while True:
            # A writable phase at the start of a cycle: choose ready for this cycle's edge.
            ready = pauses is None or not next(pauses)
            dut.o__ready.value = int(ready)
            await ReadOnly()
            if str(dut.o__valid.value) == "1":
                if ready:
                    self._take(int(dut.o__payload.value))
                await RisingEdge(dut.clk)
            else:
                await RisingEdge(dut.o__valid)


def pause_generator(probability, seed):
    """Seeded pauses for backpressure: True with the given probability."""
    rng = random.Random(seed)
    while True:
        yield rng.random() < probability


async def _drive_segments(line, segments):
    for level, cycles in segments:
        line.value = level
        await Timer(cycles * CLOCK_NS, unit="ns")


async def _drive_parts(line, parts):
    source = None
    for part in parts:
        if "segments" in part:
            await _drive_segments(line, part["segments"])
            continue
        if source is None:
            # One source per line: every byte part of a channel runs at the channel's baud.
            source = UartSource(line, baud=part["baud"])
            source.log.setLevel(logging.WARNING)
        await source.write(bytes.fromhex(part["bytes"]))
        await source.wait()


async def _count_flushes(dut, counter):
    while True:
        await RisingEdge(dut.flush)
        counter[0] += 1


async def _read_counters(dut, names, addresses):
    """The counters through the front end's read port: per channel, ``{name: value}``."""
    counters = []
    for channel in addresses:
        values = {}
        for name, address in zip(names, channel):
            dut.counters__addr.value = address
            dut.counters__r_stb.value = 1
            await RisingEdge(dut.clk)
            dut.counters__r_stb.value = 0
            await ReadOnly()
            values[name] = int(dut.counters__r_data.value)
            await RisingEdge(dut.clk)    # a cycle between two reads, for the scanner
        counters.append(values)
    return counters


@cocotb.test()
async def run_stimulus(dut):
    """Drive the stimulus file's lines, collect and check the frames, write the result."""
    logging.getLogger("cocotb.maglog_frontend").setLevel(logging.WARNING)
    with open(os.environ["MAGLOG_STIMULUS"]) as f:
        stimulus = json.load(f)
    channels = stimulus["channels"]
    n = len(channels)

    Clock(dut.clk, CLOCK_NS, unit="ns", impl="gpi").start()
    shadow = [(1 << n) - 1]
    dut.uart_rx.value = shadow[0]
    for k, channel in enumerate(channels):
        getattr(dut, f"divisor__{k}").value = channel["divisor"]
    dut.o__ready.value = 1
    dut.counters__r_stb.value = 0
    dut.rst.value = 1
    for _ in range(4):
        await RisingEdge(dut.clk)
    dut.rst.value = 0

    monitor = FrameMonitor(dut, [c.get("expected") for c in channels])
    backpressure = stimulus.get("backpressure", 0.0)
    pauses = pause_generator(backpressure, stimulus.get("seed", 0)) if backpressure else None
    cocotb.start_soon(monitor.run(pauses))
    flushes = [0]
    cocotb.start_soon(_count_flushes(dut, flushes))

    drivers = []
    for k, channel in enumerate(channels):
        line = _LineBit(dut.uart_rx, shadow, k)
        drivers.append(cocotb.start_soon(_drive_parts(line, channel["parts"])))
    for driver in drivers:
        await driver
    # Let the last characters through the receivers and the frames through the FIFOs.
    await Timer(stimulus.get("drain_ns", 100_000), unit="ns")
    cycles = round(get_sim_time(unit="ns") / CLOCK_NS)
    await RisingEdge(dut.clk)
    counters = await _read_counters(dut, stimulus["counter_names"],
                                    stimulus["counter_addresses"])

    result = {
        "frames": [[channel, frame.hex()] for channel, frame in monitor.frames],
        "counters": counters,
        "flushes": flushes[0],
        "cycles": cycles,
        "mismatches": monitor.mismatches + monitor.missing(),
    }
    with open(os.environ["MAGLOG_RESULT"], "w") as f:
        json.dump(result, f)
    assert not result["mismatches"], "\n".join(result["mismatches"][:20])
