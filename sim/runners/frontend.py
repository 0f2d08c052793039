"""Run the serial front end on a stimulus with any backend and gather what it kept.

Backends: ``amaranth`` (Python simulator on the Amaranth design), ``icarus`` and
``verilator`` (cocotb on the generated Verilog). Every backend takes the same stimulus and
returns the same :class:`FrontEndResult`, so results can be compared across backends and
against the reference filter.
"""

import random
import time
from dataclasses import dataclass, field
from pathlib import Path

from ...hw.arch import frames as arch_frames
from ...hw.frame_filter import ChannelKind, FrameFilter
from ...hw.frontend import (ChannelConfig, DEFAULT_CHANNELS, FrontEnd, TOPLEVEL_NAME,
                             generate_verilog, register_address)
from ..backends import amaranth as amaranth_backend
from ..backends.cocotb import CocotbBuild
from ..stimulus.uart_line import ChannelStimulus, Segments


__all__ = ["BACKENDS", "FrontEndResult", "FrontEndBench", "read_counter", "run_frame_filter"]

BACKENDS = ("amaranth", "icarus", "verilator")
#: cocotb's clock period, the Amaranth simulator's (one constant for both).
CLOCK_NS = amaranth_backend.CLOCK_NS


@dataclass
class FrontEndResult:
    """Frames in arrival order as ``(channel, bytes)``, counters per channel, flush events."""
    frames: list
    counters: list
    flushes: int
    cycles: int = 0
    seconds: float = 0.0
    mismatches: list = field(default_factory=list)

    def frames_of(self, channel):
        return [frame for k, frame in self.frames if k == channel]


def _drain_cycles(stimuli, fifo_depth):
    # The last character needs a bit time to decode; the FIFOs then empty at a byte a cycle.
    return max(s.bit_cycles for s in stimuli) * 2 + len(stimuli) * (fifo_depth + 16) + 64


class FrontEndBench:
    """One front-end configuration, built once per backend, run on many stimuli."""

    def __init__(self, channels=DEFAULT_CHANNELS, *, backend="amaranth", build_dir=None,
                 max_frame=arch_frames.DEFAULT_MAX_FRAME, fifo_depth=1024,
                 clk_freq=amaranth_backend.CLOCK_HZ, backpressure=0.0, seed=0):
        if backend not in BACKENDS:
            raise ValueError(f"Backend must be one of {', '.join(BACKENDS)}, not {backend!r}")
        self.channels = tuple(c if isinstance(c, ChannelConfig) else ChannelConfig(*c)
                              for c in channels)
        self.backend = backend
        self._params = dict(max_frame=max_frame, fifo_depth=fifo_depth, clk_freq=clk_freq)
        self.fifo_depth = fifo_depth
        self.build_dir = Path(build_dir).resolve() if build_dir is not None else None
        if not 0.0 <= backpressure < 1.0:
            raise ValueError(f"Backpressure must be a probability below 1, not {backpressure!r}")
        self.backpressure = backpressure
        self.seed = seed
        self._cocotb = (CocotbBuild(backend, build_dir, TOPLEVEL_NAME)
                        if backend != "amaranth" else None)

    def make_dut(self):
        return FrontEnd(self.channels, **self._params)

    def _drain(self, stimuli):
        # Backpressure slows the output: allow for the bytes still queued to leave.
        return round(_drain_cycles(stimuli, self.fifo_depth) / (1 - self.backpressure))

    # -- cocotb ------------------------------------------------------------------------

    def build(self):
        """Write the Verilog and compile it (cocotb backends); no-op for Amaranth."""
        if self.backend == "amaranth" or self._cocotb.built:
            return
        self._cocotb.build(generate_verilog(self.make_dut()))

    def _run_cocotb(self, stimuli, waves):
        self.build()
        channels = []
        for config, s in zip(self.channels, stimuli):
            entry = {"divisor": s.divisor, "parts": [
                {"segments": [list(seg) for seg in part]} if isinstance(part, Segments) else
                {"bytes": part.hex(), "baud": 1e9 / (s.bit_cycles * CLOCK_NS)}
                for part in s.parts]}
            if s.expected is not None:
                entry["expected"] = [frame.hex() for frame in s.expected]
            channels.append(entry)
        raw = self._cocotb.run("maglog.sim.backends.cocotb_frontend", {
            "channels": channels,
            "counter_names": list(arch_frames.COUNTER_NAMES),
            "counter_addresses": [[register_address(k, name) for name in arch_frames.COUNTER_NAMES]
                                  for k in range(len(self.channels))],
            "drain_ns": self._drain(stimuli) * CLOCK_NS,
            "backpressure": self.backpressure,
            "seed": self.seed,
        }, waves=waves)
        return FrontEndResult(
            frames=[(k, bytes.fromhex(frame)) for k, frame in raw["frames"]],
            counters=raw["counters"], flushes=raw["flushes"], cycles=raw["cycles"],
            mismatches=raw["mismatches"])

    # -- Amaranth ----------------------------------------------------------------------

    def _run_amaranth(self, stimuli, waves):
        dut = self.make_dut()
        frames = []
        flushes = [0]
        counters = []
        cycles = max(s.line_cycles() for s in stimuli) + self._drain(stimuli)

        def line_driver(k, stimulus):
            async def drive(ctx):
                ctx.set(dut.divisor[k], stimulus.divisor)
                await amaranth_backend.drive_line(ctx, dut.uart_rx[k], stimulus.line_segments())
            return drive

        async def timekeeper(ctx):
            await ctx.delay(cycles * amaranth_backend.CLOCK_PERIOD)
            for k in range(len(self.channels)):
                counters.append({name: await read_counter(ctx, dut, register_address(k, name))
                                 for name in arch_frames.COUNTER_NAMES})

        class Tagged:
            def append(self, item):
                frame, tags = item
                frames.append((tags["channel"], frame))

        ready = None
        if self.backpressure:
            rng = random.Random(self.seed)
            ready = lambda cycle: rng.random() >= self.backpressure

        async def monitor(ctx):
            await amaranth_backend.collect_frames(ctx, dut.o, Tagged(), fields=("data", "channel"),
                                             ready=ready)

        async def flush_counter(ctx):
            while True:
                await ctx.posedge(dut.flush)
                flushes[0] += 1

        testbenches = [line_driver(k, s) for k, s in enumerate(stimuli)] + [timekeeper]
        amaranth_backend.run_simulation(dut, testbenches, background=[monitor, flush_counter],
                                   name="frontend",
                                   vcd_dir=self.build_dir if waves else None)
        mismatches = []
        for k, s in enumerate(stimuli):
            got = [frame for channel, frame in frames if channel == k]
            if s.expected is not None and got != list(s.expected):
                mismatches.append(f"channel {k}: frames differ from the expected ones")
        return FrontEndResult(frames=frames, counters=counters, flushes=flushes[0],
                              cycles=cycles, mismatches=mismatches)

    def run(self, stimuli, *, waves=False):
        """Run the stimuli (one per channel) and return what came out."""
        if len(stimuli) != len(self.channels):
            raise ValueError(f"Expected a stimulus for each of {len(self.channels)} channels, "
                             f"got {len(stimuli)}")
        start = time.perf_counter()
        if self.backend == "amaranth":
            result = self._run_amaranth(stimuli, waves)
        else:
            result = self._run_cocotb(stimuli, waves)
        result.seconds = time.perf_counter() - start
        return result


