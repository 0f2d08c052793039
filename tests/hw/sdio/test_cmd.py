"""CmdEngine with SdClock: command bits on the wire, response checks, timeouts.

The card side here is a minimal responder written in the test from the spec's framing, with
CRCs from the `crc` package; the full card model is exercised by the host tests.
"""

import crc
import pytest
from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from maglog.hw.arch import sd as arch
from maglog.hw.sdio.clock import SdClock
from maglog.hw.sdio.cmd import CmdEngine, ResponseKind
from maglog.sim.backends.amaranth import run_simulation

CRC7 = crc.Calculator(crc.Configuration(width=8, polynomial=arch.CRC7_POLY << 1, init_value=0,
                                        final_xor_value=0, reverse_input=False,
                                        reverse_output=False))


def crc7(data):
    return CRC7.checksum(bytes(data)) >> 1


def bits_of(value, width):
    return [(value >> (width - 1 - k)) & 1 for k in range(width)]


def short_response(index, argument, *, bad_crc=False, bad_end=False, transmission=0):
    head = bytes([(transmission << 6) | index]) + argument.to_bytes(4, "big")
    last = (crc7(head) ^ (1 if bad_crc else 0)) << 1 | (0 if bad_end else 1)
    return bits_of(int.from_bytes(head + bytes([last]), "big"), 48)


def long_response(register):
    """R2: start, transmission 0, 111111, then CID/CSD bits 127..1 (CRC7 inside) and end."""
    content = register.to_bytes(16, "big")[:15]
    last = crc7(content) << 1 | 1
    return [0, 0] + [1] * 6 + bits_of(int.from_bytes(content + bytes([last]), "big"), 128)


class Harness(wiring.Component):
    def __init__(self):
        self.clock = SdClock()
        self.engine = CmdEngine()
        super().__init__({
            "divisor": In(10), "run": In(1), "clk": Out(1),
            "cmd_o": Out(1), "cmd_oe": Out(1), "cmd_i": In(1, init=1),
        })

    def elaborate(self, platform):
        m = Module()
        m.submodules.clock, m.submodules.engine = self.clock, self.engine
        m.d.comb += [
            self.clock.divisor.eq(self.divisor),
            self.clock.run.eq(self.run),
            self.clk.eq(self.clock.clk),
            self.engine.rise.eq(self.clock.rise),
            self.engine.fall.eq(self.clock.fall),
            self.cmd_o.eq(self.engine.cmd_o),
            self.cmd_oe.eq(self.engine.cmd_oe),
            self.engine.cmd_i.eq(self.cmd_i),
        ]
        return m


def transact(index, argument, kind, response_bits, *, divisor=1, n_cr=2, timeout=64):
    """Send a command; the responder answers ``response_bits`` n_cr clocks after its end."""
    dut = Harness()
    engine = dut.engine
    seen, result = [], {}

    async def host(ctx):
        ctx.set(dut.divisor, divisor)
        ctx.set(dut.run, 1)
        ctx.set(engine.timeout, timeout)
        await ctx.tick().repeat(4)
        ctx.set(engine.index, index)
        ctx.set(engine.argument, argument)
        ctx.set(engine.kind, kind)
        ctx.set(engine.start, 1)
        await ctx.tick()
        ctx.set(engine.start, 0)
        await ctx.tick().until(engine.done)
        result["status"] = ctx.get(engine.status)
        result["response"] = ctx.get(engine.response)
        await ctx.tick().until(~engine.busy)

    async def card(ctx):
        # Samples at each rising SD clock edge; drives the next bit right after it.
        reply = None
        while True:
            await ctx.posedge(dut.clk)
            if reply is None:
                seen.append(ctx.get(dut.cmd_o) if ctx.get(dut.cmd_oe) else 1)
                while seen and seen[0] == 1:
                    seen.pop(0)                  # idle line before the start bit
                if len(seen) == arch.CMD_BITS and response_bits is not None:
                    reply = [1] * (n_cr - 1) + list(response_bits)
            elif reply:
                ctx.set(dut.cmd_i, reply.pop(0))
            else:
                ctx.set(dut.cmd_i, 1)

    run_simulation(dut, [host], background=[card], name="sd_cmd", deadline=1e-3)
    return seen[:arch.CMD_BITS], result


@pytest.mark.parametrize("index,last_byte", [(0, arch.CMD0_LAST_BYTE),
                                             (17, arch.CMD17_LAST_BYTE)])
def test_command_bits_on_the_wire(index, last_byte):
    bits, result = transact(index, 0, ResponseKind.NONE, None)
    assert bits == bits_of(int.from_bytes(bytes([0x40 | index, 0, 0, 0, 0, last_byte]),
                                          "big"), 48)
    assert result["status"].timeout == 0


@pytest.mark.parametrize("divisor", [0, 1, 3])
def test_short_response_is_checked_and_returned(divisor):
    bits, result = transact(8, 0x1AA, ResponseKind.SHORT, short_response(8, 0x1AA),
                            divisor=divisor)
    head = bytes([0x48]) + (0x1AA).to_bytes(4, "big")
    assert bits == bits_of(int.from_bytes(head + bytes([crc7(head) << 1 | 1]), "big"), 48)
    status = result["status"]
    assert (status.timeout, status.crc_error, status.format_error, status.end_error) == (0,) * 4
    assert (result["response"] >> 8) & 0xFFFFFFFF == 0x1AA


@pytest.mark.parametrize("case,field", [
    (dict(bad_crc=True), "crc_error"),
    (dict(bad_end=True), "end_error"),
    (dict(transmission=1), "format_error"),
])
def test_short_response_faults(case, field):
    _, result = transact(13, 0x12340000, ResponseKind.SHORT,
                         short_response(13, 0x900, **case))
    assert getattr(result["status"], field) == 1


def test_wrong_index_is_a_format_error():
    _, result = transact(13, 0, ResponseKind.SHORT, short_response(12, 0x900))
    assert result["status"].format_error == 1


def test_ocr_response_skips_index_and_crc():
    ocr = 0xC0FF8000
    bits = [0, 0] + [1] * 6 + bits_of(ocr, 32) + [1] * 8
    _, result = transact(41, 0x40FF8000, ResponseKind.OCR, bits)
    status = result["status"]
    assert (status.crc_error, status.format_error, status.end_error) == (0, 0, 0)
    assert (result["response"] >> 8) & 0xFFFFFFFF == ocr


def test_long_response_crc_over_the_register():
    cid = int.from_bytes(bytes(range(0x10, 0x20)), "big")
    _, result = transact(2, 0, ResponseKind.LONG, long_response(cid))
    assert result["status"].crc_error == 0
    assert result["response"] >> 8 == cid >> 8
    corrupted = long_response(cid)
    corrupted[50] ^= 1
    _, result = transact(2, 0, ResponseKind.LONG, corrupted)
    assert result["status"].crc_error == 1


def test_timeout_when_no_card_answers():
    _, result = transact(8, 0x1AA, ResponseKind.SHORT, None, timeout=20)
    assert result["status"].timeout == 1


def test_late_response_within_timeout():
    _, result = transact(8, 0x1AA, ResponseKind.SHORT, short_response(8, 0x1AA), n_cr=60)
    assert result["status"].timeout == 0 and result["status"].crc_error == 0
