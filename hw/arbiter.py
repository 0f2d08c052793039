"""Frame arbiter: merges the channels' frame streams without interleaving frames."""

from amaranth import *
from amaranth.lib import data, stream, wiring
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from .frame_fifo import FrameByte


__all__ = ["TaggedFrameByte", "FrameArbiter"]


class TaggedFrameByte(data.StructLayout):
    """A frame byte with the index of the channel it came from."""
    def __init__(self, channels):
        super().__init__({
            "data":    8,
            "last":    1,
            "channel": max(1, ceil_log2(channels)),
        })


class FrameArbiter(wiring.Component):
    """Round-robin arbiter at frame granularity.

    When idle it grants the first channel with a frame ready, searching from the one after
    the channel served last, so every channel is served within N frames. The grant holds
    until the byte marked ``last`` has passed, so frames never interleave.

    Parameters
    ----------
    channels : int
        Number of input streams.

    Members
    -------
    i : ``In(stream.Signature(FrameByte))`` × channels
        Inputs ``i[0]`` … ``i[N-1]`` (a channel must present a frame's bytes back to back
        once its first byte is valid, as :class:`FrameFifo` does, or the output waits).
    o : ``Out(stream.Signature(TaggedFrameByte(channels)))``
        Merged frames.
    """
    def __init__(self, channels):
        if not isinstance(channels, int) or channels < 1:
            raise ValueError(f"Channel count must be a positive integer, not {channels!r}")
        self._channels = channels
        super().__init__({
            "i": In(stream.Signature(FrameByte())).array(channels),
            "o": Out(stream.Signature(TaggedFrameByte(channels))),
        })

    def elaborate(self, platform):
        m = Module()
        n = self._channels

        # At least one bit, as the payload's `channel`: with one channel a zero-width index
        # would be `[-1:0]` in the Verilog (Verilator: ASCRANGE).
        index = range(max(n, 2))
        grant = Signal(index, init=n - 1)      # channel served (or last served when idle)
        busy  = Signal()

        valids = Cat(self.i[k].valid for k in range(n))

        with m.If(~busy):
            # Round robin: try grant+1, grant+2, ... in that order; the first ready wins.
            # Walk the priority order backwards so the highest priority is assigned last
            # (each grant's order is a constant: no index arithmetic).
            with m.Switch(grant):
                for last in range(n):
                    with m.Case(last):
                        for step in reversed(range(1, n + 1)):
                            candidate = (last + step) % n
                            with m.If(valids[candidate]):
                                m.d.sync += [grant.eq(candidate), busy.eq(1)]

        with m.Switch(grant):
            for k in range(n):
                with m.Case(k):
                    m.d.comb += [
                        self.o.valid.eq(busy & self.i[k].valid),
                        self.o.payload.data.eq(self.i[k].payload.data),
                        self.o.payload.last.eq(self.i[k].payload.last),
                        self.o.payload.channel.eq(k),
                        self.i[k].ready.eq(busy & self.o.ready),
                    ]
        with m.If(self.o.valid & self.o.ready & self.o.payload.last):
            m.d.sync += busy.eq(0)

        return m
