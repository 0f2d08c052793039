"""A command-level SD card for the transaction-level logger model.

Commands arrive whole (index and argument) and responses leave whole, as the bit strings a
real card puts on CMD (CRC7 included), so the host model can check them as the gateware's
CMD engine does. Blocks arrive whole; the card stores a block when its programming (busy)
ends. It is written independently of sim/models/sdcard.py (the bit-level model), so that
each checks the driver from its own reading of the specification.

States, commands and status bits: hw/arch/sd.py (PLSS §4.2, §4.3, §4.7.4, §4.10.1).
"""

from __future__ import annotations

import random

from ...hw.arch import sd as arch
from ...hw.arch.sd import AppCommand, CardState, CardStatus, Command, Response


__all__ = ["crc7", "response_bits", "ModelCard", "Answer"]


def crc7(value, bits):
    """CRC7 (PLSS §4.5) of the ``bits`` low bits of ``value``, most significant first."""
    crc = 0
    for k in range(bits - 1, -1, -1):
        feedback = ((value >> k) & 1) ^ (crc >> 6)
        crc = (crc << 1) & 0x7F
        if feedback:
            crc ^= arch.CRC7_POLY
    return crc


def response_bits(response, index, payload):
    """The response's bits as the card sends them (start bit first = most significant) and
    their count. ``payload``: 32 bits, or 128 (R2: the CID/CSD with its own CRC7 in 7..1)."""
    if response is Response.R2:
        # Start 0, transmission 0, 111111, register bits 127..1, end 1 (its bit 0).
        return (arch.RESPONSE_INDEX_ONES << 128) | payload | 1, arch.R2_BITS
    if response is Response.R3:
        head = arch.RESPONSE_INDEX_ONES
        body = (head << 32) | payload
        return (body << 8) | (arch.R3_CRC_ONES << 1) | 1, arch.CMD_BITS
    body = (index << 32) | payload              # start 0, transmission 0: the top two bits
    return (body << 8) | (crc7(body, arch.CMD_CRC_LAST) << 1) | 1, arch.CMD_BITS


class Answer:
    """What the card does with a command: its response (None: silence) and what follows.

    ``busy_s`` is the time DAT0 stays low after an R1b; ``read`` the LBA of a block the card
    sends after the response (a write's blocks are taken while the card is in rcv)."""
    __slots__ = ("response", "index", "payload", "busy_s", "read")

    def __init__(self, response=None, index=0, payload=0, *, busy_s=0.0, read=None):
        self.response, self.index, self.payload = response, index, payload
        self.busy_s, self.read = busy_s, read

    def bits(self):
        return response_bits(self.response, self.index, self.payload)


class _Illegal(Exception):
    pass


