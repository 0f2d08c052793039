"""The storage path: frames into the SDRAM ring, sectors through the DMA to the SD card."""

from amaranth import *
from amaranth.lib import stream, wiring
from amaranth.lib.wiring import In, Out

from .dma import Dma
from .frame_fifo import FrameByte
from .ringbuffer import RingBuffer
from .sdio.host import SdioHost, sd_pins_signature
from .sdram import SdramController, sdram_pins_signature
from .soc import csr


__all__ = ["Storage", "sd_pins_signature"]


class Storage(wiring.Component):
    """Ring buffer over the SDRAM controller, DMA and SD host, with their registers behind
    one CSR bus (windows ``sdio`` and ``dma``).

    Members
    -------
    i : ``In(stream.Signature(FrameByte))``
        Kept frames, as the arbiter sends them.
    bus : ``In(csr.Signature(...))``
    sdram : ``Out(sdram_pins_signature(...))``; sd : ``Out(sd_pins_signature())``
    sdram_ready : ``Out(1)``
    dma_done : ``Out(1)``
        One-cycle strobe as the DMA's ``busy`` falls.
    ring_overflow : ``Out(1)``
        One-cycle strobe as the ring drops a frame (its ``dropped`` count moves on).
    sd_error : ``Out(1)``
        One-cycle strobe as an SD command or data phase ends with an error bit set (an
        error bit of the host's ``status`` rising: every phase clears its bits as it
        starts).
    """
    def __init__(self, chip, *, clk_freq, cas_latency=2, capacity=None):
        self.ctrl = SdramController(chip, clk_freq=clk_freq, cas_latency=cas_latency)
        self.ring = RingBuffer(chip.geometry, capacity=capacity)
        self.dma = Dma(level_bits=self.ring.dma.signature.level_bits)
        self.sdio = SdioHost()
        self._decoder = csr.Decoder(addr_width=5, data_width=32)
        self._decoder.add(self.sdio.bus, name="sdio")
        self._decoder.add(self.dma.bus, name="dma")
        super().__init__({
            "i":           In(stream.Signature(FrameByte())),
            "bus":         In(csr.Signature(addr_width=self._decoder.bus.addr_width,
                                            data_width=32)),
            "sdram":       Out(sdram_pins_signature(chip.geometry)),
            "sd":          Out(sd_pins_signature()),
            "sdram_ready":   Out(1),
            "dma_done":      Out(1),
            "ring_overflow": Out(1),
            "sd_error":      Out(1),
        })
        self.bus.memory_map = self._decoder.bus.memory_map

    def elaborate(self, platform):
        m = Module()
        ctrl, ring, dma, sdio = self.ctrl, self.ring, self.dma, self.sdio
        m.submodules.ctrl, m.submodules.ring = ctrl, ring
        m.submodules.dma, m.submodules.sdio = dma, sdio
        m.submodules.decoder = self._decoder
        wiring.connect(m, wiring.flipped(self.bus), self._decoder.bus)

        wiring.connect(m, wiring.flipped(self.i), ring.i)
        wiring.connect(m, ring.mem, ctrl.i)
        wiring.connect(m, ctrl.o, ring.mem_data)
        wiring.connect(m, ctrl.pins, wiring.flipped(self.sdram))
        m.d.comb += self.sdram_ready.eq(ctrl.ready)

        wiring.connect(m, dma.ring, ring.dma)
        wiring.connect(m, dma.sd_i, sdio.i)
        wiring.connect(m, sdio.o, dma.sd_o)

        wiring.connect(m, sdio.sd, wiring.flipped(self.sd))

        # Events for the SoC.
        dma_busy = Signal()
        # The drop count moves on by one at a time, so its lowest bit changes at every drop.
        dropped_lsb = Signal()
        m.d.sync += [dma_busy.eq(dma.busy), dropped_lsb.eq(ring.dma.dropped[0])]
        # The host's status register fields (read here, as the CPU reads them).
        status = sdio._status.f
        errors = Cat(Value.cast(status.cmd.r_data), Value.cast(status.write.r_data),
                     Value.cast(status.read.r_data), status.busy_timeout.r_data)
        errors_before = Signal.like(errors)
        m.d.sync += errors_before.eq(errors)
        m.d.comb += [
            self.dma_done.eq(dma_busy & ~dma.busy),
            self.ring_overflow.eq(dropped_lsb != ring.dma.dropped[0]),
            self.sd_error.eq((errors & ~errors_before).any()),
        ]
        return m
