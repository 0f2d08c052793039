"""SdCard driven bit by bit by a plain-Python host written here, from the spec.

The host builds its commands and checks the card's responses and data with the `crc` package
(CRC7 is CRC8 with the generator shifted up one place, result shifted down; CRC16 is XMODEM),
so nothing is shared with the model's own CRC code.
"""

from __future__ import annotations

import random

import crc
import pytest

from maglog.hw.arch import sd as arch
from maglog.hw.arch.sd import CardState, CardStatus, Response
from maglog.sim.models import BlockEvent, CardImage, Faults, SdCard, Transaction
from maglog.sim.models.sdcard import crc7, crc16

CRC8_FOR_CRC7 = crc.Calculator(crc.Configuration(
    width=8, polynomial=arch.CRC7_POLY << 1, init_value=0, final_xor_value=0,
    reverse_input=False, reverse_output=False))
CRC16 = crc.Calculator(crc.Crc16.XMODEM)

CAPACITY = 4096          # blocks: 2 MiB, enough for the tests and cheap to hold
HOST_N_CR_TIMEOUT = arch.N_CR_MAX + 2


def crc7_of(data: bytes) -> int:
    return CRC8_FOR_CRC7.checksum(data) >> 1


def to_bits(data: bytes) -> list[int]:
    return [(byte >> (7 - k)) & 1 for byte in data for k in range(8)]