class ModelCard:
    """An SD memory card (version 2, SDHC by default) at command and block level.

    Parameters
    ----------
    image : CardImage
    seed : int
        Seeds the programming and read access times.
    high_capacity : bool
        OCR CCS: block addressing (SDHC/SDXC) or byte addressing (standard capacity).
    version : int
        2 (answers CMD8) or 1 (a Ver1.X card: CMD8 is illegal, always standard capacity).
    pre_erase : bool
        Whether ACMD23 is taken (some cards do not: it is then an illegal command).
    busy_range : (float, float)
        Programming time of a written block (DAT0 busy), seconds, uniform.
    read_range : (float, float)
        Read access time (command end to the data's start bit), seconds, uniform.
    power_up_s : float
        ACMD41 answers busy until this long after the first ACMD41.
    stop_busy_s : float
        Busy after CMD12 ends a multi-block write.
    """
    #: MID, OID "ML", PNM "MGLOG", PRV 1.0, PSN, MDT 2026-11; CRC7 and end bit added.
    CID = int.from_bytes(bytes([0x1D]) + b"ML" + b"MGLOG" + bytes([0x10]) +
                         (0x12345678).to_bytes(4, "big") + (0x01AB).to_bytes(2, "big") +
                         bytes(1), "big")

    def __init__(self, image, *, seed=0, high_capacity=True, version=2, pre_erase=True,
                 busy_range=(50e-6, 400e-6), read_range=(20e-6, 100e-6), power_up_s=5e-3,
                 stop_busy_s=10e-6):
        if version not in (1, 2):
            raise ValueError(f"Card version must be 1 or 2, not {version!r}")
        if version == 1 and high_capacity:
            raise ValueError("A version 1 card is standard capacity: give high_capacity=False")
        for name, (low, high) in (("Busy range", busy_range), ("Read range", read_range)):
            if not 0 <= low <= high:
                raise ValueError(f"{name} must be (low, high) seconds with 0 <= low <= high, "
                                 f"not {(low, high)!r}")
        self.image = image
        self.high_capacity, self.version, self.pre_erase = high_capacity, version, pre_erase
        self.busy_range, self.read_range = busy_range, read_range
        self.power_up_s, self.stop_busy_s = power_up_s, stop_busy_s
        self._rng = random.Random(seed)
        self.present = True
        self.insertions = 0             # a block programmed across a removal is lost
        self.blocks_written = 0
        self.power_on()

    def power_on(self):
        """Power-up (or a CMD0): the idle state, no RCA, nothing pending."""
        self.state = CardState.IDLE
        self.rca = 0
        self.app = False
        self.pending_errors = CardStatus(0)     # clear condition B: shown by the next answer
        self.sticky = CardStatus(0)             # clear condition C: shown until read
        self.first_acmd41 = None
        self.ready_bit = False
        self.write_lba = None
        self.multi = False

    # -- commands ---------------------------------------------------------------------------

    def command(self, now_s, index, argument):
        """The card's answer to a command at ``now_s`` seconds."""
        if not self.present:
            return Answer()
        app, self.app = self.app, False
        before = self.state
        try:
            if app and index in set(AppCommand):
                answer = self._app(now_s, AppCommand(index), argument, before)
            else:
                answer = self._basic(now_s, index, argument, before)
        except _Illegal:
            # No response; ILLEGAL_COMMAND shows in the next answer (PLSS §4.10.1, B).
            self.pending_errors |= CardStatus.ILLEGAL_COMMAND
            return Answer()
        return answer

    def _status(self, before, extra=CardStatus(0), *, app=False):
        status = self.pending_errors | self.sticky | extra
        self.pending_errors = CardStatus(0)
        self.sticky = CardStatus(0)
        if app:
            status |= CardStatus.APP_CMD
        if before != CardState.PRG:
            status |= CardStatus.READY_FOR_DATA
        return int(status) | (int(before) << arch.STATUS_STATE_SHIFT)

    def _r1(self, index, before, extra=CardStatus(0), *, app=False, **more):
        return Answer(Response.R1, index, self._status(before, extra, app=app), **more)

    def _addressed(self, argument):
        return argument >> 16 == self.rca

    def _require(self, *states):
        if self.state not in states:
            raise _Illegal

    def _lba(self, argument):
        return argument if self.high_capacity else argument // arch.BLOCK_BYTES

    def _basic(self, now_s, index, argument, before):
        if index == Command.GO_IDLE_STATE:
            self.power_on()
            return Answer(Response.NONE)
        if index == Command.SEND_IF_COND:
            if self.version == 1:
                raise _Illegal
            self._require(CardState.IDLE)
            if (argument & arch.IF_COND_VHS_MASK) >> arch.IF_COND_VHS_SHIFT \
                    != arch.IF_COND_VHS_2V7_3V6:
                return Answer()
            return Answer(Response.R7, index, argument & arch.IF_COND_ECHO_MASK)
        if index == Command.ALL_SEND_CID:
            self._require(CardState.READY)
            self.state = CardState.IDENT
            return Answer(Response.R2, index, self._cid())
        if index == Command.SEND_RELATIVE_ADDR:
            self._require(CardState.IDENT, CardState.STBY)
            self.rca = self._rng.randrange(1, 1 << 16)
            self.state = CardState.STBY
            status = self._status(before)
            r6 = status & arch.R6_STATUS_LOW_MASK
            for bit, to in arch.R6_STATUS_HIGH_BITS:
                r6 |= ((status >> bit) & 1) << to
            return Answer(Response.R6, index, (self.rca << 16) | r6)
        if index == Command.SELECT_CARD:
            if self._addressed(argument) and self.rca:
                self._require(CardState.STBY, CardState.TRAN)
                self.state = CardState.TRAN
                return self._r1(index, before)
            if self.state in (CardState.TRAN, CardState.DATA, CardState.RCV, CardState.PRG):
                self.state = CardState.STBY      # deselected: no response
            return Answer()
        if index == Command.SEND_STATUS:
            if not self._addressed(argument) or self.state in (
                    CardState.IDLE, CardState.READY, CardState.IDENT):
                raise _Illegal
            return self._r1(index, before)
        if index == Command.APP_CMD:
            if self.state not in (CardState.IDLE,) and not self._addressed(argument):
                raise _Illegal
            self.app = True
            return self._r1(index, before, app=True)
        if index == Command.SET_BLOCKLEN:
            self._require(CardState.TRAN)
            error = CardStatus(0) if argument == arch.BLOCK_BYTES else \
                CardStatus.BLOCK_LEN_ERROR
            return self._r1(index, before, error)
        if index == Command.STOP_TRANSMISSION:
            self._require(CardState.DATA, CardState.RCV, CardState.PRG)
            if self.state == CardState.PRG:
                # The block being programmed is the last: tran when it is done.
                self.multi = False
                return self._r1(index, before)
            busy = self.stop_busy_s if self.state == CardState.RCV else 0.0
            self.state = CardState.TRAN
            self.write_lba = None
            return self._r1(index, before, busy_s=busy)
        if index == Command.READ_SINGLE_BLOCK:
            self._require(CardState.TRAN)
            lba = self._lba(argument)
            if not 0 <= lba < self.image.capacity_blocks:
                return self._r1(index, before, CardStatus.OUT_OF_RANGE)
            self.state = CardState.DATA
            return self._r1(index, before, read=lba)
        if index in (Command.WRITE_BLOCK, Command.WRITE_MULTIPLE_BLOCK):
            self._require(CardState.TRAN)
            lba = self._lba(argument)
            if not 0 <= lba < self.image.capacity_blocks:
                return self._r1(index, before, CardStatus.OUT_OF_RANGE)
            self.state = CardState.RCV
            self.write_lba = lba
            self.multi = index == Command.WRITE_MULTIPLE_BLOCK
            return self._r1(index, before)
        raise _Illegal

    def _app(self, now_s, index, argument, before):
        if index == AppCommand.SD_SEND_OP_COND:
            self._require(CardState.IDLE, CardState.READY)
            if self.first_acmd41 is None:
                self.first_acmd41 = now_s
            ocr = arch.OCR_VOLTAGE_WINDOW
            if now_s - self.first_acmd41 >= self.power_up_s:
                ocr |= arch.OCR_POWER_UP_DONE
                if self.high_capacity and argument & arch.ACMD41_HCS:
                    ocr |= arch.OCR_CCS
                self.state = CardState.READY
            return Answer(Response.R3, 0, ocr)
        if index == AppCommand.SET_BUS_WIDTH:
            self._require(CardState.TRAN)
            return self._r1(index, before, app=True)
        if index == AppCommand.SET_WR_BLK_ERASE_COUNT:
            if not self.pre_erase:
                raise _Illegal
            self._require(CardState.TRAN)
            return self._r1(index, before, app=True)
        raise _Illegal

    def _cid(self):
        cid = self.CID & ~0xFF
        return cid | (crc7(cid >> 8, 120) << 1) | 1

    # -- data -------------------------------------------------------------------------------

    def busy_s(self):
        """The programming time of the next block."""
        return self._rng.uniform(*self.busy_range)

    def read_s(self):
        return self._rng.uniform(*self.read_range)

    def receiving(self):
        """The card takes a block now (it is in rcv)."""
        return self.present and self.state == CardState.RCV and self.write_lba is not None

    def program(self, data):
        """The block just received is programmed (its busy has ended): store it."""
        lba = self.write_lba
        if lba >= self.image.capacity_blocks:
            self.sticky |= CardStatus.OUT_OF_RANGE
            self.state = CardState.TRAN
            self.write_lba = None
            return None
        self.image.write_block(lba, data)
        self.blocks_written += 1
        if self.multi:
            self.write_lba += 1
            self.state = CardState.RCV
        else:
            self.state = CardState.TRAN
            self.write_lba = None
        return lba

    def start_programming(self):
        self.state = CardState.PRG

    def block(self, lba):
        """A block to send (CMD17); the card is back in tran after it."""
        self.state = CardState.TRAN
        return self.image.read_block(lba)

    def remove(self):
        self.present = False
        self.insertions += 1

    def insert(self):
        self.present = True
        self.power_on()
