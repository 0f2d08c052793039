"""Amaranth simulator building blocks: line drivers and stream sources and sinks.

They are edge-driven where they can be (a line segment is one `delay`, an idle output stream
is one `changed`), because per-cycle Python is what limits the simulator's speed.
"""

import contextlib
import os
from pathlib import Path

from amaranth.sim import Simulator

from ..sw.bus import RegisterBus


__all__ = ["CLOCK_HZ", "CLOCK_PERIOD", "CLOCK_NS", "ClockedBus", "run_simulation", "drive_line", "feed_stream", "FrameAssembler",
           "collect_frames", "collect_payloads"]

#: The simulated system clock of every backend (Amaranth simulator and cocotb): 50 MHz, as
#: the boards' oscillators. Periods below are derived from it, never written again.
CLOCK_HZ = 50_000_000
#: Its period in seconds (Amaranth simulator) ...
CLOCK_PERIOD = 1 / CLOCK_HZ
#: ... and in nanoseconds (cocotb's ``Clock`` and ``Timer``).
CLOCK_NS = 1e9 / CLOCK_HZ

#: Set to a directory to get a VCD of every Amaranth simulation written there.
VCD_ENV = "MAGLOG_VCD_DIR"


def run_simulation(dut, testbenches, *, background=(), name="sim", vcd_dir=None,
                   deadline=None, clock_period=CLOCK_PERIOD):
    """Simulate ``dut`` with the given async testbenches (critical) and background ones.

    The clock runs at ``clock_period`` seconds (default :data:`CLOCK_PERIOD`); a test that
    tells firmware another system clock runs the simulation at that clock too.

    A VCD is written into ``vcd_dir`` (or ``$MAGLOG_VCD_DIR``) when one is given: never into
    the working tree by default. ``deadline`` (seconds of simulated time) turns a hang into
    a ``TimeoutError``.
    """
    sim = Simulator(dut)
    sim.add_clock(clock_period)
    for tb in testbenches:
        sim.add_testbench(tb)
    for tb in background:
        sim.add_testbench(tb, background=True)
    if deadline is not None:
        async def watchdog(ctx):
            await ctx.delay(deadline)
            raise TimeoutError(f"simulation '{name}' did not finish within {deadline} s "
                               f"of simulated time")
        sim.add_testbench(watchdog, background=True)
    vcd_dir = vcd_dir or os.environ.get(VCD_ENV)
    if vcd_dir:
        path = Path(vcd_dir) / f"{name}.vcd"
        path.parent.mkdir(parents=True, exist_ok=True)
        writer = sim.write_vcd(str(path))
    else:
        writer = contextlib.nullcontext()
    with writer:
        sim.run()


class ClockedBus(RegisterBus):
    """A register bus on the Amaranth simulator that keeps time in clock cycles: a
    subclass's accesses add the cycles they take to ``_cycles``; :meth:`wait` jumps (one
    delay, then back onto a clock edge) and :meth:`now` is the cycles times the period."""
    def __init__(self, ctx, *, clock_period):
        self._ctx, self._period = ctx, clock_period
        self._cycles = 0

    async def wait(self, seconds):
        cycles = max(1, round(seconds / self._period))
        await self._ctx.delay((cycles - 1) * self._period)
        await self._ctx.tick()
        self._cycles += cycles

    def now(self):
        return self._cycles * self._period


async def drive_line(ctx, line, segments):
    """Drive a serial line through ``(level, cycles)`` segments (see sim.uart_line)."""
    for level, cycles in segments:
        ctx.set(line, level)
        await ctx.delay(cycles * CLOCK_PERIOD)


async def feed_stream(ctx, stream, payloads, *, hold=None):
    """Offer each payload on ``stream`` until it is taken; ``hold(i)`` idle cycles before i."""
    for index, payload in enumerate(payloads):
        if hold is not None:
            for _ in range(hold(index)):
                ctx.set(stream.valid, 0)
                await ctx.tick()
        ctx.set(stream.payload, payload)
        ctx.set(stream.valid, 1)
        # (plain awaits, not tick().until(): an async generator still waiting when the
        # simulation ends is reported by Python as an unraisable exception)
        while True:
            _, _, ready = await ctx.tick().sample(stream.ready)
            if ready:
                break
    ctx.set(stream.valid, 0)


class FrameAssembler:
    """A sink for :func:`collect_payloads` that joins ``last``-marked bytes into frames.

    Each frame is appended to ``frames`` as ``bytes`` when ``fields`` is ``("data",)``,
    otherwise as ``(bytes, {field: value of the frame's last byte})``.
    """
    def __init__(self, frames, fields=("data",)):
        self.frames = frames
        self._fields = [f for f in fields if f != "data"]
        self._current = bytearray()

    def append(self, payload):
        self._current.append(payload.data)
        if payload.last:
            frame = bytes(self._current)
            self._current.clear()
            if self._fields:
                self.frames.append((frame, {f: getattr(payload, f) for f in self._fields}))
            else:
                self.frames.append(frame)


async def collect_frames(ctx, stream, sink, *, fields=("data",), ready=None):
    """Gather frames from a ``last``-marked byte stream into ``sink`` (a list); see
    :class:`FrameAssembler` for the form and :func:`collect_payloads` for ``ready``."""
    await collect_payloads(ctx, stream, FrameAssembler(sink, fields), ready=ready)


async def collect_payloads(ctx, stream, sink, *, ready=None):
    """Append every payload taken from ``stream`` to ``sink``.

    ``ready(cycle)`` gives backpressure; without it the sink is always ready and sleeps
    while the stream is idle (one ``changed`` trigger instead of a tick per cycle).
    """
    cycle = 0
    if ready is None:
        ctx.set(stream.ready, 1)
    while True:
        if ready is None:
            if not ctx.get(stream.valid):
                await ctx.changed(stream.valid)
            rdy = True
        else:
            rdy = bool(ready(cycle))
            ctx.set(stream.ready, rdy)
        _, _, valid, payload = await ctx.tick().sample(stream.valid, stream.payload)
        cycle += 1
        if valid and rdy:
            sink.append(payload)