def to_bytes(bits) -> bytes:
    bits = list(bits)
    return int("".join(map(str, bits)), 2).to_bytes(len(bits) // 8, "big")


def line_crc(nibbles, line) -> int:
    return CRC16.checksum(to_bytes((n >> line) & 1 for n in nibbles))


def command_bits(index: int, argument: int, *, bad_crc=False) -> list[int]:
    head = bytes([0x40 | index]) + argument.to_bytes(4, "big")
    crc_value = crc7_of(head) ^ (1 if bad_crc else 0)
    return to_bits(head + bytes([(crc_value << 1) | 1]))


class Reply:
    """A response as the host received it."""
    def __init__(self, bits, n_cr):
        self.bits, self.n_cr = bits, n_cr

    @property
    def index(self):
        return to_bytes([0, 0] + self.bits[2:8])[0]

    @property
    def payload(self):
        return int.from_bytes(to_bytes(self.bits[8:40]), "big")

    @property
    def crc_ok(self):
        if len(self.bits) == arch.R2_BITS:
            register = to_bytes(self.bits[8:])
            return crc7_of(register[:15]) == register[15] >> 1 and self.bits[-1] == 1
        return (crc7_of(to_bytes(self.bits[:40])) == int("".join(map(str, self.bits[40:47])), 2)
                and self.bits[-1] == 1)

    @property
    def register(self):
        return int.from_bytes(to_bytes(self.bits[8:]), "big")

    @property
    def state(self):
        return CardState((self.payload >> arch.STATUS_STATE_SHIFT) & 0xF)

    def has(self, flag):
        return bool(self.payload & flag)


class Host:
    """Clocks the card directly: each `clock` is one SD clock period then its rising edge."""

    def __init__(self, card: SdCard):
        self.card = card
        self.card_out = (0, 1, 0, 0xF)
        self.clocks = 0

    def clock(self, cmd=None, dat=None, dat_oe=0xF):
        """Drive ``cmd`` (None: released) and ``dat`` on ``dat_oe`` for one period; return the
        (cmd, dat) levels sampled at the rising edge that ends it."""
        card_cmd_oe, card_cmd, card_dat_oe, card_dat = self.card_out
        bus_cmd = 1
        if cmd is not None:
            bus_cmd &= cmd
        if card_cmd_oe:
            bus_cmd &= card_cmd
            if cmd is not None:
                self.card.report("contention on CMD")
        host_oe = dat_oe if dat is not None else 0
        bus_dat = 0xF & ((dat if dat is not None else 0xF) | ~host_oe)
        bus_dat &= card_dat | ~card_dat_oe & 0xF
        if host_oe & card_dat_oe:
            self.card.report(f"contention on DAT {host_oe & card_dat_oe:04b}")
        self.card_out = self.card.edge(bus_cmd, bus_dat)
        self.clocks += 1
        return bus_cmd, bus_dat

    def idle(self, clocks):
        for _ in range(clocks):
            self.clock()

    def send(self, index, argument, *, bad_crc=False):
        for bit in command_bits(index, argument, bad_crc=bad_crc):
            self.clock(cmd=bit)

    def receive(self, length=arch.CMD_BITS, timeout=HOST_N_CR_TIMEOUT):
        waited = 0
        while self.clock()[0] == 1:
            waited += 1
            if waited > timeout:
                return None
        return Reply([0] + [self.clock()[0] for _ in range(length - 1)], waited)

    def cmd(self, index, argument=0, *, length=arch.CMD_BITS, then=arch.N_RC, check=True,
            bad_crc=False):
        """Send a command and receive its response; idle ``then`` clocks afterwards."""
        self.send(index, argument, bad_crc=bad_crc)
        reply = self.receive(length)
        if reply is not None and check and index != 41:        # R3 carries no CRC7
            assert reply.crc_ok, f"CMD{index}: bad response CRC7"
            if length == arch.CMD_BITS:
                assert reply.index == index
        self.idle(then)
        return reply

    def acmd(self, index, argument=0, **kwargs):
        app = self.cmd(55, self.card.rca << 16)
        assert app is not None and app.has(CardStatus.APP_CMD)
        reply = self.cmd(index, argument, **kwargs)
        if reply is not None and index != 41:
            assert reply.has(CardStatus.APP_CMD)
        return reply

    # -- data ----------------------------------------------------------------------------------

    def write_block(self, data, *, n_wr=arch.N_WR, token_timeout=arch.TOKEN_TIMEOUT_CLOCKS,
                    busy_timeout=100_000, corrupt_crc=False, grace=2):
        """Send one 4-bit block ``n_wr`` clocks after now; return (token, busy clocks), token
        None when none came, busy None past the timeout."""
        nibbles = [n for byte in data for n in (byte >> 4, byte & 0xF)]
        crcs = [line_crc(nibbles, line) for line in range(4)]
        if corrupt_crc:
            crcs[3] ^= 1
        crc_nibbles = [sum(((crcs[line] >> (15 - i)) & 1) << line for line in range(4))
                       for i in range(16)]
        for _ in range(n_wr):
            self.clock(dat=0xF)
        for value in [0] + nibbles + crc_nibbles + [0xF]:
            self.clock(dat=value)
        return self.token_and_busy(token_timeout, busy_timeout, grace)

    def token_and_busy(self, token_timeout, busy_timeout, grace=2):
        waited = 0
        while self.clock()[1] & 1:
            waited += 1
            if waited > token_timeout:
                return None, None
        assert waited == arch.N_CRC
        bits = [self.clock()[1] & 1 for _ in range(4)]
        assert bits[3] == 1, "token end bit"
        token = bits[0] << 2 | bits[1] << 1 | bits[2]
        return token, self.wait_busy(busy_timeout, grace=grace)

    def wait_busy(self, timeout=100_000, grace=2):
        """Clocks of DAT0 low (busy), which must start within ``grace`` clocks (0: it did
        not); ``busy_start`` is then the number of clocks DAT0 stayed high before it."""
        for self.busy_start in range(grace):
            if not self.clock()[1] & 1:
                break
        else:
            return 0
        busy = 1
        while not self.clock()[1] & 1:
            busy += 1
            if busy >= timeout:
                return None
        return busy

    def read_data(self, nbytes=arch.BLOCK_BYTES, timeout=1000, width=4):
        """Receive one data packet; return (bytes, CRCs good, clocks waited for its start)."""
        waited = 0
        mask = 0xF if width == 4 else 0x1
        while self.clock()[1] & mask:
            waited += 1
            if waited > timeout:
                return None, None, None
        if width == 4:
            samples = [self.clock()[1] for _ in range(2 * nbytes + 16 + 1)]
            nibbles, crc_nibbles, end = samples[:2 * nbytes], samples[2 * nbytes:-1], samples[-1]
            data = bytes(nibbles[2 * i] << 4 | nibbles[2 * i + 1] for i in range(nbytes))
            ok = end == 0xF and all(
                line_crc(nibbles, line) == int("".join(str((n >> line) & 1)
                                                       for n in crc_nibbles), 2)
                for line in range(4))
            return data, ok, waited
        samples = [self.clock()[1] & 1 for _ in range(8 * nbytes + 16 + 1)]
        data = to_bytes(samples[:8 * nbytes])
        ok = samples[-1] == 1 and CRC16.checksum(data) == int(
            "".join(map(str, samples[8 * nbytes:-1])), 2)
        return data, ok, waited


def initialise(host: Host, *, four_bit=True):
    """The firmware's init sequence; returns the replies by name. HCS goes with ACMD41 only
    when CMD8 was answered (PLSS §4.2.3.1)."""
    replies = {}
    host.idle(arch.INIT_CLOCKS)
    host.send(0, 0)
    host.idle(arch.N_CC)
    replies["CMD8"] = host.cmd(8, arch.IF_COND_ARGUMENT)
    hcs = arch.ACMD41_HCS if replies["CMD8"] is not None else 0
    polls = []
    while True:
        polls.append(host.acmd(41, hcs | arch.OCR_VOLTAGE_WINDOW))
        if polls[-1].payload & arch.OCR_POWER_UP_DONE:
            break
        assert len(polls) < 20
    replies["ACMD41"] = polls
    replies["CMD2"] = host.cmd(2, length=arch.R2_BITS)
    replies["CMD3"] = host.cmd(3)
    rca = replies["CMD3"].payload >> 16
    replies["CMD7"] = host.cmd(7, rca << 16)
    host.wait_busy()
    if four_bit:
        replies["ACMD6"] = host.acmd(6, arch.BUS_WIDTH_4)
    return replies


def make_card(seed=1, **kwargs):
    image = CardImage(CAPACITY)
    card = SdCard(image, seed=seed, **kwargs)
    return card, Host(card), image


def random_block(seed):
    return random.Random(seed).randbytes(arch.BLOCK_BYTES)


def ready_card(**kwargs):
    card, host, image = make_card(**kwargs)
    initialise(host)
    assert card.state is CardState.TRAN and card.bus_width == 4
    return card, host, image


# -- CRCs --------------------------------------------------------------------------------------

def test_crcs_match_golden_values_and_the_crc_package():
    assert (crc7(command_bits(0, 0)[:40]) << 1) | 1 == arch.CMD0_LAST_BYTE
    assert (crc7(command_bits(17, 0)[:40]) << 1) | 1 == arch.CMD17_LAST_BYTE
    assert crc16([1] * 4096) == arch.CRC16_512_FF
    # The test host's own frames (built with the `crc` package) carry the same values.
    assert to_bytes(command_bits(0, 0))[-1] == arch.CMD0_LAST_BYTE
    assert to_bytes(command_bits(17, 0))[-1] == arch.CMD17_LAST_BYTE
    assert CRC16.checksum(bytes([0xFF]) * 512) == arch.CRC16_512_FF
    rng = random.Random(7)
    for _ in range(50):
        data = rng.randbytes(rng.randint(1, 40))
        assert crc7(to_bits(data)) == crc7_of(data)
        assert crc16(to_bits(data)) == CRC16.checksum(data)


# -- identification ----------------------------------------------------------------------------

def test_init_sequence():
    card, host, _ = make_card(seed=3)
    assert card.state is CardState.IDLE
    replies = initialise(host)

    r7 = replies["CMD8"]
    assert r7.index == 8 and r7.payload == arch.IF_COND_ARGUMENT and r7.n_cr == arch.N_CR_MIN

    polls = replies["ACMD41"]
    assert len(polls) >= 2, "the card reports busy at least once by default"
    for r3 in polls:
        assert r3.index == 0x3F and r3.bits[40:48] == [1] * 8     # CRC field all ones, end
        assert r3.n_cr == arch.N_ID
        assert r3.payload & arch.OCR_VOLTAGE_WINDOW == arch.OCR_VOLTAGE_WINDOW
    assert all(not p.payload & arch.OCR_POWER_UP_DONE for p in polls[:-1])
    assert polls[-1].payload & arch.OCR_CCS

    r2 = replies["CMD2"]
    assert len(r2.bits) == arch.R2_BITS and r2.crc_ok and r2.n_cr == arch.N_ID
    assert r2.index == 0x3F and r2.register == card.cid
    assert to_bytes(r2.bits[8 + 24:8 + 64]) == b"MAGLG"

    r6 = replies["CMD3"]
    rca = r6.payload >> 16
    assert rca == card.rca != 0
    assert (r6.payload >> arch.STATUS_STATE_SHIFT) & 0xF == CardState.IDENT

    r1 = replies["CMD7"]
    assert r1.state is CardState.STBY and r1.has(CardStatus.READY_FOR_DATA)
    assert replies["ACMD6"].state is CardState.TRAN

    status = host.cmd(13, rca << 16)
    assert status.state is CardState.TRAN and not status.has(CardStatus.APP_CMD)
    csd = host.cmd(9, rca << 16, length=arch.R2_BITS)
    assert csd is None, "CMD9 is only legal in stby"
    host.cmd(7, 0)                                           # deselect: no answer
    assert card.state is CardState.STBY
    csd = host.cmd(9, rca << 16, length=arch.R2_BITS)
    c_size = (csd.register >> 48) & ((1 << 22) - 1)
    assert csd.register >> 126 == 1 and (c_size + 1) * 1024 == CAPACITY

    assert len(card.errors) == 1 and "CMD9" in card.errors[0] and "state tran" in card.errors[0]
    commands = [t.command for t in card.log if isinstance(t, Transaction)]
    assert commands[:3] == ["CMD0", "CMD8", "CMD55"] and "ACMD41" in commands


def test_acmd41_without_hcs_never_ready():
    card, host, _ = make_card(acmd41_busy=(0, 0))
    host.idle(80)
    host.cmd(8, arch.IF_COND_ARGUMENT)
    for _ in range(5):
        r3 = host.acmd(41, arch.OCR_VOLTAGE_WINDOW)
        assert not r3.payload & arch.OCR_POWER_UP_DONE
    assert card.state is CardState.IDLE
    assert len(card.errors) == 1 and "HCS" in card.errors[0]


def test_configurable_n_cr_and_seeded_determinism():
    card, host, _ = make_card(seed=5, n_cr=(2, 64))
    host.idle(arch.INIT_CLOCKS)
    seen = {host.cmd(8, arch.IF_COND_ARGUMENT).n_cr for _ in range(20)}
    assert all(2 <= n <= 64 for n in seen) and len(seen) > 3
    runs = []
    for _ in range(2):
        card, host, _ = make_card(seed=11)
        initialise(host)
        host.cmd(24, 3, then=0)
        runs.append((card.rca, host.write_block(random_block(3)), card.log))
    assert runs[0] == runs[1]
    card, host, _ = make_card(seed=12)
    initialise(host)
    assert card.rca != runs[0][0]


@pytest.mark.parametrize("kwargs, message", [
    (dict(n_cr=1), "N_CR"), (dict(n_cr=(2, 65)), "N_CR"),
    (dict(busy_clocks=(0, 4)), "Busy"), (dict(busy_clocks=(9, 8)), "Busy"),
    (dict(rca=0), "RCA"), (dict(capacity_blocks=CAPACITY + 1), "Capacity"),
    (dict(n_ac=1), "N_AC"), (dict(acmd41_busy=(-1, 2)), "ACMD41"),
    (dict(version=1), "version 1 card is standard capacity"), (dict(version=3), "Version"),
    (dict(busy_start_delay=-1), "Busy start delay"),
    (dict(busy_start_delay=True), "Busy start delay"),
    (dict(cmd13=0), "CMD13"), (dict(illegal_kept="yes"), "Illegal kept"),
    (dict(ocr_ccs=1), "OCR CCS"),
])
def test_bad_parameters(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SdCard(CardImage(CAPACITY), **kwargs)


def test_bad_faults():
    with pytest.raises(ValueError, match="flip_line"):
        Faults(flip_dat_bit=0, flip_line=4)
    with pytest.raises(ValueError, match="withhold_token"):
        Faults(withhold_token=-1)


# -- data --------------------------------------------------------------------------------------

def test_cmd24_write_then_cmd17_readback():
    card, host, image = ready_card(busy_clocks=(20, 20))
    data = random_block(1)
    r1 = host.cmd(24, 1234, then=0)
    assert r1.state is CardState.TRAN and r1.has(CardStatus.READY_FOR_DATA)
    assert card.state is CardState.RCV
    token, busy = host.write_block(data)
    assert token == arch.TOKEN_ACCEPTED and busy == 20
    assert image.read_block(1234) == data and card.state is CardState.TRAN
    host.idle(arch.N_RC)

    r1 = host.cmd(17, 1234, then=0)
    assert r1.state is CardState.TRAN and card.state is CardState.DATA
    read, ok, waited = host.read_data()
    assert ok and read == image.read_block(1234) == data and waited == arch.N_AC_MIN
    host.idle(arch.N_RC)
    assert host.cmd(13, card.rca << 16).state is CardState.TRAN
    # An unwritten block reads as zeros.
    host.cmd(17, 99, then=0)
    assert host.read_data()[:2] == (bytes(arch.BLOCK_BYTES), True)
    assert card.errors == []
    assert [e.outcome for e in card.log if isinstance(e, BlockEvent)] == ["stored", "sent", "sent"]


def test_cmd25_multi_block_write_with_acmd23_and_cmd18_readback():
    card, host, image = ready_card(busy_clocks=(8, 64), seed=9)
    blocks = [random_block(10 + i) for i in range(4)]
    assert host.acmd(23, 4).state is CardState.TRAN
    assert card.pre_erase_count == 4
    host.cmd(25, 100, then=0)
    assert card.pre_erase_count is None
    busies = []
    for block in blocks:
        token, busy = host.write_block(block)
        assert token == arch.TOKEN_ACCEPTED
        busies.append(busy)
    assert all(8 <= b <= 64 for b in busies) and len(set(busies)) > 1
    stop = host.cmd(12, then=0)
    assert stop.state is CardState.RCV
    host.wait_busy()
    assert card.state is CardState.TRAN
    for i, block in enumerate(blocks):
        assert image.read_block(100 + i) == block
    assert any(isinstance(t, Transaction) and t.command == "CMD25" and "pre-erase count 4"
               in t.note for t in card.log)
    assert any(isinstance(t, Transaction) and t.command == "ACMD23" for t in card.log)
    host.idle(arch.N_RC)

    # ACMD22: well-written blocks of the last write.
    host.acmd(22, then=0)
    assert host.read_data(4)[:2] == ((4).to_bytes(4, "big"), True)
    host.idle(arch.N_RC)

    # Multi-block read, stopped by CMD12 while the card is sending.
    host.cmd(18, 100, then=0)
    for i in range(3):
        read, ok, _ = host.read_data()
        assert ok and read == blocks[i]
    stop = host.cmd(12, then=20)
    assert stop.state is CardState.DATA
    assert card.state is CardState.TRAN and card.busy is False
    assert host.clock()[1] == 0xF
    assert card.errors == []


def test_cmd17_in_one_bit_mode_and_scr():
    card, host, image = make_card()
    initialise(host, four_bit=False)
    data = random_block(4)
    image.write_block(7, data)
    host.cmd(17, 7, then=0)
    read, ok, _ = host.read_data(width=1)
    assert ok and read == data
    host.idle(arch.N_RC)
    host.acmd(6, arch.BUS_WIDTH_4)
    host.acmd(51, then=0)
    scr, ok, _ = host.read_data(8)
    assert ok and (scr[1] & 0x0F) == 0b0101            # SD_BUS_WIDTHS: 1 and 4 bits
    assert card.errors == []


def test_out_of_range_addresses():
    card, host, image = ready_card()
    r1 = host.cmd(17, CAPACITY, then=0)
    assert r1.has(CardStatus.OUT_OF_RANGE) and card.state is CardState.TRAN
    assert host.read_data(timeout=200)[0] is None
    r1 = host.cmd(24, CAPACITY + 5)
    assert r1.has(CardStatus.OUT_OF_RANGE) and card.state is CardState.TRAN
    assert not host.cmd(13, card.rca << 16).has(CardStatus.OUT_OF_RANGE)   # cleared on read
    # A CMD25 running off the end: the block past the end gets the write-error token.
    host.cmd(25, CAPACITY - 1, then=0)
    assert host.write_block(random_block(1))[0] == arch.TOKEN_ACCEPTED
    assert host.write_block(random_block(2))[0] == arch.TOKEN_WRITE_ERROR
    stop = host.cmd(12, then=0)
    assert stop.has(CardStatus.OUT_OF_RANGE)
    host.wait_busy()
    assert image.read_block(CAPACITY - 1) == random_block(1) and len(image) == 1


# -- faults ------------------------------------------------------------------------------------

def test_fault_flip_dat_bit_rejects_block():
    card, host, image = ready_card(faults=Faults(flip_dat_bit=1, flip_line=2))
    host.cmd(25, 40, then=0)
    assert host.write_block(random_block(1))[0] == arch.TOKEN_ACCEPTED
    assert host.write_block(random_block(2))[0] == arch.TOKEN_CRC_ERROR
    host.idle(arch.N_RC)
    assert host.cmd(12, then=0).state is CardState.RCV
    host.wait_busy()
    assert card.state is CardState.TRAN
    assert image.is_written(40) and not image.is_written(41)
    assert [e.outcome for e in card.log if isinstance(e, BlockEvent)] == ["stored", "crc error"]
    assert card.errors == []


def test_host_crc_error_gets_101_and_card_ignores_rest_of_cmd25():
    card, host, image = ready_card()
    host.cmd(25, 50, then=0)
    assert host.write_block(random_block(1), corrupt_crc=True)[0] == arch.TOKEN_CRC_ERROR
    assert host.write_block(random_block(2)) == (None, None)      # ignored until CMD12
    host.cmd(12, then=0)
    host.wait_busy()
    assert len(image) == 0 and card.state is CardState.TRAN
    assert len(card.errors) == 1 and "rejected block" in card.errors[0]
    # CMD24: after 101 the card is back in tran at once.
    host.idle(arch.N_RC)
    host.cmd(24, 51, then=0)
    assert host.write_block(random_block(3), corrupt_crc=True)[0] == arch.TOKEN_CRC_ERROR
    assert card.state is CardState.TRAN and len(image) == 0


def test_fault_corrupt_response_crc():
    # Response 0 is CMD8's R7: the host sees a bad CRC7 and asks again.
    card, host, _ = make_card(faults=Faults(corrupt_response_crc=0))
    host.idle(80)
    bad = host.cmd(8, arch.IF_COND_ARGUMENT, check=False)
    assert not bad.crc_ok and bad.payload == arch.IF_COND_ARGUMENT
    good = host.cmd(8, arch.IF_COND_ARGUMENT)
    assert good.crc_ok
    # Response 2 is CMD2's R2 here (R7, CMD55's R1; R3 carries no CRC7).
    card, host, _ = make_card(faults=Faults(corrupt_response_crc=2), acmd41_busy=(0, 0))
    host.idle(80)
    host.cmd(8, arch.IF_COND_ARGUMENT)
    assert host.acmd(41, arch.ACMD41_HCS | arch.OCR_VOLTAGE_WINDOW).payload >> 31
    r2 = host.cmd(2, length=arch.R2_BITS, check=False)
    assert not r2.crc_ok and r2.register ^ card.cid == 0b10
    assert card.errors == []


def test_fault_withhold_token():
    card, host, image = ready_card(faults=Faults(withhold_token=0))
    host.cmd(24, 60, then=0)
    assert host.write_block(random_block(1)) == (None, None)
    assert card.state is CardState.TRAN and not image.is_written(60)
    assert host.cmd(13, card.rca << 16).state is CardState.TRAN
    host.cmd(24, 60, then=0)                                     # the retry goes through
    assert host.write_block(random_block(1))[0] == arch.TOKEN_ACCEPTED
    assert image.read_block(60) == random_block(1)
    # In a CMD25 the card then ignores data until CMD12.
    card, host, image = ready_card(faults=Faults(withhold_token=1))
    host.cmd(25, 70, then=0)
    assert host.write_block(random_block(1))[0] == arch.TOKEN_ACCEPTED
    assert host.write_block(random_block(2)) == (None, None)
    host.idle(arch.N_RC)
    host.cmd(12, then=0)
    host.wait_busy()
    assert card.state is CardState.TRAN and len(image) == 1 and image.is_written(70)
    assert card.errors == []


def test_fault_busy_past_timeout():
    card, host, image = ready_card(faults=Faults(busy_past_timeout=0,
                                                 busy_past_timeout_clocks=3000))
    host.cmd(24, 80, then=0)
    token, busy = host.write_block(random_block(1), busy_timeout=1000)
    assert token == arch.TOKEN_ACCEPTED and busy is None             # the host gives up
    status = host.cmd(13, card.rca << 16)
    assert status.state is CardState.PRG and not status.has(CardStatus.READY_FOR_DATA)
    assert not image.is_written(80)
    # Every clock since the busy began saw DAT0 low: 1000, the CMD13 exchange, the rest.
    exchange = 2 * arch.CMD_BITS + arch.N_CR_MIN + arch.N_RC
    assert 1000 + exchange + host.wait_busy(grace=1) == 3000
    assert image.read_block(80) == random_block(1) and card.state is CardState.TRAN
    host.idle(arch.N_RC)
    host.cmd(24, 81, then=0)
    assert host.write_block(random_block(1), busy_timeout=1000)[1] <= 64   # only block 0
    assert card.errors == []


def test_fault_no_card():
    card, host, image = make_card(faults=Faults(no_card=True))
    host.idle(80)
    host.send(0, 0)
    assert host.cmd(8, arch.IF_COND_ARGUMENT) is None
    assert host.cmd(55) is None
    for _ in range(100):
        assert host.clock() == (1, 0xF)
    assert card.errors == [] and card.log == []


# -- protocol errors ---------------------------------------------------------------------------

def test_bad_command_crc_gets_no_response_and_com_crc_error_next():
    card, host, _ = ready_card()
    assert host.cmd(13, card.rca << 16, bad_crc=True) is None
    assert len(card.errors) == 1 and "CRC7" in card.errors[0]
    status = host.cmd(13, card.rca << 16)
    assert status.has(CardStatus.COM_CRC_ERROR) and status.state is CardState.TRAN
    assert not host.cmd(13, card.rca << 16).has(CardStatus.COM_CRC_ERROR)


def test_illegal_and_unknown_commands():
    card, host, _ = ready_card()
    assert host.cmd(2) is None                                  # CMD2 in tran
    assert host.cmd(13, card.rca << 16).has(CardStatus.ILLEGAL_COMMAND)
    assert host.cmd(5) is None                                  # not an SD memory command
    status = host.cmd(13, card.rca << 16)
    assert status.has(CardStatus.ILLEGAL_COMMAND) and not status.has(CardStatus.COM_CRC_ERROR)
    assert "illegal in state tran" in card.errors[0] and "unknown" in card.errors[1]
    assert host.cmd(13, (card.rca ^ 1) << 16) is None          # another card's RCA
    assert "RCA" in card.errors[2]


def test_data_before_n_wr():
    card, host, image = ready_card()
    host.cmd(24, 5, then=0)
    token, _ = host.write_block(random_block(5), n_wr=arch.N_WR - 1)
    assert token == arch.TOKEN_ACCEPTED
    assert len(card.errors) == 1 and "N_WR" in card.errors[0]
    # The same after a CMD25 block's busy.
    host.cmd(25, 6, then=0)
    host.write_block(random_block(6))
    host.write_block(random_block(7), n_wr=0)
    assert len(card.errors) == 2 and "N_WR" in card.errors[1]


def test_fewer_than_74_init_clocks():
    card, host, _ = make_card()
    host.idle(10)
    host.send(0, 0)
    assert len(card.errors) == 1 and "74" in card.errors[0]
    host.idle(arch.N_CC)
    assert host.cmd(8, arch.IF_COND_ARGUMENT) is not None       # the card still works


def test_command_while_busy():
    card, host, image = ready_card(busy_clocks=(600, 600))
    host.cmd(24, 9, then=0)
    host.write_block(random_block(9), busy_timeout=50)
    assert card.busy and card.state is CardState.PRG
    assert host.cmd(17, 9) is None
    assert "while the card is busy" in card.errors[-1]
    status = host.cmd(13, card.rca << 16)                       # CMD13 is fine while busy
    assert status.state is CardState.PRG and status.has(CardStatus.ILLEGAL_COMMAND)
    assert not status.has(CardStatus.READY_FOR_DATA)
    host.wait_busy(grace=1)
    assert image.read_block(9) == random_block(9) and len(card.errors) == 1


def test_command_spacing_and_contention():
    card, host, _ = ready_card()
    host.cmd(13, card.rca << 16, then=3)
    host.cmd(13, card.rca << 16)
    assert len(card.errors) == 1 and "N_RC" in card.errors[0]
    # The host talks over the card's response: the adapter (here the host) reports it.
    host.send(13, card.rca << 16)
    host.idle(arch.N_CR_MIN)
    for _ in range(5):
        host.clock(cmd=1)
    assert any("contention on CMD" in e for e in card.errors)


def test_four_bit_data_on_one_bit_bus_is_reported():
    card, host, image = make_card()
    initialise(host, four_bit=False)
    host.cmd(24, 3, then=0)
    host.write_block(random_block(3))
    host.idle(4096)
    assert any("1 bit wide" in e for e in card.errors)
    assert not image.is_written(3)


def test_cmd0_resets_and_aborts():
    card, host, image = ready_card(busy_clocks=(500, 500))
    host.cmd(24, 2, then=0)
    host.write_block(random_block(2), busy_timeout=10)
    host.send(0, 0)
    assert card.state is CardState.IDLE and card.rca == 0 and card.bus_width == 1
    host.idle(600)
    assert not image.is_written(2) and card.errors == []
    initialise(host)
    assert card.state is CardState.TRAN


def test_deselect_while_programming():
    card, host, image = ready_card(busy_clocks=(400, 400))
    host.cmd(24, 11, then=0)
    host.write_block(random_block(11), busy_timeout=20)
    host.cmd(7, 0, then=0)                                       # deselect: prg -> dis
    assert card.state is CardState.DIS
    assert host.clock()[1] & 1, "a deselected card leaves DAT0 alone"
    host.idle(arch.N_RC)
    assert host.cmd(13, card.rca << 16).state is CardState.DIS
    assert host.cmd(7, card.rca << 16, then=0).state is CardState.DIS     # dis -> prg
    assert card.state is CardState.PRG and not host.clock()[1] & 1        # busy again
    host.wait_busy(grace=1)
    assert card.state is CardState.TRAN and image.read_block(11) == random_block(11)
    # Programming that ends while deselected leaves the card in stby.
    host.idle(arch.N_RC)
    host.cmd(24, 12, then=0)
    host.write_block(random_block(12), busy_timeout=20)
    host.cmd(7, 0)
    host.idle(500)
    assert card.state is CardState.STBY and image.is_written(12)
    assert card.errors == []


def test_cmd12_during_a_block_discards_it():
    card, host, image = ready_card()
    host.cmd(25, 20, then=0)
    assert host.write_block(random_block(20))[0] == arch.TOKEN_ACCEPTED
    for _ in range(arch.N_WR):
        host.clock(dat=0xF)
    for value in [0] + [n for b in random_block(21)[:150] for n in (b >> 4, b & 0xF)]:
        host.clock(dat=value)
    stop = host.cmd(12, then=0)
    assert stop.state is CardState.RCV
    assert host.wait_busy() > 0 and card.state is CardState.TRAN
    assert image.is_written(20) and not image.is_written(21)
    assert BlockEvent in {type(e) for e in card.log}
    assert any(getattr(e, "outcome", "") == "partial block discarded" for e in card.log)
    assert card.errors == []


def test_register_commands():
    card, host, _ = ready_card()
    host.acmd(13, then=0)                                       # SD status: 4-bit bus
    status, ok, _ = host.read_data(64)
    assert ok and status[0] >> 6 == 0b10
    host.idle(arch.N_RC)
    assert not host.cmd(16, 512).has(CardStatus.BLOCK_LEN_ERROR)
    assert host.cmd(16, 1024).has(CardStatus.BLOCK_LEN_ERROR)
    assert host.acmd(6, 0b01).has(CardStatus.ERROR) and card.bus_width == 4
    assert host.acmd(42, 1).state is CardState.TRAN
    assert len(card.errors) == 1 and "reserved bus width" in card.errors[0]
    host.send(15, card.rca << 16)                               # CMD15: inactive for good
    host.idle(arch.N_CC)
    assert card.inactive and host.cmd(0) is None
    host.send(0, 0)
    assert host.cmd(8, arch.IF_COND_ARGUMENT) is None


def test_unexpected_dat_activity_is_reported():
    card, host, _ = ready_card()
    for _ in range(10):
        host.clock(dat=0x0)
    assert len(card.errors) == 1 and "no data transfer" in card.errors[0]


# -- cards as they are: SDSC, Ver1.X, no ACMD23, late busy ---------------------------------------

def csd_v1_capacity_blocks(csd: int) -> int:
    """Capacity of a CSD 1.0 (PLSS §5.3.2), in 512-byte blocks."""
    assert csd >> 126 == 0, "CSD_STRUCTURE 1.0"
    read_bl_len = (csd >> 80) & 0xF
    c_size = (csd >> 62) & 0xFFF
    c_size_mult = (csd >> 47) & 0x7
    assert (csd >> 22) & 0xF == read_bl_len, "WRITE_BL_LEN = READ_BL_LEN"
    assert (csd >> 79) & 1, "READ_BL_PARTIAL is 1 on every SD card"
    return ((c_size + 1) << (c_size_mult + 2) << read_bl_len) // arch.BLOCK_BYTES


@pytest.mark.parametrize("blocks, expected", [
    (CAPACITY, CAPACITY), (1000, 1000), (arch.SDSC_MAX_BLOCKS, arch.SDSC_MAX_BLOCKS),
    (3_000_001, 2_999_296),          # rounded down to what C_SIZE can say
])
def test_sdsc_csd_says_the_capacity(blocks, expected):
    card = SdCard(CardImage(blocks), high_capacity=False)
    assert card.capacity_blocks == expected == csd_v1_capacity_blocks(card.csd)
    assert (card.csd >> 80) & 0xF == (9 if blocks <= (1 << 21) else 10)   # §4.3.2


def test_sdsc_over_2_gb_is_refused():
    with pytest.raises(ValueError, match="at most 2 GB"):
        SdCard(CardImage(arch.SDSC_MAX_BLOCKS + 1), high_capacity=False)


def test_sdsc_card_takes_byte_addresses():
    card, host, image = make_card(high_capacity=False, busy_clocks=(10, 10))
    replies = initialise(host)
    assert replies["CMD8"] is not None
    assert replies["ACMD41"][-1].payload & arch.OCR_POWER_UP_DONE
    assert not replies["ACMD41"][-1].payload & arch.OCR_CCS
    data = random_block(21)
    assert host.cmd(24, 100 * arch.BLOCK_BYTES, then=0).state is CardState.TRAN
    assert host.write_block(data) == (arch.TOKEN_ACCEPTED, 10)
    assert image.read_block(100) == data and len(image) == 1
    host.idle(arch.N_RC)
    host.cmd(17, 100 * arch.BLOCK_BYTES, then=0)
    assert host.read_data()[:2] == (data, True)
    host.idle(arch.N_RC)
    # A byte address that is not a multiple of 512: ADDRESS_ERROR, no data either way.
    r1 = host.cmd(17, 100 * arch.BLOCK_BYTES + 4, then=0)
    assert r1.has(CardStatus.ADDRESS_ERROR) and card.state is CardState.TRAN
    assert host.read_data(timeout=200)[0] is None
    r1 = host.cmd(24, 7)
    assert r1.has(CardStatus.ADDRESS_ERROR) and card.state is CardState.TRAN
    assert not host.cmd(13, card.rca << 16).has(CardStatus.ADDRESS_ERROR)  # cleared on read
    # Past the end, in bytes.
    assert host.cmd(24, CAPACITY * arch.BLOCK_BYTES).has(CardStatus.OUT_OF_RANGE)
    # A multi-block write from a byte address.
    blocks = [random_block(30 + k) for k in range(3)]
    host.cmd(25, 200 * arch.BLOCK_BYTES, then=0)
    assert [host.write_block(b)[0] for b in blocks] == [arch.TOKEN_ACCEPTED] * 3
    host.cmd(12, then=0)
    host.wait_busy()
    assert [image.read_block(200 + k) for k in range(3)] == blocks
    assert card.errors == []


def test_sdsc_block_length():
    card, host, _ = ready_card(high_capacity=False)
    assert card.block_length == arch.BLOCK_BYTES          # the default, without CMD16
    assert host.cmd(16, 1024).has(CardStatus.BLOCK_LEN_ERROR)
    assert card.block_length == arch.BLOCK_BYTES
    assert not host.cmd(16, 256).has(CardStatus.BLOCK_LEN_ERROR)
    assert card.block_length == 256
    # The model moves whole 512-byte blocks only, and says so.
    assert host.cmd(17, 0).has(CardStatus.BLOCK_LEN_ERROR)
    assert len(card.errors) == 1 and "block length 256" in card.errors[0]
    host.cmd(16, 512)
    host.send(0, 0)                                       # CMD0: back to 512
    assert card.block_length == arch.BLOCK_BYTES


def test_version_1_card_ignores_cmd8_and_hcs():
    card, host, _ = make_card(high_capacity=False, version=1)
    replies = initialise(host)
    assert replies["CMD8"] is None
    assert not replies["ACMD41"][-1].payload & arch.OCR_CCS
    assert card.state is CardState.TRAN and card.errors == []
    cmd8 = next(t for t in card.log if isinstance(t, Transaction) and t.command == "CMD8")
    assert cmd8.response is Response.NONE and "Ver1.X" in cmd8.note
    # ILLEGAL_COMMAND went out with the next response, the first CMD55's R1.
    first_r1 = next(t for t in card.log if isinstance(t, Transaction) and t.command == "CMD55")
    assert first_r1.value & CardStatus.ILLEGAL_COMMAND


def test_version_1_card_reports_hcs():
    card, host, _ = make_card(high_capacity=False, version=1, acmd41_busy=(0, 0))
    host.idle(arch.INIT_CLOCKS)
    assert host.cmd(8, arch.IF_COND_ARGUMENT) is None
    r3 = host.acmd(41, arch.ACMD41_HCS | arch.OCR_VOLTAGE_WINDOW)
    assert r3.payload & arch.OCR_POWER_UP_DONE and not r3.payload & arch.OCR_CCS
    assert len(card.errors) == 1 and "HCS" in card.errors[0]


def test_card_without_acmd23():
    card, host, image = ready_card(acmd23=False)
    assert host.acmd(23, 4) is None                       # taken as CMD23: illegal
    assert card.pre_erase_count is None and card.block_count is None
    assert host.cmd(13, card.rca << 16).has(CardStatus.ILLEGAL_COMMAND)
    assert not host.cmd(13, card.rca << 16).has(CardStatus.ILLEGAL_COMMAND)
    blocks = [random_block(40 + k) for k in range(2)]
    host.cmd(25, 50, then=0)
    assert [host.write_block(b)[0] for b in blocks] == [arch.TOKEN_ACCEPTED] * 2
    host.cmd(12, then=0)
    host.wait_busy()
    assert [image.read_block(50 + k) for k in range(2)] == blocks
    assert card.errors == []          # a host may try ACMD23: not a protocol violation
    assert [t.command for t in card.log if isinstance(t, Transaction)].count("ACMD23") == 0
    # A plain CMD23 to a card without it is the host's mistake.
    assert host.cmd(23, 2) is None
    assert len(card.errors) == 1 and "no CMD23" in card.errors[0]


def test_card_with_cmd23_instead_of_acmd23():
    card, host, image = ready_card(acmd23=False, cmd23=True)
    host.cmd(55, card.rca << 16)
    r1 = host.cmd(23, 2)                                  # after CMD55: ACMD23 → CMD23
    assert r1 is not None and not r1.has(CardStatus.APP_CMD)
    assert card.block_count == 2 and card.pre_erase_count is None
    blocks = [random_block(50 + k) for k in range(2)]
    host.cmd(25, 70, then=0)
    assert [host.write_block(b)[0] for b in blocks] == [arch.TOKEN_ACCEPTED] * 2
    host.idle(arch.N_RC)
    assert card.state is CardState.TRAN                   # ended by itself after 2 blocks
    assert [image.read_block(70 + k) for k in range(2)] == blocks
    host.acmd(51, then=0)                                 # SCR: CMD_SUPPORT bit 33 set
    scr, ok, _ = host.read_data(8)
    assert ok and int.from_bytes(scr, "big") >> 33 & 1
    assert card.errors == []


@pytest.mark.parametrize("delay", [0, 3, arch.BUSY_START_CLOCKS])
def test_busy_start_delay(delay):
    card, host, image = ready_card(busy_start_delay=delay, busy_clocks=(12, 12))
    host.cmd(25, 60, then=0)
    for k in range(2):
        token, busy = host.write_block(random_block(k), grace=delay + 2)
        assert (token, busy, host.busy_start) == (arch.TOKEN_ACCEPTED, 12, delay)
    # CMD12's R1b: busy starts ``delay`` clocks after the response's end bit.
    host.cmd(12, then=0)
    assert host.wait_busy(grace=delay + 2) == 12 and host.busy_start == delay
    assert image.read_block(61) == random_block(1) and card.errors == []


# -- card models of other projects, as options: no CMD13, ILLEGAL_COMMAND not kept, v1 with CCS --

def test_card_without_cmd13_nor_acmd23():
    card, host, image = ready_card(acmd23=False, cmd13=False)
    assert host.cmd(13, card.rca << 16) is None
    assert host.acmd(23, 4) is None
    assert host.cmd(13, card.rca << 16) is None
    # Nothing answers CMD13, and it flags nothing: the ILLEGAL_COMMAND of the ACMD23 (taken
    # as CMD23) is what the next response carries.
    assert host.cmd(55, card.rca << 16).has(CardStatus.ILLEGAL_COMMAND)
    assert not host.cmd(55, card.rca << 16).has(CardStatus.ILLEGAL_COMMAND)
    host.cmd(24, 9, then=0)
    assert host.write_block(random_block(9))[0] == arch.TOKEN_ACCEPTED
    assert image.read_block(9) == random_block(9)
    notes = [t.note for t in card.log if isinstance(t, Transaction) and t.command == "CMD13"]
    assert notes == ["this card does not answer CMD13"] * 2
    assert card.errors == []


@pytest.mark.parametrize("kept", [True, False])
def test_illegal_command_kept_or_cleared_by_the_next_command(kept):
    card, host, _ = ready_card(illegal_kept=kept)
    assert host.cmd(2) is None                                  # CMD2 in tran: illegal
    status = host.cmd(13, card.rca << 16)
    assert status.has(CardStatus.ILLEGAL_COMMAND) is kept
    assert not host.cmd(13, card.rca << 16).has(CardStatus.ILLEGAL_COMMAND)
    # A command lost to a CRC error is still reported, either way.
    assert host.cmd(13, card.rca << 16, bad_crc=True) is None
    assert host.cmd(13, card.rca << 16).has(CardStatus.COM_CRC_ERROR)


def test_version_1_card_with_ccs_takes_byte_addresses():
    card, host, image = make_card(high_capacity=False, version=1, ocr_ccs=True)
    replies = initialise(host)
    assert replies["CMD8"] is None
    assert replies["ACMD41"][-1].payload & arch.OCR_CCS         # claims block addressing
    assert all(not r.payload & arch.OCR_CCS for r in replies["ACMD41"][:-1])
    # ... yet takes byte addresses: block 3 is at byte 1536; "3" is misaligned.
    assert host.cmd(24, 3).has(CardStatus.ADDRESS_ERROR)
    host.cmd(24, 3 * arch.BLOCK_BYTES, then=0)
    assert host.write_block(random_block(3))[0] == arch.TOKEN_ACCEPTED
    assert image.read_block(3) == random_block(3)
    assert card.errors == []
