"""SD bus CRCs against the Physical Layer spec's golden values and the `crc` package."""

import random

import crc
import pytest

from maglog.hw.arch import sd as arch
from maglog.hw.sdio.crc import Crc7, Crc16, Crc16Lanes, SerialCrc
from maglog.sim.backends.amaranth import run_simulation

# CRC7 (x^7 + x^3 + 1) is CRC8 with the generator shifted up one place, result shifted down:
# the `crc` package only handles whole-byte widths.
CRC8_FOR_CRC7 = crc.Calculator(crc.Configuration(
    width=8, polynomial=arch.CRC7_POLY << 1, init_value=0, final_xor_value=0,
    reverse_input=False, reverse_output=False))
CRC16 = crc.Calculator(crc.Crc16.XMODEM)      # x^16 + x^12 + x^5 + 1, init 0, MSB first


def bits_of(data):
    return [(byte >> (7 - k)) & 1 for byte in data for k in range(8)]


def run_serial(dut, bits):
    """Clock ``bits`` into a SerialCrc and return its register afterwards."""
    result = []

    async def tb(ctx):
        ctx.set(dut.clear, 1)
        await ctx.tick()
        ctx.set(dut.clear, 0)
        ctx.set(dut.en, 1)
        for bit in bits:
            ctx.set(dut.bit, bit)
            await ctx.tick()
        ctx.set(dut.en, 0)
        result.append(ctx.get(dut.crc))

    run_simulation(dut, [tb], name="crc")
    return result[0]


@pytest.mark.parametrize("command,last_byte", [
    (bytes([0x40, 0, 0, 0, 0]), arch.CMD0_LAST_BYTE),      # CMD0, argument 0
    (bytes([0x51, 0, 0, 0, 0]), arch.CMD17_LAST_BYTE),     # CMD17, argument 0
    (bytes([0x11, 0, 0, 0x09, 0]), 0x67),                  # R1 of CMD17 (spec example)
])
def test_crc7_golden(command, last_byte):
    value = run_serial(Crc7(), bits_of(command))
    assert (value << 1) | 1 == last_byte
    assert value == CRC8_FOR_CRC7.checksum(command) >> 1


def test_crc16_golden_512_bytes_of_ff():
    assert run_serial(Crc16(), bits_of(b"\xff" * 512)) == arch.CRC16_512_FF
    assert CRC16.checksum(b"\xff" * 512) == arch.CRC16_512_FF


@pytest.mark.parametrize("seed", range(3))
def test_crc7_random_commands(seed):
    rng = random.Random(seed)
    for _ in range(8):
        command = bytes([0x40 | rng.randrange(64)]) + rng.randbytes(4)
        assert run_serial(Crc7(), bits_of(command)) == CRC8_FOR_CRC7.checksum(command) >> 1


def test_crc16_lanes_of_a_4bit_block():
    """512 bytes on four lines, high nibble first: each line's CRC16 over its own bits."""
    rng = random.Random(11)
    block = rng.randbytes(512)
    nibbles = [n for byte in block for n in (byte >> 4, byte & 0xF)]
    dut = Crc16Lanes(4)
    result = []

    async def tb(ctx):
        ctx.set(dut.en, 1)
        for nibble in nibbles:
            ctx.set(dut.bits, nibble)
            await ctx.tick()
        ctx.set(dut.en, 0)
        result.extend(ctx.get(dut.crc[lane]) for lane in range(4))

    run_simulation(dut, [tb], name="crc16_lanes")
    for lane in range(4):
        # The line's bit stream packed into bytes (1024 bits = 128 bytes).
        bits = [(n >> lane) & 1 for n in nibbles]
        packed = bytes(int("".join(map(str, bits[i:i + 8])), 2) for i in range(0, len(bits), 8))
        assert result[lane] == CRC16.checksum(packed), f"DAT{lane}"


def test_parameters_are_checked():
    with pytest.raises(ValueError, match="CRC width must be a positive integer, not 0"):
        SerialCrc(0, 1)
    with pytest.raises(ValueError, match=r"Generator must be a nonzero integer below 2\*\*7, "
                                         r"not 128"):
        SerialCrc(7, 128)
    with pytest.raises(ValueError, match="An SD bus has 1 or 4 data lines, not 2"):
        Crc16Lanes(2)
