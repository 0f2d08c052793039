"""Serial CRC generators of the SD bus: CRC7 (CMD line) and CRC16 (each DAT line)."""

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from ..arch import sd as arch


__all__ = ["SerialCrc", "Crc7", "Crc16", "Crc16Lanes"]


class SerialCrc(wiring.Component):
    """A bit-serial CRC with zero initial value, fed most significant bit first.

    One bit a cycle when ``en``; ``clear`` (which wins over ``en``) returns the register to
    zero. After the message's last bit, ``crc`` holds the remainder of M(x)·x^n / G(x), the
    value that is sent after the message, most significant bit first.

    Parameters
    ----------
    width : int
        Degree n of the generator.
    poly : int
        The generator without its x^n term (e.g. 0x09 for x^7 + x^3 + 1).
    """
    def __init__(self, width, poly):
        if not isinstance(width, int) or width < 1:
            raise ValueError(f"CRC width must be a positive integer, not {width!r}")
        if not isinstance(poly, int) or not 0 < poly < 1 << width:
            raise ValueError(f"Generator must be a nonzero integer below 2**{width}, "
                             f"not {poly!r}")
        self._width = width
        self._poly = poly
        super().__init__({
            "clear": In(1),
            "en":    In(1),
            "bit":   In(1),
            "crc":   Out(width),
        })

    def elaborate(self, platform):
        m = Module()
        feedback = self.bit ^ self.crc[-1]
        shifted = Cat(C(0, 1), self.crc[:-1])
        with m.If(self.clear):
            m.d.sync += self.crc.eq(0)
        with m.Elif(self.en):
            m.d.sync += self.crc.eq(shifted ^ Mux(feedback, self._poly, 0))
        return m


class Crc7(SerialCrc):
    """CRC7 of commands and responses (PLSS §4.5)."""
    def __init__(self):
        super().__init__(arch.CRC7_BITS, arch.CRC7_POLY)


class Crc16(SerialCrc):
    """CRC16 of one DAT line (PLSS §4.5)."""
    def __init__(self):
        super().__init__(arch.CRC16_BITS, arch.CRC16_POLY)


class Crc16Lanes(wiring.Component):
    """One CRC16 per DAT line: in 4-bit mode each line carries its own CRC.

    Members
    -------
    clear, en : ``In(1)``
    bits : ``In(lanes)``
        This cycle's bit of each line (DAT0 in bit 0).
    crc : ``Out(16)`` × lanes
    """
    def __init__(self, lanes=4):
        if lanes not in (1, 4):
            raise ValueError(f"An SD bus has 1 or 4 data lines, not {lanes!r}")
        self._lanes = lanes
        super().__init__({
            "clear": In(1),
            "en":    In(1),
            "bits":  In(lanes),
            "crc":   Out(arch.CRC16_BITS).array(lanes),
        })

    def elaborate(self, platform):
        m = Module()
        for lane in range(self._lanes):
            crc = m.submodules[f"lane{lane}"] = Crc16()
            m.d.comb += [
                crc.clear.eq(self.clear),
                crc.en.eq(self.en),
                crc.bit.eq(self.bits[lane]),
                self.crc[lane].eq(crc.crc),
            ]
        return m