async def read_counter(ctx, front_end, address):
    """One counter of a running front end, through its read port (two cycles)."""
    port = front_end.counters
    ctx.set(port.addr, address)
    ctx.set(port.r_stb, 1)
    await ctx.tick()
    ctx.set(port.r_stb, 0)
    value = ctx.get(port.r_data)
    await ctx.tick()                 # a cycle between two reads, for the scanner
    return value


def run_frame_filter(kind, events, *, max_frame=arch_frames.DEFAULT_MAX_FRAME, fifo_depth=1024,
                     ready=None, hold=None, tail_cycles=None):
    """Run a lone FrameFilter on the Amaranth simulator.

    ``events`` are bytes or ``(byte, error)`` pairs, offered one a cycle (``hold(i)`` idle
    cycles before event i); ``ready(cycle)`` is the sink's backpressure. Returns the kept
    frames, the counters after ``tail_cycles`` more cycles, and the number of flush events.
    """
    dut = FrameFilter(kind, max_frame=max_frame, fifo_depth=fifo_depth)
    events = [(e, False) if isinstance(e, int) else e for e in events]
    frames, counters, flushes = [], {}, [0]

    async def source(ctx):
        await amaranth_backend.feed_stream(ctx, dut.i, [{"data": b, "framing_error": int(err)}
                                       for b, err in events], hold=hold)
        await ctx.tick().repeat(tail_cycles or fifo_depth + 16)
        counters.update({name: ctx.get(getattr(dut.counters, name))
                         for name in arch_frames.COUNTER_NAMES})

    async def sink(ctx):
        await amaranth_backend.collect_frames(ctx, dut.o, frames, ready=ready)

    async def flush(ctx):
        while True:
            await ctx.posedge(dut.flush)
            flushes[0] += 1

    amaranth_backend.run_simulation(dut, [source], background=[sink, flush],
                               name=f"filter_{ChannelKind(kind).value}")
    return frames, counters, flushes[0]
