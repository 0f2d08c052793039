"""amaranth-soc for the whole of hw/: the only module that imports it.

amaranth-soc is not published on PyPI (its name holds an empty placeholder); luna-soc ships
the upstream code and, when imported, puts its vendored folder on ``sys.path``. Importing
the same code a second way (``luna_soc.gateware.vendor.amaranth_soc``) would make a second
copy of every class, so everything in hw/ takes ``csr``, ``wishbone`` and ``MemoryMap`` from
here.
"""

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In

import luna_soc

from amaranth_soc import csr, wishbone
from amaranth_soc.csr.wishbone import WishboneCSRBridge
from amaranth_soc.memory import MemoryMap


__all__ = ["csr", "wishbone", "MemoryMap", "WishboneCSRBridge", "WordBridge", "VENDOR"]

#: Where amaranth-soc came from (for reports).
VENDOR = luna_soc.__name__


class WordBridge(wiring.Component):
    """A CSR bridge for registers of one bus word each: a drop-in for ``csr.Bridge``.

    amaranth-soc's ``csr.Multiplexer`` (inside ``csr.Bridge``) keeps a read and a write
    shadow as wide as the widest register, with their muxes, to make registers wider than
    the bus atomic. With every register one word wide there is nothing to make atomic: the
    register's ``r_stb`` is high in the strobe's cycle and its word is on ``r_data`` in the
    next cycle only (zero otherwise, as a CSR decoder ORs its windows), as from the
    multiplexer; a write reaches the register's fields in the strobe's cycle (they take it
    at that edge, one cycle before the multiplexer's shadow would pass it on).

    Parameters
    ----------
    memory_map : MemoryMap
        The registers (``csr.Builder(...).as_memory_map()``), each one word of the bus.

    Members
    -------
    bus : ``In(csr.Signature(addr_width=memory_map.addr_width, data_width=...))``
    """
    def __init__(self, memory_map):
        for reg, name, (start, end) in memory_map.resources():
            if end - start != 1:
                raise ValueError(f"Register {'_'.join(str(p) for p in name)} takes "
                                 f"{end - start} bus words; WordBridge takes one-word "
                                 f"registers only")
        self._memory_map = memory_map
        super().__init__({"bus": In(csr.Signature(addr_width=memory_map.addr_width,
                                                  data_width=memory_map.data_width))})
        self.bus.memory_map = memory_map

    def elaborate(self, platform):
        m = Module()
        bus = self.bus
        r_word = 0
        for reg, name, (start, _) in self._memory_map.resources():
            label = "_".join(str(part) for part in name)
            m.submodules[label] = reg
            select = Signal(name=f"select_{label}")
            m.d.comb += select.eq(bus.addr == start)
            if reg.element.access.readable():
                m.d.comb += reg.element.r_stb.eq(bus.r_stb & select)
                r_word = r_word | Mux(select, reg.element.r_data, 0)
            if reg.element.access.writable():
                m.d.comb += [
                    reg.element.w_stb.eq(bus.w_stb & select),
                    reg.element.w_data.eq(bus.w_data),
                ]
        # Loaded in every cycle (zero without a read), so it needs no reset.
        r_data = Signal.like(bus.r_data, reset_less=True)
        m.d.sync += r_data.eq(Mux(bus.r_stb, r_word, 0))
        m.d.comb += bus.r_data.eq(r_data)
        return m
