"""Event counters kept in one block RAM, one word each, behind a CSR-style read port.

A bank of N w-bit counters in flip-flops costs N*w flip-flops and about as many LUTs again
for the adders; here they share one memory and one adder. Each counter has a 1-bit
*pending* flag that its event strobe sets; a scanner walks the memory word by word, and
where the flag of the word it reads is set it writes the word back plus one on the next
cycle (taking the flag as it reads; an event in that same cycle sets it again).

No event is lost as long as every counter's events are further apart than a sweep of the
scanner: a flag holds one event, and it is taken at the latest one sweep after it is set.
A sweep reads each of the ``depth`` words once; a read by the bus takes the memory's read
port for its cycle and holds the scanner back by one, so a sweep lasts ``depth`` cycles,
and at most ``2 * depth`` when the bus reads every other cycle (a Wishbone-to-CSR bridge
strobes at most every third cycle: strobe, data and ack, then back to idle).
:attr:`CounterBank.min_event_spacing` is the spacing a user must guarantee; see
:class:`~maglog.hw.frontend.FrontEnd` for why its filters' events keep it.

Reset clears the counters: the scanner first writes zeros to every word (one sweep of
``depth`` cycles, whatever the bus does; reads return 0 meanwhile). Events in that sweep
wait in their flags, as if they came at its end: the spacing counts from there.
"""

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.memory import Memory
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2


__all__ = ["CounterBank", "read_signature"]


def read_signature(addr_width, data_width):
    """A read-only CSR-style port, seen from the reader: ``r_data`` holds the word at
    ``addr`` on the cycle after ``r_stb`` was high, and zero on every other cycle."""
    return wiring.Signature({
        "addr":   Out(addr_width),
        "r_stb":  Out(1),
        "r_data": In(data_width),
    })


class CounterBank(wiring.Component):
    """Counters in one memory, one word each at a given word address.

    Parameters
    ----------
    addresses : sequence of int
        Word address of each counter, in ``events`` order (distinct). Words at other
        addresses read as zero.
    width : int
        Bits per counter (they wrap at ``2**width``).

    Members
    -------
    events : ``In(len(addresses))``
        One-cycle strobes, one bit per counter; a counter's strobes must be at least
        ``min_event_spacing`` cycles apart (an event in the ``depth`` cycles after reset
        counts as one at their end).
    read : ``In(read_signature(addr_width, width))``
        The words, by address; a read may come on any cycle, but not on two in a row
        (see the module's notes).
    """
    def __init__(self, addresses, *, width=32):
        addresses = tuple(addresses)
        if not addresses or not all(isinstance(a, int) and a >= 0 for a in addresses):
            raise ValueError(f"Counter addresses must be non-negative integers, "
                             f"not {addresses!r}")
        if len(set(addresses)) != len(addresses):
            raise ValueError(f"Counter addresses must be distinct, not {addresses!r}")
        if not isinstance(width, int) or not 2 <= width <= 64:
            raise ValueError(f"Counter width must be an integer from 2 to 64, not {width!r}")
        self._addresses = addresses
        self._width = width
        self._addr_width = max(1, ceil_log2(max(addresses) + 1))
        self._depth = 1 << self._addr_width
        self._memory = Memory(shape=width, depth=self._depth, init=[])
        super().__init__({
            "events": In(len(addresses)),
            "read":   In(read_signature(self._addr_width, width)),
        })

    @property
    def addresses(self):
        return self._addresses

    @property
    def memory(self):
        """The words (for a simulator to look at or preset)."""
        return self._memory

    @property
    def addr_width(self):
        return self._addr_width

    @property
    def depth(self):
        """Words of memory (a power of two): the scanner's sweep."""
        return self._depth

    @property
    def min_event_spacing(self):
        """Cycles between two events of one counter that no reading can outrun: a sweep with
        the bus reading every other cycle, plus the cycle of the write-back."""
        return 2 * self._depth + 1

    def elaborate(self, platform):
        m = Module()
        width, depth = self._width, self._depth
        m.submodules.memory = memory = self._memory
        rd = memory.read_port(transparent_for=())
        wr = memory.write_port()

        clearing = Signal(init=1)               # the reset sweep writing zeros
        scan     = Signal(self._addr_width)     # the word the scanner reads (or clears) next
        pending  = Signal(len(self._addresses)) # an event not yet counted, per counter
        take     = Signal()                     # last cycle's read was of a pending counter
        take_at  = Signal(self._addr_width, reset_less=True)

        steal = self.read.r_stb
        m.d.comb += rd.addr.eq(Mux(steal, self.read.addr, scan))

        # Counters the scanner takes this cycle: the one at `scan` when the read port is its.
        taken = Signal(len(self._addresses))
        scanning = ~clearing & ~steal
        m.d.comb += taken.eq(Cat(scanning & (scan == a) for a in self._addresses))
        m.d.sync += pending.eq((pending & ~taken) | self.events)
        # The flag of the word at `scan` (a multiplexer, not an OR of one AND per counter).
        flags = Signal(self._depth)
        m.d.comb += [flags[a].eq(pending[k]) for k, a in enumerate(self._addresses)]
        m.d.sync += take.eq(scanning & flags.bit_select(scan, 1))
        with m.If(clearing | ~steal):            # clearing needs the write port only
            m.d.sync += [scan.eq(scan + 1), take_at.eq(scan)]

        with m.If(clearing):
            m.d.comb += [wr.addr.eq(scan), wr.data.eq(0), wr.en.eq(1)]
            with m.If(scan == depth - 1):
                m.d.sync += clearing.eq(0)
        with m.Else():
            # The word read last cycle, plus one, to where it came from.
            m.d.comb += [wr.addr.eq(take_at), wr.data.eq(rd.data + 1), wr.en.eq(take)]

        # The bus's read data: the cycle after its strobe only, and zero while clearing.
        valid = Signal()
        m.d.sync += valid.eq(steal & ~clearing)
        m.d.comb += self.read.r_data.eq(Mux(valid, rd.data, 0))
        return m
