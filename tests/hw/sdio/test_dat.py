"""DatWriter and DatReader with SdClock against a minimal card side written in the test.

The card side decodes and encodes the 4-bit block format from the spec, with CRC16s from the
`crc` package; the full card model is exercised by the host tests.
"""

import random

import crc
import pytest
from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.wiring import In, Out

from maglog.hw.arch import sd as arch
from maglog.hw.sdio.clock import TICK_CLOCKS, SdClock
from maglog.hw.sdio.crc import Crc16Lanes
from maglog.hw.sdio.dat import DatReader, DatWriter
from maglog.sim.backends.amaranth import collect_payloads, feed_stream, run_simulation

CRC16 = crc.Calculator(crc.Crc16.XMODEM)


def lane_crcs(block):
    nibbles = [n for byte in block for n in (byte >> 4, byte & 0xF)]
    crcs = []
    for lane in range(4):
        bits = "".join(str((n >> lane) & 1) for n in nibbles)
        crcs.append(CRC16.checksum(int(bits, 2).to_bytes(len(bits) // 8, "big")))
    return crcs


class Harness(wiring.Component):
    """SdClock driving one engine, with its own CRC16 lanes; the DAT bus is left to the
    test."""
    def __init__(self, engine):
        self.clock = SdClock()
        self.engine = engine
        super().__init__({"divisor": In(10), "clk": Out(1), "rises": Out(32)})

    def elaborate(self, platform):
        m = Module()
        m.submodules.clock, m.submodules.engine = self.clock, self.engine
        m.submodules.crc16 = crc16 = Crc16Lanes(4)
        wiring.connect(m, self.engine.crc, crc16)
        m.d.comb += [
            self.clock.divisor.eq(self.divisor),
            self.clock.run.eq(self.engine.run),
            self.clk.eq(self.clock.clk),
            self.engine.rise.eq(self.clock.rise),
            self.engine.fall.eq(self.clock.fall),
            self.engine.tick.eq(self.clock.tick),
        ]
        with m.If(self.clock.rise):
            m.d.sync += self.rises.eq(self.rises + 1)
        return m


class CardSide:
    """Receives blocks on rising edges and answers with a token and busy."""
    def __init__(self, tokens=None, busy=8, token_delay=2, no_token_for=()):
        self.blocks, self.crc_ok, self.errors = [], [], []
        self.tokens = tokens or {}            # block index -> 3-bit token to send
        self.busy = busy
        self.token_delay = token_delay
        self.no_token_for = set(no_token_for)

    async def run(self, ctx, dut):
        engine = dut.engine
        reply = []
        nibbles = None
        while True:
            await ctx.posedge(dut.clk)
            host_oe = ctx.get(engine.dat_oe)
            if reply:
                if host_oe:
                    self.errors.append("host drives DAT while the card answers")
                ctx.set(engine.dat_i, 0b1110 | reply.pop(0))
                continue
            ctx.set(engine.dat_i, 0b1111)
            level = ctx.get(engine.dat_o) if host_oe else 0b1111
            if nibbles is None:
                if host_oe and level == 0:
                    nibbles = []
                continue
            nibbles.append(level)
            if len(nibbles) == arch.DATA_NIBBLES + arch.CRC16_BITS + 1:
                data, crcs, end = (nibbles[:arch.DATA_NIBBLES],
                                   nibbles[arch.DATA_NIBBLES:-1], nibbles[-1])
                block = bytes(data[i] << 4 | data[i + 1] for i in range(0, len(data), 2))
                got = [int("".join(str((c >> lane) & 1) for c in crcs), 2) for lane in range(4)]
                index = len(self.blocks)
                self.blocks.append(block)
                good = got == lane_crcs(block) and end == 0b1111
                self.crc_ok.append(good)
                token = self.tokens.get(index, arch.TOKEN_ACCEPTED if good else
                                        arch.TOKEN_CRC_ERROR)
                if index not in self.no_token_for:
                    reply = ([1] * self.token_delay + [0] +
                             [(token >> k) & 1 for k in (2, 1, 0)] + [1] +
                             [0] * self.busy + [1])
                nibbles = None


def write_blocks(blocks, *, card=None, divisor=0, hold=None, busy_timeout=100,
                 count=None):
    engine = DatWriter()
    dut = Harness(engine)
    card = card or CardSide()
    result = {}

    async def host(ctx):
        ctx.set(dut.divisor, divisor)
        ctx.set(engine.busy_timeout, busy_timeout)
        ctx.set(engine.blocks, count if count is not None else len(blocks))
        ctx.set(engine.start, 1)
        await ctx.tick()
        ctx.set(engine.start, 0)
        await ctx.tick().until(engine.done)
        result.update(status=ctx.get(engine.status), accepted=ctx.get(engine.accepted),
                      rises=ctx.get(dut.rises), flags=ctx.get(engine.status.as_value()))

    async def source(ctx):
        await feed_stream(ctx, engine.i, [b for block in blocks for b in block], hold=hold)

    async def card_side(ctx):
        await card.run(ctx, dut)

    run_simulation(dut, [host], background=[source, card_side], name="dat_write",
                   deadline=5e-3)
    return card, result


def random_blocks(seed, n):
    rng = random.Random(seed)
    return [rng.randbytes(arch.BLOCK_BYTES) for _ in range(n)]


@pytest.mark.parametrize("divisor", [0, 2])
def test_blocks_arrive_whole_with_good_crcs(divisor):
    blocks = random_blocks(divisor, 3)
    card, result = write_blocks(blocks, divisor=divisor)
    assert card.blocks == blocks
    assert all(card.crc_ok)
    assert card.errors == []
    assert result["accepted"] == 3
    assert result["flags"] == 0


def test_late_data_pauses_the_clock_instead_of_underrunning():
    blocks = random_blocks(7, 2)
    rng = random.Random(3)
    card, result = write_blocks(blocks, hold=lambda i: rng.choice([0, 0, 0, 5, 17]))
    assert card.blocks == blocks and all(card.crc_ok)
    assert result["accepted"] == 2


def test_data_phase_uses_the_bus_without_pauses_when_data_keeps_up():
    blocks = random_blocks(9, 4)
    card, result = write_blocks(blocks, card=CardSide(busy=0))
    # Per block: N_WR + start + 1024 nibbles + 16 CRC + end + release + token wait and
    # token (2 + 5) + busy check; data clocks are 1024 of them.
    per_block = result["rises"] / len(blocks)
    assert per_block <= arch.DATA_NIBBLES + 40
    assert arch.DATA_NIBBLES / per_block >= 0.95


def test_no_byte_is_taken_beyond_the_run():
    """A source that keeps offering bytes loses none: after the last block's data the
    writer takes nothing more (the next run starts from its own first byte)."""
    engine = DatWriter()
    dut = Harness(engine)
    blocks = random_blocks(15, 2)
    stream = [b for block in blocks for b in block] + list(range(40))
    taken = []

    async def host(ctx):
        ctx.set(engine.busy_timeout, 100)
        ctx.set(engine.blocks, 2)
        ctx.set(engine.start, 1)
        await ctx.tick()
        ctx.set(engine.start, 0)
        await ctx.tick().until(engine.done)
        await ctx.tick().repeat(50)

    async def source(ctx):
        for byte in stream:
            ctx.set(engine.i.payload, byte)
            ctx.set(engine.i.valid, 1)
            while True:
                _, _, ready = await ctx.tick().sample(engine.i.ready)
                if ready:
                    taken.append(byte)
                    break

    card = CardSide()

    async def card_side(ctx):
        await card.run(ctx, dut)

    run_simulation(dut, [host], background=[source, card_side], name="dat_tail",
                   deadline=5e-3)
    assert card.blocks == blocks
    assert len(taken) == 2 * arch.BLOCK_BYTES


def test_crc_rejected_block_stops_the_run():
    blocks = random_blocks(11, 3)
    card, result = write_blocks(blocks, card=CardSide(tokens={1: arch.TOKEN_CRC_ERROR}))
    assert result["status"].crc_rejected == 1
    assert result["accepted"] == 1
    assert len(card.blocks) == 2


def test_write_error_token():
    card, result = write_blocks(random_blocks(12, 1),
                                card=CardSide(tokens={0: arch.TOKEN_WRITE_ERROR}))
    assert result["status"].write_error == 1 and result["accepted"] == 0


def test_missing_token_is_an_error():
    card, result = write_blocks(random_blocks(13, 2), card=CardSide(no_token_for={0}))
    assert result["status"].no_token == 1 and result["accepted"] == 0


# The busy timeout is counted in ticks of TICK_CLOCKS SD clocks from the token's end bit:
# N ticks end N to N + 1 ticks later. The card's busy starts 1 clock after the token.
@pytest.mark.parametrize("ticks, busy, timed_out", [
    (2, 2 * TICK_CLOCKS - 4, False),        # ends just before the timeout can run out
    (2, 3 * TICK_CLOCKS + 4, True),         # outlasts the longest the timeout can last
    (0, TICK_CLOCKS + 4, True),
])
def test_busy_timeout(ticks, busy, timed_out):
    card, result = write_blocks(random_blocks(14, 2), card=CardSide(busy=busy),
                                busy_timeout=ticks)
    assert result["status"].busy_timeout == timed_out
    assert result["accepted"] == (0 if timed_out else 2)
    assert result["flags"] == (1 << 4 if timed_out else 0)     # WriteStatus.busy_timeout
    assert len(card.blocks) == (1 if timed_out else 2)


def r1b_wait(*, busy, ticks, start=1, status_before=0):
    """DatWriter's R1b busy wait alone: DAT0 goes low ``start`` clocks after ``wait_busy``
    for ``busy`` clocks (``busy=None``: never)."""
    engine = DatWriter()
    dut = Harness(engine)
    result = {}

    async def host(ctx):
        ctx.set(dut.divisor, 0)
        ctx.set(engine.busy_timeout, ticks)
        ctx.set(engine.wait_busy, 1)
        await ctx.tick()
        ctx.set(engine.wait_busy, 0)
        result["busy"] = ctx.get(engine.busy)
        first = ctx.get(dut.rises)
        await ctx.tick().until(engine.done)
        result.update(rises=ctx.get(dut.rises) - first, r1b_timeout=ctx.get(engine.r1b_timeout),
                      flags=ctx.get(engine.status.as_value()), accepted=ctx.get(engine.accepted),
                      ready=ctx.get(engine.i.ready))
        await ctx.tick().repeat(10)
        result["busy_after"] = ctx.get(engine.busy)

    async def card(ctx):
        levels = [1] * start + ([0] * busy if busy is not None else [0] * 100_000)
        while True:
            await ctx.posedge(dut.clk)
            ctx.set(engine.dat_i, 0b1110 | (levels.pop(0) if levels else 1))

    async def source(ctx):
        ctx.set(engine.i.valid, 1)          # a byte on offer must not be taken

    run_simulation(dut, [host], background=[card, source], name="dat_r1b", deadline=5e-3)
    return result


@pytest.mark.parametrize("busy, ticks, timed_out", [
    (2 * TICK_CLOCKS - 4, 2, False),
    (None, 2, True),
    (0, 0, False),                          # no busy at all: done after the start window
])
def test_r1b_busy_wait(busy, ticks, timed_out):
    result = r1b_wait(busy=busy, ticks=ticks)
    assert result["busy"] and not result["busy_after"]
    assert result["r1b_timeout"] == timed_out
    assert result["flags"] == 0 and result["accepted"] == 0 and not result["ready"]
    if timed_out:
        assert ticks * TICK_CLOCKS <= result["rises"] <= (ticks + 1) * TICK_CLOCKS + 2
    elif busy:
        assert busy <= result["rises"] <= busy + 4
    else:
        assert result["rises"] <= arch.BUSY_START_CLOCKS + 2


# --- reader ---------------------------------------------------------------------------------

def read_block(block, *, corrupt=None, bad_end=False, delay=5, ready=None, timeout=4,
               send=True):
    engine = DatReader()
    dut = Harness(engine)
    got, result = [], {}
    nibbles = [n for byte in block for n in (byte >> 4, byte & 0xF)]
    crcs = lane_crcs(block)
    crc_nibbles = [sum(((crcs[lane] >> (15 - k)) & 1) << lane for lane in range(4))
                   for k in range(16)]
    frame = [0b1111] * delay + [0] + nibbles + crc_nibbles + [0b0111 if bad_end else 0b1111]
    if corrupt is not None:
        frame[delay + 1 + corrupt[0]] ^= 1 << corrupt[1]

    async def host(ctx):
        ctx.set(dut.divisor, 0)
        ctx.set(engine.timeout, timeout)
        ctx.set(engine.start, 1)
        await ctx.tick()
        ctx.set(engine.start, 0)
        await ctx.tick().until(engine.done)
        result["status"] = ctx.get(engine.status)
        result["flags"] = ctx.get(engine.status.as_value())

    async def card(ctx):
        pending = list(frame) if send else []
        while True:
            await ctx.posedge(dut.clk)
            ctx.set(engine.dat_i, pending.pop(0) if pending else 0b1111)

    async def sink(ctx):
        await collect_payloads(ctx, engine.o, got, ready=ready)

    run_simulation(dut, [host], background=[card, sink], name="dat_read", deadline=5e-3)
    return bytes(got), result["status"], result["flags"]


def test_read_block_with_good_crc():
    block = random_blocks(21, 1)[0]
    data, status, flags = read_block(block)
    assert data == block
    assert flags == 0


def test_read_block_pauses_for_a_slow_consumer():
    block = random_blocks(22, 1)[0]
    rng = random.Random(1)
    pattern = [rng.random() < 0.2 for _ in range(4096)]
    data, status, flags = read_block(block, ready=lambda cycle: pattern[cycle % 4096])
    assert data == block and flags == 0


@pytest.mark.parametrize("where", [(0, 0), (700, 3), (1024 + 5, 2)])
def test_read_block_crc_error(where):
    _, status, _ = read_block(random_blocks(23, 1)[0], corrupt=where)
    assert status.crc_error == 1


def test_read_block_end_bit_and_timeout():
    _, status, _ = read_block(random_blocks(24, 1)[0], bad_end=True)
    assert status.end_error == 1
    _, status, _ = read_block(random_blocks(25, 1)[0], send=False, timeout=2)
    assert status.timeout == 1


# The read timeout: N ticks of TICK_CLOCKS SD clocks end N to N + 1 ticks after `start`.
@pytest.mark.parametrize("delay, timed_out", [
    (2 * TICK_CLOCKS - 4, False),           # the start bit just before it can run out
    (3 * TICK_CLOCKS + 4, True),            # after the longest it can last
])
def test_read_timeout_in_ticks(delay, timed_out):
    block = random_blocks(26, 1)[0]
    data, status, _ = read_block(block, delay=delay, timeout=2)
    assert status.timeout == timed_out
    assert data == (b"" if timed_out else block)
