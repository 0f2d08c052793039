"""Run the serial front end on a stimulus with any backend and gather what it kept.

Backends: ``amaranth`` (Python simulator on the Amaranth design), ``icarus`` and
``verilator`` (cocotb on the generated Verilog). Every backend takes the same stimulus and
returns the same :class:`FrontEndResult`, so results can be compared across backends and
against the reference filter.
"""

import json
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..hw.arch import frames as arch_frames
from ..hw.arch import uart as arch_uart
from ..hw.frontend import ChannelConfig, DEFAULT_CHANNELS, FrontEnd, TOPLEVEL_NAME, generate_verilog
from . import amaranth_tb
from .uart_line import encode


__all__ = ["BACKENDS", "ChannelStimulus", "FrontEndResult", "FrontEndBench", "run_frontend"]

BACKENDS = ("amaranth", "icarus", "verilator")
#: cocotb's clock period; the Amaranth simulator's is the same.
CLOCK_NS = 20
assert abs(amaranth_tb.CLOCK_PERIOD * 1e9 - CLOCK_NS) < 1e-9


@dataclass
class ChannelStimulus:
    """What one serial line carries.

    Either ``data`` (plain 8N1 characters back to back at the divisor's nominal bit time) or
    ``segments`` (``(level, cycles)`` pairs, see :mod:`maglog.sim.uart_line`, for baud
    error and line faults). ``expected`` frames, if given, are checked in order by the
    cocotb scoreboard as they arrive.
    """
    divisor: int
    data: bytes | None = None
    segments: list | None = None
    expected: list | None = None

    def __post_init__(self):
        if (self.data is None) == (self.segments is None):
            raise ValueError("A channel's stimulus is either data or segments, not both "
                             "or neither")

    @property
    def bit_cycles(self):
        return arch_uart.OVERSAMPLING * self.divisor

    def line_segments(self):
        if self.segments is not None:
            return list(self.segments)
        return encode(self.data, bit_cycles=self.bit_cycles).segments

    def line_cycles(self):
        return sum(cycles for _, cycles in self.line_segments())


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
                 max_frame=arch_frames.DEFAULT_MAX_FRAME, fifo_depth=1024, clk_freq=50e6):
        if backend not in BACKENDS:
            raise ValueError(f"Backend must be one of {', '.join(BACKENDS)}, not {backend!r}")
        self.channels = tuple(c if isinstance(c, ChannelConfig) else ChannelConfig(*c)
                              for c in channels)
        self.backend = backend
        self._params = dict(max_frame=max_frame, fifo_depth=fifo_depth, clk_freq=clk_freq)
        self.fifo_depth = fifo_depth
        self.build_dir = Path(build_dir) if build_dir is not None else None
        self._built = False
        self._runs = 0

    def make_dut(self):
        return FrontEnd(self.channels, **self._params)

    # -- cocotb ------------------------------------------------------------------------

    def build(self):
        """Write the Verilog and compile it (cocotb backends); no-op for Amaranth."""
        if self.backend == "amaranth" or self._built:
            return
        from cocotb_tools.runner import get_runner
        if self.build_dir is None:
            raise ValueError("cocotb backends need a build directory")
        if shutil.which("iverilog" if self.backend == "icarus" else "verilator") is None:
            raise RuntimeError(f"{self.backend} is not on PATH (run scripts/setup.sh)")
        self.build_dir.mkdir(parents=True, exist_ok=True)
        source = self.build_dir / f"{TOPLEVEL_NAME}.v"
        source.write_text(generate_verilog(self.make_dut()))
        runner = get_runner(self.backend)
        build_args = ["-Wno-fatal"] if self.backend == "verilator" else []
        runner.build(sources=[source], hdl_toplevel=TOPLEVEL_NAME, build_dir=self.build_dir,
                     build_args=build_args, timescale=("1ns", "1ps"), always=True,
                     log_file=self.build_dir / "build.log")
        self._runner = runner
        self._built = True

    def _run_cocotb(self, stimuli, waves):
        self.build()
        self._runs += 1
        run_dir = self.build_dir / f"run{self._runs}"
        run_dir.mkdir(parents=True, exist_ok=True)
        channels = []
        for config, s in zip(self.channels, stimuli):
            entry = {"divisor": s.divisor}
            if s.data is not None:
                entry["bytes"] = s.data.hex()
                entry["baud"] = 1e9 / (s.bit_cycles * CLOCK_NS)
            else:
                entry["segments"] = [list(seg) for seg in s.segments]
            if s.expected is not None:
                entry["expected"] = [frame.hex() for frame in s.expected]
            channels.append(entry)
        stimulus_file = run_dir / "stimulus.json"
        result_file = run_dir / "result.json"
        stimulus_file.write_text(json.dumps({
            "channels": channels,
            "counter_names": list(arch_frames.COUNTER_NAMES),
            "drain_ns": _drain_cycles(stimuli, self.fifo_depth) * CLOCK_NS,
        }))
        self._runner.test(test_module="maglog.sim.cocotb_frontend", hdl_toplevel=TOPLEVEL_NAME,
                          build_dir=self.build_dir, test_dir=run_dir, waves=waves,
                          extra_env={"MAGLOG_STIMULUS": str(stimulus_file),
                                     "MAGLOG_RESULT": str(result_file),
                                     "COCOTB_LOG_LEVEL": "WARNING"},
                          log_file=run_dir / "sim.log")
        raw = json.loads(result_file.read_text())
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
        cycles = max(s.line_cycles() for s in stimuli) + _drain_cycles(stimuli, self.fifo_depth)

        def line_driver(k, stimulus):
            async def drive(ctx):
                ctx.set(dut.divisor[k], stimulus.divisor)
                await amaranth_tb.drive_line(ctx, dut.uart_rx[k], stimulus.line_segments())
            return drive

        async def timekeeper(ctx):
            await ctx.delay(cycles * amaranth_tb.CLOCK_PERIOD)
            for k in range(len(self.channels)):
                counters.append({name: ctx.get(getattr(dut.counters[k], name))
                                 for name in arch_frames.COUNTER_NAMES})

        async def monitor(ctx):
            current = bytearray()
            ctx.set(dut.o.ready, 1)
            while True:
                if not ctx.get(dut.o.valid):
                    await ctx.changed(dut.o.valid)
                _, _, valid, payload = await ctx.tick().sample(dut.o.valid, dut.o.payload)
                if valid:
                    current.append(payload.data)
                    if payload.last:
                        frames.append((payload.channel, bytes(current)))
                        current.clear()

        async def flush_counter(ctx):
            while True:
                await ctx.posedge(dut.flush)
                flushes[0] += 1

        testbenches = [line_driver(k, s) for k, s in enumerate(stimuli)] + [timekeeper]
        amaranth_tb.run_simulation(dut, testbenches, background=[monitor, flush_counter],
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


def run_frontend(stimuli, *, channels=DEFAULT_CHANNELS, backend="amaranth", build_dir=None,
                 **params):
    """Build the front end for ``backend`` and run ``stimuli`` (one per channel) once."""
    bench = FrontEndBench(channels, backend=backend, build_dir=build_dir, **params)
    return bench.run(stimuli)
