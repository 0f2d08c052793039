"""Serial CRC generators of the SD bus: CRC7 (CMD line) and CRC16 (each DAT line)."""

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from ..arch import sd as arch


__all__ = ["SerialCrc", "Crc7", "Crc16", "crc16_lanes_signature", "Crc16Lanes",
           "SharedCrc16Lanes"]


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


def crc16_lanes_signature(lanes=4):
    """The user's side of :class:`Crc16Lanes` (an engine's ``Out`` port to connect to it):
    ``clear``, ``en``, ``bits`` out, each line's ``crc`` in."""
    return wiring.Signature({
        "clear": Out(1),
        "en":    Out(1),
        "bits":  Out(lanes),
        "crc":   In(arch.CRC16_BITS).array(lanes),
    })


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


class SharedCrc16Lanes(wiring.Component):
    """One :class:`Crc16Lanes` for several users that never use it at the same time (the SD
    host's block writer and reader: it runs one data phase at a time).

    ``clear`` and ``en`` are any user's; ``bits`` are those of the first user (in order)
    whose ``en`` is high. Every user sees the same ``crc``. Users that overlap corrupt each
    other's CRCs.

    Members
    -------
    users : ``In(crc16_lanes_signature(lanes))`` × users
    """
    def __init__(self, lanes=4, users=2):
        if not isinstance(users, int) or users < 1:
            raise ValueError(f"Users must be a positive integer, not {users!r}")
        self._lanes = Crc16Lanes(lanes)
        self._users = users
        super().__init__({"users": In(crc16_lanes_signature(lanes)).array(users)})

    def elaborate(self, platform):
        m = Module()
        m.submodules.lanes = lanes = self._lanes
        bits = self.users[-1].bits
        for user in reversed(self.users[:-1]):
            bits = Mux(user.en, user.bits, bits)
        m.d.comb += [
            lanes.clear.eq(Cat(user.clear for user in self.users).any()),
            lanes.en.eq(Cat(user.en for user in self.users).any()),
            lanes.bits.eq(bits),
        ]
        for user in self.users:
            m.d.comb += [user.crc[lane].eq(lanes.crc[lane]) for lane in range(len(user.crc))]
        return m
