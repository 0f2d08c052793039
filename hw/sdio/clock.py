"""SD bus clock: a divided clock with strobes for the engines, that can pause low."""

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out


__all__ = ["TICK_BITS", "TICK_CLOCKS", "SdClock"]

#: The long timeouts (busy, read access) count ticks of TICK_CLOCKS SD clocks.
TICK_BITS = 8
TICK_CLOCKS = 1 << TICK_BITS


class SdClock(wiring.Component):
    """The SD clock, ``f_sys / (2 * (divisor + 1))``.

    The engines change the bus outputs on ``fall`` and sample the bus on ``rise`` (both are
    high in the system clock cycle whose end is that edge of ``clk``). The clock pauses low,
    before a rising edge, while ``run`` is low: an engine whose next bit is not ready holds
    ``run`` low instead of letting the card sample a bit that is not there yet, so the bus
    never underruns.

    Members
    -------
    divisor : ``In(divisor_bits)``
        Half period minus one, in system clock cycles (0 gives f_sys / 2).
    run : ``In(1)``
        Allow the next rising edge.
    clk : ``Out(1)``
        The SD clock (registered).
    rise, fall : ``Out(1)``
        The clock rises / falls at the end of this cycle.
    tick : ``Out(1)``
        With every :data:`TICK_CLOCKS`-th ``rise`` (a free-running count of rising edges):
        the time base of the long timeouts.
    """
    def __init__(self, *, divisor_bits=10):
        if not isinstance(divisor_bits, int) or divisor_bits < 1:
            raise ValueError(f"Divisor width must be a positive integer, not {divisor_bits!r}")
        super().__init__({
            "divisor": In(divisor_bits),
            "run":     In(1),
            "clk":     Out(1),
            "rise":    Out(1),
            "fall":    Out(1),
            "tick":    Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        # Cycles left in this half period: loaded with the divisor at each edge, the edge
        # comes when it reaches 0 (a new divisor takes effect from the next edge).
        count = Signal.like(self.divisor)
        rises = Signal(TICK_BITS)
        due = Signal()
        m.d.comb += [
            due.eq(count == 0),
            self.rise.eq(due & ~self.clk & self.run),
            self.fall.eq(due & self.clk),
            self.tick.eq(self.rise & rises.all()),
        ]
        with m.If(self.rise | self.fall):
            m.d.sync += [count.eq(self.divisor), self.clk.eq(~self.clk)]
        with m.Elif(~due):
            m.d.sync += count.eq(count - 1)
        with m.If(self.rise):
            m.d.sync += rises.eq(rises + 1)
        return m
