"""A protocol-checking SD card (SD mode, SDHC or SDSC, 1- or 4-bit bus), bit by bit, in plain
Python.

:class:`SdCard` is written from the SD Physical Layer Simplified Specification (PLSS, see
:mod:`maglog.hw.arch.sd`), independently of the gateware: it shares nothing with hw/ but the
protocol constants, and computes its CRCs itself. The adapters for the Amaranth simulator and
for cocotb go through one :class:`SdBus`, which resolves the lines (host, card, pull-up),
calls :meth:`SdCard.edge` at every rising edge of the SD clock with the bus levels and hands
back what the host sees until the next one.

Clocking convention. ``edge(cmd, dat)`` is rising edge number :attr:`SdCard.clock` (counted
from 0). Its inputs are the levels sampled at that edge; its outputs are what the card drives
during the following clock period, so the host samples them at the next edge. Every timing
below counts whole clock periods *between* two bits: "N_CR = 2" means two periods in which
nobody drives CMD between the command's end bit and the response's start bit.

What the card does (PLSS chapter 4):

* Commands: 48 bits, CRC7 checked. A bad CRC7 or end bit (COM_CRC_ERROR), an unknown
  command or one that is illegal in the current state (ILLEGAL_COMMAND) gets no response;
  the flag is set in the next response that carries card status (clear condition B, kept
  until reported). Frames with a zero transmission bit, and addressed commands carrying
  another card's RCA, are ignored. Commands other than CMD0, CMD7, CMD12, CMD13 and CMD55
  are illegal while the card programs (prg), and reported as commands sent during busy.
* Identification: CMD0, CMD8 (R7, 0x1AA echoed), CMD55 + ACMD41 (R3; with HCS after a CMD8
  the card is busy for a seeded number of calls, then ready with CCS = 1), CMD2 (R2 CID),
  CMD3 (R6, new RCA); CMD2 and ACMD41 answer N_ID = 5 clocks after the command, every other
  response N_CR (configurable, 2..64) clocks after.
* Standard capacity (``high_capacity=False``, at most 2 GB): CCS = 0 in the OCR, HCS
  ignored, a version 1.0 CSD, and byte addresses (PLSS §4.3.14 note 2, Table 4-24): the
  argument of CMD17/18/24/25 is a byte address, a multiple of the block length (512 by
  default, PLSS Table 4-22 CMD16) or ADDRESS_ERROR (no transfer, PLSS §4.3.3). With
  ``version=1`` the card is a Ver1.X card: CMD8 is an illegal command to it (no response,
  ILLEGAL_COMMAND next), and the host must send ACMD41 with HCS = 0 (PLSS §4.2.3.1).
* ``acmd23=False``: a card that does not define ACMD23 (SET_WR_BLK_ERASE_COUNT; mandatory
  in the PLSS, so this is a card outside it). PLSS §4.3.9.1: an ACMD the card does not
  define is taken as the regular command of that index, here CMD23 (SET_BLOCK_COUNT,
  optional). Without CMD23 (``cmd23=False``) that is illegal: no response, ILLEGAL_COMMAND in
  the next response (§4.10.1, condition B); a command this card lacks is logged, not
  reported as a host error. With ``cmd23=True`` it sets the block count of the next CMD25,
  answered by an R1 with APP_CMD clear (§4.3.9.1 item 4); that CMD25 ends by itself after
  so many blocks (no CMD12, which would be illegal in tran).
* Cards outside the spec, as other SD card models behave (options, all off by default):
  ``cmd13=False``, a card that never answers CMD13 (no response, nothing flagged); with
  ``acmd23=False`` it answers neither ACMD23 nor CMD13. ``illegal_kept=False``: the
  ILLEGAL_COMMAND flag is cleared when the next command arrives instead of being kept until
  a response reports it (§4.10.1 clear condition B), so no response ever shows it.
  ``ocr_ccs=True`` on a Ver1.X card (``version=1``, standard capacity): the OCR's CCS bit is
  set although the card takes byte addresses (CCS is reserved for it, PLSS §5.1).
* Transfer: CMD7 (select R1b / deselect), CMD9/CMD10 (R2 CSD/CID), CMD13 (R1), CMD16, CMD17
  and CMD18 (reads), CMD24 and CMD25 (writes, ended by CMD12), CMD12 (R1b), CMD15, ACMD6
  (bus width), ACMD13 (SD status), ACMD22 (well-written blocks), ACMD23 (pre-erase count),
  ACMD42, ACMD51 (SCR). Block addressing (SDHC): the argument is the LBA.
* Data: start bit 0 on every line in use, 512 bytes (1024 nibbles high nibble first on four
  lines, DAT3 carrying the nibble's MSB; or 4096 bits MSB first on DAT0), one CRC16 per line,
  end bit 1. Written blocks are answered N_CRC = 2 clocks after their end bit by the CRC
  status token on DAT0 (0, ``010`` accepted / ``101`` CRC error / ``110`` write error, 1), then
  the card holds DAT0 low while it programs (a seeded number of clocks in ``busy_clocks``;
  with ``busy_start_delay`` it first leaves DAT0 released for that many clocks),
  stores the block, drives DAT0 high for one clock and releases it. CMD12 ends a CMD25:
  a block being received is discarded, one being programmed is finished, and the R1b's busy
  starts right after its end bit. A deselected card (dis) programs without driving DAT0.

Protocol violations are appended to :attr:`SdCard.errors` as ``"clock N: ..."`` strings;
the card keeps going as a real card would. Commands and block transfers are recorded in
:attr:`SdCard.log`.
"""

from __future__ import annotations

import random
from collections.abc import Generator, Iterable, Iterator
from dataclasses import dataclass

from ...hw.arch import sd as arch
from ...hw.arch.sd import AppCommand, CardState, CardStatus, Command, Response

from .card_image import CardImage

__all__ = ["SdCard", "SdBus", "Faults", "Transaction", "BlockEvent", "CardState", "crc7",
           "crc16"]

#: Released lines: what ``edge`` returns while the card drives nothing.
_RELEASED = (0, 1, 0, 0xF)
_ALL_LINES = 0xF
_DAT0 = 0b0001
#: DAT0 low (busy, a token's 0 bit), other lines shown high (they are not driven).
_DAT0_LOW = _ALL_LINES & ~_DAT0
_DATA_BITS_1BIT = 8 * arch.BLOCK_BYTES
_CRC16_MASK = (1 << arch.CRC16_BITS) - 1
_CRC7_MASK = (1 << arch.CRC7_BITS) - 1
_RCA_SHIFT = 16
_RCA_MASK = 0xFFFF

#: States in which an addressed command (CMD7, 9, 10, 13, 15, 55) can be legal.
_ADDRESSED_STATES = (CardState.STBY, CardState.TRAN, CardState.DATA, CardState.RCV,
                     CardState.PRG, CardState.DIS)
_COMMAND_INDICES = {int(c) for c in Command}
_ACMD_INDICES = {int(c) for c in AppCommand}


def crc7(bits: Iterable[int]) -> int:
    """CRC7 (x^7 + x^3 + 1, register starting at 0) of a bit sequence, MSB first."""
    reg = 0
    for bit in bits:
        feedback = (reg >> (arch.CRC7_BITS - 1)) ^ bit
        reg = (reg << 1) & _CRC7_MASK
        if feedback & 1:
            reg ^= arch.CRC7_POLY
    return reg


def crc16(bits: Iterable[int]) -> int:
    """CRC16-CCITT (x^16 + x^12 + x^5 + 1, register starting at 0) of a bit sequence."""
    reg = 0
    for bit in bits:
        feedback = (reg >> (arch.CRC16_BITS - 1)) ^ bit
        reg = (reg << 1) & _CRC16_MASK
        if feedback & 1:
            reg ^= arch.CRC16_POLY
    return reg


def _bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - i)) & 1 for i in range(width)]


def _value(bits: Iterable[int]) -> int:
    value = 0
    for bit in bits:
        value = (value << 1) | bit
    return value


@dataclass(frozen=True)
class Faults:
    """Injected card faults, all off by default and all deterministic.

    Written blocks are numbered from 0 in the order the card receives them (CMD24 and CMD25
    alike, over the card's life; blocks the card ignores after a rejected block of a CMD25
    are not counted). Responses are numbered from 0 among those that carry a CRC7 (all but R3).
    """
    #: Number of the written block in which one received data bit is flipped: the card sees
    #: a CRC error on that line, answers ``101`` and does not store the block.
    flip_dat_bit: int | None = None
    #: DAT line of the flipped bit (0 in 1-bit mode).
    flip_line: int = 0
    #: Bit position on that line within the block's data (0 = first), or None for one drawn
    #: from the card's seed.
    flip_position: int | None = None
    #: Number of the response sent with a wrong CRC7 (for R2, the CID/CSD's own CRC7).
    corrupt_response_crc: int | None = None
    #: Number of the written block after which no CRC status token comes; the card does not
    #: store it (after CMD24 it is back in tran; in a CMD25 it ignores data until CMD12).
    withhold_token: int | None = None
    #: Number of the written block whose busy lasts ``busy_past_timeout_clocks`` clocks.
    busy_past_timeout: int | None = None
    #: Default: one clock past the host's 250 ms write timeout at 25 MHz.
    busy_past_timeout_clocks: int = arch.BUSY_TIMEOUT_CLOCKS + 1
    #: No card in the socket: it never drives anything and checks nothing.
    no_card: bool = False

    def __post_init__(self):
        for name in ("flip_dat_bit", "corrupt_response_crc", "withhold_token",
                     "busy_past_timeout", "flip_position"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 0):
                raise ValueError(f"Fault {name} must be a non-negative integer or None, "
                                 f"not {value!r}")
        if self.flip_position is not None and self.flip_position >= _DATA_BITS_1BIT:
            raise ValueError(f"Fault flip_position must be below {_DATA_BITS_1BIT} (below "
                             f"{arch.DATA_NIBBLES} on a 4-bit bus), not {self.flip_position!r}")
        if self.flip_line not in range(4):
            raise ValueError(f"Fault flip_line must be a DAT line 0..3, not {self.flip_line!r}")
        clocks = self.busy_past_timeout_clocks
        if not isinstance(clocks, int) or clocks < 1:
            raise ValueError(f"Fault busy_past_timeout_clocks must be a positive integer, not "
                             f"{self.busy_past_timeout_clocks!r}")


@dataclass(frozen=True)
class Transaction:
    """A command as the card saw it (``clock`` is the edge of its end bit)."""
    clock: int
    command: str                 # "CMD17", "ACMD41"
    argument: int
    response: Response           # Response.NONE when the card did not answer
    value: int | None = None     # status, OCR, RCA << 16 | status, R7 argument, CID/CSD
    note: str = ""


@dataclass(frozen=True)
class BlockEvent:
    """A data block on the DAT lines (``clock`` is the edge of its end bit, or the abort)."""
    clock: int
    direction: str               # "write" (host to card) or "read"
    lba: int | None              # None for register reads (SCR, SD status, ...)
    outcome: str                 # "stored", "crc error", "token withheld", "sent", ...


class _Illegal(Exception):
    """The command is illegal in the card's state: no response, ILLEGAL_COMMAND next."""


class _Unsupported(_Illegal):
    """Illegal because this card's configuration lacks the command (a Ver1.X card's CMD8,
    ACMD23 on a card without it): no response and ILLEGAL_COMMAND, as for any illegal
    command, but no host error is recorded — a host may probe for it."""


class _NotAddressed(Exception):
    """The command carries another card's RCA: this card ignores it."""


@dataclass
class _Reply:
    response: Response
    value: int = 0
    note: str = ""


class SdCard:
    """An SDHC or SDSC card on an SD-mode bus; see the module documentation.

    Parameters
    ----------
    image : CardImage
        Where written blocks go and read blocks come from.
    seed : int
        Seeds every random choice (RCA, serial number, ACMD41 busy calls, busy times,
        response delays when ``n_cr`` is a range, fault positions).
    capacity_blocks : int or None
        Addressable blocks (default: the image's capacity; at most that).
    busy_clocks : (int, int)
        Inclusive range of the programming busy after each accepted block, in clocks.
    faults : Faults or None
    rca : int or None
        Relative card address published by CMD3 (default: seeded, non-zero).
    n_cr : int or (int, int)
        Clocks between a command's end bit and the response's start bit (2..64), or an
        inclusive range to draw each response's delay from.
    n_ac : int or None
        Clocks between a read command's end bit and the first data start bit (≥ 2); by
        default the data starts 2 clocks after the response's end bit.
    acmd41_busy : (int, int)
        Inclusive range of the number of ACMD41 calls answered busy before the card is ready.
    high_capacity : bool
        True: SDHC (block addresses, CSD 2.0). False: SDSC, at most 2 GB (byte addresses,
        CSD 1.0); its capacity is the largest the CSD 1.0 fields express up to
        ``capacity_blocks``, and :attr:`capacity_blocks` says what it is.
    version : int
        2: the card answers CMD8 (physical layer 2.00 or later). 1: a Ver1.X card (SDSC
        only), to which CMD8 is an illegal command.
    acmd23 : bool
        False: this card does not define ACMD23 (see the module documentation).
    cmd23 : bool
        The card supports CMD23 (SET_BLOCK_COUNT) for CMD25 (SCR CMD_SUPPORT bit 33).
    busy_start_delay : int
        Clocks the card leaves DAT0 released after a CRC status token's end bit (and after
        the end bit of CMD12's R1b) before it holds DAT0 low for busy; 0 = at once, as the
        PLSS timing diagrams draw it.
    cmd13 : bool
        False: the card never answers CMD13 (SEND_STATUS) and flags nothing for it.
    illegal_kept : bool
        False: ILLEGAL_COMMAND is cleared when the next command arrives, before its
        response, instead of being kept until reported: no response shows it.
    ocr_ccs : bool or None
        The CCS bit of the OCR once the card is ready; None: as ``high_capacity``. True on a
        standard-capacity card gives a card that claims block addressing in its OCR but
        takes byte addresses.
    """

    def __init__(self, image: CardImage, *, seed=0, capacity_blocks=None, busy_clocks=(8, 64),
                 faults: Faults | None = None, rca=None, n_cr=arch.N_CR_MIN, n_ac=None,
                 acmd41_busy=(1, 4), high_capacity=True, version=2, acmd23=True,
                 cmd23=False, busy_start_delay=0, cmd13=True, illegal_kept=True,
                 ocr_ccs=None):
        if not isinstance(image, CardImage):
            raise TypeError(f"Image must be a CardImage, not {image!r}")
        if capacity_blocks is None:
            capacity_blocks = image.capacity_blocks
        if (not isinstance(capacity_blocks, int) or
                not 1 <= capacity_blocks <= image.capacity_blocks):
            raise ValueError(f"Capacity must be 1..{image.capacity_blocks} blocks (the "
                             f"image's), not {capacity_blocks!r}")
        self._busy_range = _check_range("Busy clocks", busy_clocks, 1, None)
        self._n_cr = _check_range("N_CR", n_cr, arch.N_CR_MIN, arch.N_CR_MAX)
        if n_ac is not None and (not isinstance(n_ac, int) or n_ac < arch.N_AC_MIN):
            raise ValueError(f"N_AC must be an integer of at least {arch.N_AC_MIN} clocks or "
                             f"None, not {n_ac!r}")
        self._n_ac = n_ac
        self._acmd41_range = _check_range("ACMD41 busy calls", acmd41_busy, 0, None)
        if rca is not None and (not isinstance(rca, int) or not 1 <= rca <= _RCA_MASK):
            raise ValueError(f"RCA must be an integer in 1..0xFFFF or None, not {rca!r}")
        if version not in (1, 2):
            raise ValueError(f"Version must be 1 (Ver1.X, no CMD8) or 2, not {version!r}")
        if version == 1 and high_capacity:
            raise ValueError("A version 1 card is standard capacity: give high_capacity=False")
        if not high_capacity and capacity_blocks > arch.SDSC_MAX_BLOCKS:
            raise ValueError(f"A standard-capacity card holds at most 2 GB "
                             f"({arch.SDSC_MAX_BLOCKS} blocks), not {capacity_blocks!r} blocks")
        if (not isinstance(busy_start_delay, int) or isinstance(busy_start_delay, bool)
                or busy_start_delay < 0):
            raise ValueError(f"Busy start delay must be a non-negative number of clocks, not "
                             f"{busy_start_delay!r}")
        for name, value in (("CMD13", cmd13), ("Illegal kept", illegal_kept)):
            if not isinstance(value, bool):
                raise ValueError(f"{name} must be True or False, not {value!r}")
        if ocr_ccs is not None and not isinstance(ocr_ccs, bool):
            raise ValueError(f"OCR CCS must be True, False or None, not {ocr_ccs!r}")
        if faults is None:
            faults = Faults()
        if not isinstance(faults, Faults):
            raise TypeError(f"Faults must be a Faults instance or None, not {faults!r}")

        self.image = image
        self.high_capacity = bool(high_capacity)
        self.version = version
        self.acmd23 = bool(acmd23)
        self.cmd23 = bool(cmd23)
        self.busy_start_delay = busy_start_delay
        self.cmd13 = cmd13
        self.illegal_kept = illegal_kept
        self.ocr_ccs = self.high_capacity if ocr_ccs is None else ocr_ccs
        if not self.high_capacity:
            self._csd_v1 = _csd_v1_fields(capacity_blocks)
            capacity_blocks = self._csd_v1["blocks"]
        self.capacity_blocks = capacity_blocks
        self.faults = faults
        self._fixed_rca = rca
        # One stream per purpose, so that (say) an extra CMD13 does not change busy times.
        self._id_rng = random.Random(f"identity/{seed}")
        self._timing_rng = random.Random(f"timing/{seed}")
        self._busy_rng = random.Random(f"busy/{seed}")
        self._fault_rng = random.Random(f"faults/{seed}")

        #: Protocol violations, as "clock N: message".
        self.errors: list[str] = []
        #: :class:`Transaction` and :class:`BlockEvent` records, in order.
        self.log: list = []
        #: Rising edges seen so far (the number of the next edge).
        self.clock = 0
        #: Written blocks received, accepted and stored (all commands).
        self.blocks_received = 0
        self.blocks_stored = 0

        self.cid = self._make_cid()
        self.csd = self._make_csd()

        # CMD line: receiver and transmitter.
        self._rx: list[int] | None = None
        self._rx_start = 0
        self._commands_seen = 0
        self._line_free_since: int | None = None   # edge of the last CMD bit (host or card)
        self._line_free_after_response = False
        self._cmd_tx: tuple[int, list[int]] | None = None   # (edge of first bit, bits)
        self._cmd_turnaround_reported = False
        self._responses_with_crc = 0
        self._prev_cmd_oe = 0
        self._prev_dat_oe = 0
        self._dat_activity_reported = False

        self._reset()

    # -- state ---------------------------------------------------------------------------------

    def _reset(self):
        """Power-up and CMD0 state (PLSS §4.2.1): idle, RCA 0, 1-bit bus, no transfer."""
        op = getattr(self, "_op", None)
        if op is not None:
            op.close()
        self.state = CardState.IDLE
        self.rca = 0
        self.bus_width = 1
        self.inactive = False
        self.ocr_ready = False
        #: Pre-erase count set by ACMD23 for the next CMD25 (None: not set).
        self.pre_erase_count: int | None = None
        #: Block count set by CMD23 for the next CMD25 (None: not set, CMD12 ends it).
        self.block_count: int | None = None
        #: SDSC: block length of reads and writes, 512 after power-up and CMD0 (PLSS Table
        #: 4-22, CMD16: "Default block length is fixed to 512 Bytes").
        self.block_length = arch.BLOCK_BYTES
        self._if_cond = False
        self._acmd41_left: int | None = None
        self._hcs_reported = False
        self._app = False
        self._pending = CardStatus(0)
        self._op: Generator | None = None
        self._busy = False
        self._stop_at: int | None = None
        self._stop_busy_from = 0
        self._well_written = 0

    def report(self, message: str) -> None:
        """Record a protocol violation (adapters report bus contention this way)."""
        self.errors.append(f"clock {self.clock}: {message}")

    def _error(self, now: int, message: str) -> None:
        self.errors.append(f"clock {now}: {message}")

    @property
    def busy(self) -> bool:
        """The card is programming (DAT0 held low while selected)."""
        return self._busy

    # -- the bus -------------------------------------------------------------------------------

    def edge(self, cmd: int, dat: int) -> tuple[int, int, int, int]:
        """One rising edge of the SD clock. `cmd` (0/1) and `dat` (4 bits, DAT0 in bit 0)
        are the bus levels at this edge (host-driven value, or the card's own, or the
        pull-up's 1). Returns (cmd_oe, cmd_out, dat_oe, dat_out): what the card drives during
        the following clock period (dat_oe is a 4-bit mask: e.g. 0b0001 while it drives only
        DAT0)."""
        if cmd not in (0, 1) or not 0 <= dat <= _ALL_LINES:
            raise ValueError(f"CMD must be 0 or 1 and DAT 0..15, not {cmd!r} and {dat!r}")
        now = self.clock
        self.clock = now + 1
        if self.faults.no_card or self.inactive:
            return _RELEASED
        if not self._prev_cmd_oe:
            self._cmd_input(now, cmd)
        dat_oe, dat_out = self._dat_step(now, dat)
        cmd_oe, cmd_out = self._cmd_output(now)
        if self.state is CardState.DIS:
            dat_oe, dat_out = 0, _ALL_LINES     # a deselected card leaves the DAT lines alone
        self._prev_cmd_oe = cmd_oe
        self._prev_dat_oe = dat_oe
        return cmd_oe, cmd_out, dat_oe, dat_out

    # -- CMD line ------------------------------------------------------------------------------

    def _cmd_input(self, now: int, cmd: int) -> None:
        tx = self._cmd_tx
        if tx is not None and now <= tx[0]:
            # Between the command's end bit and our response: nobody may drive CMD.
            if cmd == 0 and not self._cmd_turnaround_reported:
                self._cmd_turnaround_reported = True
                self._error(now, "CMD driven low between a command and its response (N_CR)")
            return
        if self._rx is None:
            if cmd == 0:
                self._rx = [0]
                self._rx_start = now
                self._check_command_spacing(now)
            return
        self._rx.append(cmd)
        if len(self._rx) == arch.CMD_BITS:
            bits, self._rx = self._rx, None
            self._command(now, bits)

    def _check_command_spacing(self, now: int) -> None:
        if self._commands_seen == 0 and now < arch.INIT_CLOCKS:
            self._error(now, f"first command after {now} clocks; the card needs at least "
                             f"{arch.INIT_CLOCKS} (the command is ignored)")
        if self._line_free_since is None:
            return
        gap = now - self._line_free_since - 1
        if self._line_free_after_response and gap < arch.N_RC:
            self._error(now, f"command {gap} clocks after the response's end bit; "
                             f"N_RC is at least {arch.N_RC}")
        elif not self._line_free_after_response and gap < arch.N_CC:
            self._error(now, f"command {gap} clocks after the previous command's end bit; "
                             f"N_CC is at least {arch.N_CC}")

    def _cmd_output(self, now: int) -> tuple[int, int]:
        tx = self._cmd_tx
        if tx is None:
            return 0, 1
        start, bits = tx
        i = now - start
        if i < 0:
            return 0, 1
        if i == len(bits) - 1:
            self._cmd_tx = None
            self._line_free_since = now + 1      # the edge at which the host samples it
            self._line_free_after_response = True
        return 1, bits[i]

    def _command(self, now: int, bits: list[int]) -> None:
        """A 48-bit frame has been received; its end bit is at edge ``now``."""
        first = self._commands_seen == 0
        self._commands_seen += 1
        self._line_free_since = now
        self._line_free_after_response = False
        index = _value(bits[2:8])
        argument = _value(bits[8:40])
        app, self._app = self._app, False
        is_acmd = app and index in _ACMD_INDICES and not (
            index == AppCommand.SET_WR_BLK_ERASE_COUNT and not self.acmd23)
        name = f"{'ACMD' if is_acmd else 'CMD'}{index}"

        def ignore(note):
            self.log.append(Transaction(now, name, argument, Response.NONE, None, note))

        if first and self._rx_start < arch.INIT_CLOCKS:
            return ignore("before the initialisation clocks")
        if self.inactive:
            return ignore("card inactive")
        if bits[1] != 1:
            self._error(now, f"{name}: transmission bit is 0 (a response, not a command)")
            return ignore("transmission bit 0")
        expected = crc7(bits[:arch.CMD_CRC_LAST])
        received = _value(bits[arch.CMD_CRC_LAST:arch.CMD_CRC_LAST + arch.CRC7_BITS])
        if received != expected:
            self._pending |= CardStatus.COM_CRC_ERROR
            self._error(now, f"{name} (argument 0x{argument:08X}): CRC7 0x{received:02X}, "
                             f"expected 0x{expected:02X}")
            return ignore("bad CRC7")
        if bits[-1] != 1:
            self._pending |= CardStatus.COM_CRC_ERROR
            self._error(now, f"{name}: end bit is 0")
            return ignore("end bit 0")

        if not self.illegal_kept:
            self._pending &= ~CardStatus.ILLEGAL_COMMAND    # cleared, never reported
        state_before = self.state
        delay = arch.N_ID if (index == Command.ALL_SEND_CID or
                              (is_acmd and index == AppCommand.SD_SEND_OP_COND)) \
            else self._timing_rng.randint(*self._n_cr)
        self._response_end = now + delay + arch.CMD_BITS    # edge the host samples its end bit
        try:
            if is_acmd:
                reply = self._app_command(now, index, argument)
            else:
                reply = self._basic_command(now, index, argument, app)
        except _Unsupported as lacking:
            self._pending |= CardStatus.ILLEGAL_COMMAND
            return ignore(f"illegal: {lacking}")
        except _Illegal as illegal:
            self._pending |= CardStatus.ILLEGAL_COMMAND
            busy = " while the card is busy" if self._busy else ""
            self._error(now, f"{name} (argument 0x{argument:08X}) illegal in state "
                             f"{state_before.name.lower()}{busy}: {illegal}")
            return ignore(f"illegal: {illegal}")
        except _NotAddressed as other:
            self._error(now, f"{name} {other}: ignored")
            return ignore(str(other))
        if reply.response is Response.NONE:
            self.log.append(Transaction(now, name, argument, Response.NONE, None, reply.note))
            return
        if reply.response in (Response.R1, Response.R1B):
            reply.value = self._status(state_before, CardStatus(reply.value), app=is_acmd or
                                       index == Command.APP_CMD)
        elif reply.response is Response.R6:
            reply.value |= self._r6_status(state_before)
        frame, corrupted = self._frame(index, reply)
        self._cmd_tx = (now + delay, frame)
        self._cmd_turnaround_reported = False
        note = reply.note + (" [CRC7 corrupted by fault]" if corrupted else "")
        self.log.append(Transaction(now, name, argument, reply.response, reply.value,
                                    note.strip()))

    def _status(self, state_before: CardState, extra: CardStatus, *, app: bool) -> int:
        """The 32-bit card status of an R1, clearing the flags it reports (conditions B, C)."""
        flags = self._pending | extra
        self._pending = CardStatus(0)
        if app:
            flags |= CardStatus.APP_CMD
        if not self._busy:
            flags |= CardStatus.READY_FOR_DATA
        return int(flags) | (int(state_before) << arch.STATUS_STATE_SHIFT)

    def _r6_status(self, state_before: CardState) -> int:
        """R6's 16 status bits: card status bits 23, 22, 19 and 12..0 (PLSS §4.9.5)."""
        full = int(self._pending) | (int(state_before) << arch.STATUS_STATE_SHIFT)
        if not self._busy:
            full |= CardStatus.READY_FOR_DATA
        value = full & arch.R6_STATUS_LOW_MASK
        reported = CardStatus(0)
        for status_bit, r6_bit in arch.R6_STATUS_HIGH_BITS:
            if full >> status_bit & 1:
                value |= 1 << r6_bit
                reported |= CardStatus(1 << status_bit)
        self._pending &= ~reported
        return value

    def _frame(self, index: int, reply: _Reply) -> tuple[list[int], bool]:
        """The response's bits on CMD and whether a fault corrupted its CRC7."""
        corrupt = False
        if reply.response is not Response.R3:
            corrupt = self._responses_with_crc == self.faults.corrupt_response_crc
            self._responses_with_crc += 1
        if reply.response is Response.R2:
            register = reply.value
            if corrupt:
                register ^= 1 << 1                      # lowest bit of the register's CRC7
            return [0, 0] + _bits(arch.RESPONSE_INDEX_ONES, 6) + _bits(register, 128), corrupt
        if reply.response is Response.R3:
            head = [0, 0] + _bits(arch.RESPONSE_INDEX_ONES, 6) + _bits(reply.value, 32)
            return head + _bits(arch.R3_CRC_ONES, arch.CRC7_BITS) + [1], False
        head = [0, 0] + _bits(index, 6) + _bits(reply.value, 32)
        crc = crc7(head) ^ (1 if corrupt else 0)
        return head + _bits(crc, arch.CRC7_BITS) + [1], corrupt

    # -- commands ------------------------------------------------------------------------------

    def _check_rca(self, argument: int) -> None:
        rca = argument >> _RCA_SHIFT
        if rca != self.rca:
            raise _NotAddressed(f"addressed to RCA 0x{rca:04X}, card has 0x{self.rca:04X}")

    def _require(self, *states: CardState) -> None:
        if self.state not in states:
            raise _Illegal(f"allowed in {', '.join(s.name.lower() for s in states)}")

    def _basic_command(self, now: int, index: int, argument: int, app: bool) -> _Reply:
        state = self.state
        if index == Command.GO_IDLE_STATE:
            if self._op is not None or self._busy:
                self.log.append(BlockEvent(now, "write" if state in (CardState.RCV,
                                CardState.PRG, CardState.DIS) else "read", None,
                                "aborted by CMD0"))
            self._reset()
            return _Reply(Response.NONE, note="reset")

        if index == Command.SEND_IF_COND:
            if self.version == 1:
                raise _Unsupported("a Ver1.X card has no CMD8")
            self._require(CardState.IDLE)
            vhs = (argument & arch.IF_COND_VHS_MASK) >> arch.IF_COND_VHS_SHIFT
            if vhs != arch.IF_COND_VHS_2V7_3V6:
                return _Reply(Response.NONE, note=f"VHS {vhs:04b} not supported: no response")
            self._if_cond = True
            echo = argument & (arch.IF_COND_VHS_MASK | arch.IF_COND_PATTERN_MASK)
            return _Reply(Response.R7, echo)

        if index == Command.ALL_SEND_CID:
            self._require(CardState.READY)
            self.state = CardState.IDENT
            return _Reply(Response.R2, self.cid, "CID")

        if index == Command.SEND_RELATIVE_ADDR:
            self._require(CardState.IDENT, CardState.STBY)
            self.rca = self._fixed_rca or self._id_rng.randint(1, _RCA_MASK)
            self.state = CardState.STBY
            return _Reply(Response.R6, self.rca << _RCA_SHIFT, f"RCA 0x{self.rca:04X}")

        if index == Command.SELECT_CARD:
            return self._select(now, argument)

        if index in (Command.SEND_CSD, Command.SEND_CID):
            self._require(*_ADDRESSED_STATES)
            self._check_rca(argument)
            self._require(CardState.STBY)
            if index == Command.SEND_CSD:
                return _Reply(Response.R2, self.csd, "CSD")
            return _Reply(Response.R2, self.cid, "CID")

        if index == Command.STOP_TRANSMISSION:
            self._require(CardState.DATA, CardState.RCV)
            self._stop_at = now + arch.N_ST
            self._stop_busy_from = self._response_end
            self.state = CardState.TRAN if state is CardState.DATA else CardState.PRG
            return _Reply(Response.R1B)

        if index == Command.SEND_STATUS:
            if not self.cmd13:
                return _Reply(Response.NONE, note="this card does not answer CMD13")
            self._require(*_ADDRESSED_STATES)
            self._check_rca(argument)
            return _Reply(Response.R1)

        if index == Command.GO_INACTIVE_STATE:
            self._require(*_ADDRESSED_STATES)
            self._check_rca(argument)
            self._reset()
            self.inactive = True
            return _Reply(Response.NONE, note="inactive")

        if index == Command.SET_BLOCKLEN:
            self._require(CardState.TRAN)
            # SDHC: reads and writes always use 512-byte blocks; CMD16 only sets the length
            # of CMD42's block. SDSC: it sets the length of reads and writes. Either way it
            # may not exceed 512 (PLSS Table 4-22, §4.3.2, §4.10.1).
            if not 1 <= argument <= arch.BLOCK_BYTES:
                return _Reply(Response.R1, CardStatus.BLOCK_LEN_ERROR)
            if not self.high_capacity:
                self.block_length = argument
            return _Reply(Response.R1, note=f"block length {argument}")

        if index in (Command.READ_SINGLE_BLOCK, Command.READ_MULTIPLE_BLOCK):
            self._require(CardState.TRAN)
            lba, error = self._address(now, argument)
            if error is not None:
                return error
            multi = index == Command.READ_MULTIPLE_BLOCK
            self._start_op(self._op_send(now, self._read_blocks(lba, multi), lba=lba),
                           CardState.DATA)
            return _Reply(Response.R1, note=f"LBA {lba}")

        if index in (Command.WRITE_BLOCK, Command.WRITE_MULTIPLE_BLOCK):
            self._require(CardState.TRAN)
            lba, error = self._address(now, argument)
            if error is not None:
                return error
            argument = lba
            multi = index == Command.WRITE_MULTIPLE_BLOCK
            note = f"LBA {argument}"
            if multi and self.pre_erase_count is not None:
                note += f", pre-erase count {self.pre_erase_count}"
                self.pre_erase_count = None        # ACMD23 applies to the next CMD25 only
            count = None
            if multi and self.block_count is not None:
                count, self.block_count = self.block_count, None
                note += f", block count {count}"
            self._well_written = 0
            ready = self._response_end + arch.N_WR + 1
            self._start_op(self._op_receive(argument, multi, ready, count), CardState.RCV)
            return _Reply(Response.R1, note=note)

        if index == Command.SET_BLOCK_COUNT:
            if not self.cmd23:
                if app:     # meant as ACMD23, which this card does not define either
                    raise _Unsupported("this card has neither ACMD23 nor CMD23")
                raise _Illegal("this card has no CMD23 (SCR CMD_SUPPORT)")
            self._require(CardState.TRAN)
            self.block_count = argument & 0xFFFF
            return _Reply(Response.R1, note=f"block count {self.block_count}")

        if index == Command.APP_CMD:
            self._require(CardState.IDLE, *_ADDRESSED_STATES)
            self._check_rca(argument)
            self._app = True
            return _Reply(Response.R1)

        known = index in _COMMAND_INDICES
        raise _Illegal("not implemented by the card model" if known else "unknown command")

    def _address(self, now: int, argument: int) -> tuple[int, _Reply | None]:
        """The block a data command's argument names, or the R1 that rejects it (no data
        transfer follows, PLSS §4.3.3): block addresses on SDHC, byte addresses on SDSC."""
        if self.high_capacity:
            lba, where = argument, f"LBA {argument}"
        else:
            lba, where = argument // arch.BLOCK_BYTES, f"byte address 0x{argument:08X}"
            if self.block_length != arch.BLOCK_BYTES:
                self._error(now, f"block length {self.block_length}: the card model transfers "
                                 f"only {arch.BLOCK_BYTES}-byte blocks")
                return lba, _Reply(Response.R1, CardStatus.BLOCK_LEN_ERROR,
                                   f"block length {self.block_length}")
        if lba >= self.capacity_blocks:
            return lba, _Reply(Response.R1, CardStatus.OUT_OF_RANGE,
                               f"{where} beyond {self.capacity_blocks} blocks")
        if argument % arch.BLOCK_BYTES and not self.high_capacity:
            # READ_BL_MISALIGN = WRITE_BLK_MISALIGN = 0: a 512-byte block must not cross a
            # physical block boundary (PLSS Tables 4-23, 4-24, note 1).
            return lba, _Reply(Response.R1, CardStatus.ADDRESS_ERROR,
                               f"{where} not a multiple of {arch.BLOCK_BYTES}")
        return lba, None

    def _select(self, now: int, argument: int) -> _Reply:
        """CMD7 (PLSS §4.8): its own RCA selects, any other RCA deselects; only the selected
        card answers."""
        state = self.state
        rca = argument >> _RCA_SHIFT
        if rca == self.rca and rca != 0:
            if state is CardState.STBY:
                self.state = CardState.TRAN
            elif state is CardState.DIS:
                self.state = CardState.PRG         # busy shows on DAT0 again
            else:
                raise _Illegal("a selected card cannot be selected again")
            return _Reply(Response.R1B, note="select")
        if state in (CardState.STBY, CardState.DIS):
            return _Reply(Response.NONE, note="not addressed")
        if state in (CardState.TRAN, CardState.DATA):
            if state is CardState.DATA:
                self._stop_at = now + arch.N_ST
            self.state = CardState.STBY
            return _Reply(Response.NONE, note="deselect")
        if state is CardState.PRG:
            self.state = CardState.DIS
            return _Reply(Response.NONE, note="deselect while programming")
        raise _Illegal("allowed in stby, tran, data, prg, dis")

    def _app_command(self, now: int, index: int, argument: int) -> _Reply:
        if index == AppCommand.SD_SEND_OP_COND:
            return self._send_op_cond(now, argument)
        self._require(CardState.TRAN)
        if index == AppCommand.SET_BUS_WIDTH:
            width = argument & 0b11
            if width == arch.BUS_WIDTH_1:
                self.bus_width = 1
            elif width == arch.BUS_WIDTH_4:
                self.bus_width = 4
            else:
                self._error(now, f"ACMD6 with reserved bus width code {width:02b}")
                return _Reply(Response.R1, CardStatus.ERROR, "reserved width")
            return _Reply(Response.R1, note=f"{self.bus_width}-bit bus")
        if index == AppCommand.SET_WR_BLK_ERASE_COUNT:
            self.pre_erase_count = argument & arch.PRE_ERASE_COUNT_MASK
            return _Reply(Response.R1, note=f"pre-erase count {self.pre_erase_count}")
        if index == AppCommand.SET_CLR_CARD_DETECT:
            return _Reply(Response.R1, note=f"DAT3 pull-up {'on' if argument & 1 else 'off'}")
        if index == AppCommand.SEND_SCR:
            payload = self._make_scr()
        elif index == AppCommand.SD_STATUS:
            payload = self._make_sd_status()
        elif index == AppCommand.SEND_NUM_WR_BLOCKS:
            payload = self._well_written.to_bytes(4, "big")
        else:
            raise _Illegal("not implemented by the card model")
        self._start_op(self._op_send(now, [payload], lba=None), CardState.DATA)
        return _Reply(Response.R1, note=f"{len(payload)}-byte register read")

    def _send_op_cond(self, now: int, argument: int) -> _Reply:
        """ACMD41 (PLSS §4.2.3): inquiry, or initialisation until the card reports ready."""
        self._require(CardState.IDLE)
        window = argument & arch.OCR_VOLTAGE_WINDOW
        if argument & 0xFFFFFF and not window:
            self._reset()
            self.inactive = True
            self._error(now, f"ACMD41 voltage window 0x{argument & 0xFFFFFF:06X} outside "
                             f"2.7..3.6 V: the card goes inactive")
            return _Reply(Response.NONE, note="voltage mismatch: inactive")
        note = "inquiry"
        if window:
            if (argument & arch.ACMD41_HCS and not self._if_cond and not self._hcs_reported
                    and not self.high_capacity):
                # PLSS §4.2.3.1 / Figure 4-2: after no answer to CMD8 the host sends HCS = 0.
                self._hcs_reported = True
                self._error(now, "ACMD41 with HCS after CMD8 went unanswered (HCS must be 0)")
            if self.high_capacity and not (self._if_cond and argument & arch.ACMD41_HCS):
                if not self._hcs_reported:
                    self._hcs_reported = True
                    self._error(now, "ACMD41 without HCS or without a CMD8 first: an SDHC "
                                     "card never becomes ready")
                note = "busy (no HCS)"
            else:
                if self._acmd41_left is None:
                    self._acmd41_left = self._id_rng.randint(*self._acmd41_range)
                if self._acmd41_left > 0:
                    self._acmd41_left -= 1
                    note = "busy"
                else:
                    self.ocr_ready = True
                    self.state = CardState.READY
                    note = "ready"
        ocr = arch.OCR_VOLTAGE_WINDOW
        if self.ocr_ready:
            ocr |= arch.OCR_POWER_UP_DONE | (arch.OCR_CCS if self.ocr_ccs else 0)
        return _Reply(Response.R3, ocr, note)

    # -- registers -----------------------------------------------------------------------------

    def _make_cid(self) -> int:
        """CID register (PLSS §5.2) with its CRC7 in bits 7..1 and bit 0 = 1."""
        fields = [
            (8, 0x4D),                                  # MID (not an assigned one)
            (16, int.from_bytes(b"ML", "big")),         # OID
            (40, int.from_bytes(b"MAGLG", "big")),      # PNM
            (8, 0x10),                                  # PRV 1.0
            (32, self._id_rng.getrandbits(32)),            # PSN
            (4, 0),                                     # reserved
            (12, (26 << 4) | 1),                        # MDT: 2026-01
        ]
        return _register_with_crc(fields)

    def _make_csd(self) -> int:
        """CSD version 2.0 (PLSS §5.3.3): capacity = (C_SIZE + 1) × 512 KiB; for SDSC,
        version 1.0 (PLSS §5.3.2)."""
        if not self.high_capacity:
            return self._make_csd_v1()
        c_size = max(self.capacity_blocks // 1024, 1) - 1
        fields = [
            (2, 0b01), (6, 0),                          # CSD_STRUCTURE 2.0
            (8, 0x0E), (8, 0x00),                       # TAAC 1 ms, NSAC
            (8, 0x32),                                  # TRAN_SPEED 25 MHz
            (12, 0x5B5), (4, 9),                        # CCC, READ_BL_LEN 512
            (1, 0), (1, 0), (1, 0), (1, 0),             # partial/misalign, DSR_IMP
            (6, 0), (22, c_size), (1, 0),               # C_SIZE
            (1, 1), (7, 0x7F), (7, 0),                  # ERASE_BLK_EN, SECTOR_SIZE, WP_GRP
            (1, 0), (2, 0), (3, 0b010), (4, 9), (1, 0), (5, 0),     # R2W_FACTOR, WRITE_BL_LEN
            (1, 0), (1, 0), (1, 0), (1, 0), (2, 0), (2, 0),         # file format, protection
        ]
        return _register_with_crc(fields)

    def _make_csd_v1(self) -> int:
        """CSD version 1.0 (PLSS §5.3.2): capacity = (C_SIZE + 1) × 2^(C_SIZE_MULT + 2) ×
        2^READ_BL_LEN bytes; READ_BL_LEN = WRITE_BL_LEN (1024 bytes only for a card above
        1 GB, §4.3.2), partial reads allowed (always, in SD), no misaligned blocks."""
        v1 = self._csd_v1
        fields = [
            (2, 0b00), (6, 0),                          # CSD_STRUCTURE 1.0
            (8, 0x26), (8, 0x00),                       # TAAC 1.5 ms, NSAC
            (8, 0x32),                                  # TRAN_SPEED 25 MHz
            (12, 0x5B5), (4, v1["read_bl_len"]),        # CCC, READ_BL_LEN
            (1, 1), (1, 0), (1, 0), (1, 0),             # READ_BL_PARTIAL, misalign, DSR_IMP
            (2, 0), (12, v1["c_size"]),                 # C_SIZE
            (3, 0b111), (3, 0b110), (3, 0b111), (3, 0b110),         # VDD currents
            (3, v1["c_size_mult"]),                     # C_SIZE_MULT
            (1, 1), (7, 0x7F), (7, 0),                  # ERASE_BLK_EN, SECTOR_SIZE, WP_GRP
            (1, 0), (2, 0), (3, 0b010), (4, v1["read_bl_len"]), (1, 0), (5, 0),
            (1, 0), (1, 0), (1, 0), (1, 0), (2, 0), (2, 0),         # file format, protection
        ]
        return _register_with_crc(fields)

    def _make_scr(self) -> bytes:
        """SCR (PLSS §5.6): spec 3.0x (1.0 for a Ver1.X card), SDHC or SDSC security, 1- and
        4-bit bus."""
        spec, spec3 = (2, 1) if self.version == 2 else (0, 0)
        security = 3 if self.high_capacity else 2
        value = ((0 << 60) | (spec << 56) | (0 << 55) | (security << 52) | (0b0101 << 48)
                 | (spec3 << 47) | (int(self.cmd23) << 33))
        return value.to_bytes(8, "big")

    def _make_sd_status(self) -> bytes:
        """SD Status (PLSS §4.10.2), 64 bytes: bus width in bits 511..510, the rest zero
        but the speed class (Class 10)."""
        value = (0b10 if self.bus_width == 4 else 0b00) << 510
        value |= 0x04 << 440
        return value.to_bytes(64, "big")

    # -- DAT lines -----------------------------------------------------------------------------

    def _start_op(self, op: Generator, state: CardState) -> None:
        if self._op is not None:
            self._op.close()
        self._stop_at = None
        self.state = state
        next(op)
        self._op = op

    def _dat_step(self, now: int, dat: int) -> tuple[int, int]:
        op = self._op
        if op is None:
            self._check_idle_dat(now, dat)
            return 0, _ALL_LINES
        try:
            return op.send((now, dat))
        except StopIteration:
            self._op = None
            return 0, _ALL_LINES

    def _lines(self) -> int:
        return _ALL_LINES if self.bus_width == 4 else _DAT0

    def _check_idle_dat(self, now: int, dat: int) -> None:
        """Nobody should drive the DAT lines low when no transfer is under way."""
        host_low = ~dat & self._lines() & ~self._prev_dat_oe
        if host_low and not self._dat_activity_reported and self._commands_seen:
            self._dat_activity_reported = True
            self._error(now, f"DAT lines {host_low:04b} driven low with no data transfer "
                             f"under way (state {self.state.name.lower()})")
        elif not host_low:
            self._dat_activity_reported = False

    def _read_blocks(self, lba: int, multi: bool) -> Iterator[bytes | None]:
        while True:
            yield self.image.read_block(lba) if lba < self.capacity_blocks else None
            if not multi:
                return
            lba += 1

    def _data_packet(self, payload: bytes) -> tuple[list[int], int]:
        """Start bit, data, CRC16 per line and end bit, as DAT values; and the line mask."""
        if self.bus_width == 4:
            nibbles = []
            for byte in payload:
                nibbles += (byte >> 4, byte & 0xF)
            crcs = [crc16([(n >> line) & 1 for n in nibbles]) for line in range(4)]
            crc_nibbles = [sum(((crcs[line] >> (15 - i)) & 1) << line for line in range(4))
                           for i in range(arch.CRC16_BITS)]
            return [0] + nibbles + crc_nibbles + [_ALL_LINES], _ALL_LINES
        bits = [(byte >> (7 - k)) & 1 for byte in payload for k in range(8)]
        packet = [0] + bits + _bits(crc16(bits), arch.CRC16_BITS) + [1]
        return [_DAT0_LOW | bit for bit in packet], _DAT0

    def _op_send(self, now: int, payloads: Iterable[bytes | None], *, lba: int | None):
        """Read data (CMD17, CMD18, register reads): blocks N_AC after the command, then
        every 2 clocks until the last one or CMD12 (which stops the data N_ST clocks after
        its end bit, with an end bit on every line)."""
        if self._n_ac is None:
            start = self._response_end + arch.N_AC_MIN      # edge that returns the start bit
        else:
            start = now + self._n_ac
        now, dat = yield
        past_end = False
        for payload in payloads:
            if payload is None:
                self._pending |= CardStatus.OUT_OF_RANGE     # CMD18 ran past the last block
                self.log.append(BlockEvent(now, "read", lba, "out of range"))
                past_end = True
                break
            packet, mask = self._data_packet(payload)
            while now < start:
                if self._stop_at is not None:
                    return self._read_done(now, lba, "stopped")
                now, dat = yield 0, _ALL_LINES
            for value in packet:
                if self._stop_at is not None and now >= self._stop_at:
                    now, dat = yield mask, _ALL_LINES      # end bit, then release
                    return self._read_done(now, lba, "stopped")
                now, dat = yield mask, value
            self.log.append(BlockEvent(now - 1, "read", lba, "sent"))
            if lba is not None:
                lba += 1
            start = now + arch.N_AC_MIN
        while past_end and self._stop_at is None and self.state is CardState.DATA:
            now, dat = yield 0, _ALL_LINES                # past the end: wait for CMD12
        self._read_done(now, lba, None)

    def _read_done(self, now: int, lba, outcome: str | None) -> None:
        if outcome is not None:
            self.log.append(BlockEvent(now, "read", lba, outcome))
        if self.state is CardState.DATA:
            self.state = CardState.TRAN

    def _op_receive(self, lba: int, multi: bool, ready: int, count: int | None = None):
        """Write data (CMD24, CMD25): receive blocks, answer each with a CRC status token and
        a busy, store accepted blocks; end after one block (CMD24) or at CMD12 (CMD25).

        ``ready`` is the first edge at which a start bit respects N_WR; ``count`` (CMD23)
        ends a CMD25 after so many blocks are stored.
        """
        now, dat = yield
        ignoring = False          # after a rejected block of a CMD25: wait for CMD12
        ignoring_reported = False
        while True:
            # Waiting for a start bit (or for CMD12).
            while True:
                if self._stop_at is not None:
                    yield from self._final_busy(now, dat)
                    return
                low = ~dat & _ALL_LINES & ~self._prev_dat_oe
                if ignoring:
                    if low and not ignoring_reported:
                        ignoring_reported = True
                        self._error(now, "data sent after a rejected block; the card ignores "
                                         "it until CMD12")
                elif low & _DAT0:
                    break
                now, dat = yield 0, _ALL_LINES
            self._check_start_bit(now, dat, ready)
            block = self.blocks_received
            self.blocks_received += 1
            four = self.bus_width == 4
            units = arch.DATA_NIBBLES if four else _DATA_BITS_1BIT
            samples = []
            for _ in range(units + arch.CRC16_BITS + 1):
                now, dat = yield 0, _ALL_LINES
                if self._stop_at is not None:
                    self.log.append(BlockEvent(now, "write", lba, "partial block discarded"))
                    yield from self._final_busy(now, dat)
                    return
                samples.append(dat if four else dat & _DAT0)
            outcome, data = self._check_block(now, block, samples, units)
            if self.faults.withhold_token == block:
                self.log.append(BlockEvent(now, "write", lba, "token withheld"))
                if not multi:
                    self.state = CardState.TRAN
                    return
                ignoring = True
                now, dat = yield 0, _ALL_LINES
                continue
            # N_CRC released clocks, then the token on DAT0.
            for _ in range(arch.N_CRC):
                now, dat = yield 0, _ALL_LINES
            if outcome == "stored" and lba >= self.capacity_blocks:
                outcome = "out of range"
                self._pending |= CardStatus.OUT_OF_RANGE
            token = {"stored": arch.TOKEN_ACCEPTED, "crc error": arch.TOKEN_CRC_ERROR,
                     "out of range": arch.TOKEN_WRITE_ERROR}[outcome]
            self._busy = True
            for bit in [0] + _bits(token, arch.TOKEN_STATUS_BITS) + [1]:
                now, dat = yield _DAT0, _DAT0_LOW | bit
                self._check_dat_while_busy(now, dat)
            if outcome != "stored":
                self._busy = False
                self.log.append(BlockEvent(now, "write", lba, outcome))
                if not multi or self._stop_at is not None:
                    self.state = CardState.TRAN
                    return
                ignoring = True
                continue
            if self.state is CardState.RCV and not multi:
                self.state = CardState.PRG
            for _ in range(self.busy_start_delay):
                now, dat = yield 0, _ALL_LINES
                self._check_dat_while_busy(now, dat)
            if self.faults.busy_past_timeout == block:
                clocks = self.faults.busy_past_timeout_clocks
            else:
                clocks = self._busy_rng.randint(*self._busy_range)
            for _ in range(clocks):
                now, dat = yield _DAT0, _DAT0_LOW
                self._check_dat_while_busy(now, dat)
            # Programming done: store, show DAT0 high for one clock, release.
            self.image.write_block(lba, data)
            self.blocks_stored += 1
            self._well_written += 1
            self._busy = False
            self.log.append(BlockEvent(now, "write", lba, "stored"))
            done = (not multi or self._stop_at is not None
                    or (count is not None and self._well_written == count))
            if done:
                self._end_programming()
            now, dat = yield _DAT0, _ALL_LINES
            if done:
                return
            lba += 1
            ready = now + arch.N_WR

    def _check_start_bit(self, now: int, dat: int, ready: int) -> None:
        if now < ready:
            self._error(now, f"data start bit {arch.N_WR - (ready - now)} clocks after the "
                             f"response or busy; N_WR is at least {arch.N_WR}")
        if self.bus_width == 4 and dat & _ALL_LINES:
            self._error(now, f"data start bit on DAT0 but not on every line (DAT {dat:04b})")
        elif self.bus_width == 1 and dat & 0b1110 != 0b1110:
            self._error(now, f"start bit on DAT lines {~dat & 0b1110:04b} while the bus is 1 bit "
                             f"wide (ACMD6 not sent?)")

    def _check_block(self, now: int, block: int, samples: list[int], units: int):
        """Apply the bit-flip fault, check the CRC16 of every line and the end bit."""
        lines = 4 if self.bus_width == 4 else 1
        if self.faults.flip_dat_bit == block:
            line = self.faults.flip_line if lines == 4 else 0
            position = self.faults.flip_position
            if position is None:
                position = self._fault_rng.randrange(units)
            if position >= units:
                raise ValueError(f"Fault flip_position must be below {units}, not {position}")
            samples[position] ^= 1 << line
        ok = True
        for line in range(lines):
            data_bits = [(s >> line) & 1 for s in samples[:units]]
            received = _value((s >> line) & 1 for s in samples[units:units + arch.CRC16_BITS])
            if crc16(data_bits) != received:
                ok = False
        end = samples[-1]
        if end != (1 << lines) - 1:
            ok = False
            self._error(now, f"data block end bit missing (DAT {end:04b})")
        if lines == 4:
            data = bytes((samples[2 * i] << 4) | samples[2 * i + 1]
                         for i in range(arch.BLOCK_BYTES))
        else:
            data = bytes(_value(samples[8 * i:8 * i + 8]) for i in range(arch.BLOCK_BYTES))
        return ("stored" if ok else "crc error"), data

    def _check_dat_while_busy(self, now: int, dat: int) -> None:
        host_low = ~dat & self._lines() & ~_DAT0
        if host_low and not self._dat_activity_reported:
            self._dat_activity_reported = True
            self._error(now, f"DAT lines {host_low:04b} driven low while the card sends its "
                             f"CRC status or is busy")

    def _final_busy(self, now: int, dat: int):
        """After CMD12 in a write: busy from the end of the R1b until programming is done."""
        self._busy = True
        while now < self._stop_busy_from + self.busy_start_delay:
            now, dat = yield 0, _ALL_LINES
        for _ in range(self._busy_rng.randint(*self._busy_range)):
            now, dat = yield _DAT0, _DAT0_LOW
            self._check_dat_while_busy(now, dat)
        self._busy = False
        self._end_programming()
        yield _DAT0, _ALL_LINES

    def _end_programming(self) -> None:
        if self.state in (CardState.PRG, CardState.RCV):
            self.state = CardState.TRAN
        elif self.state is CardState.DIS:
            self.state = CardState.STBY


class SdBus:
    """The CMD and DAT lines between a host's pins and a card: written once for every
    simulator adapter (Amaranth, cocotb), so that they resolve the bus alike.

    At each rising edge of the SD clock the adapter calls :meth:`rising_edge` with what the
    host drives; the card (anything with ``edge`` and ``report`` as :class:`SdCard` has them)
    sees the bus levels: the host's drive, the card's own, or the pull-up's 1. The levels the
    host reads back until the next rising edge are returned; an adapter applies them after
    the falling edge, where a default-speed card changes its outputs. A line driven by both
    sides is reported to the card as a protocol error.
    """

    def __init__(self, card):
        self.card = card
        self._cmd_oe, self._cmd, self._dat_oe, self._dat = _RELEASED

    def _card_dat(self) -> int:
        return (self._dat & self._dat_oe) | (_ALL_LINES & ~self._dat_oe)

    def rising_edge(self, host_cmd_oe: int, host_cmd: int, host_dat_oe: int,
                    host_dat: int) -> tuple[int, int]:
        """The host's CMD and DAT outputs and enables at this edge → (cmd, dat) levels the
        host sees until the next one."""
        if host_cmd_oe and self._cmd_oe:
            self.card.report("bus contention on CMD")
        if host_dat_oe and self._dat_oe:
            self.card.report("bus contention on DAT")
        cmd = host_cmd if host_cmd_oe else (self._cmd if self._cmd_oe else 1)
        dat = host_dat if host_dat_oe else self._card_dat()
        self._cmd_oe, self._cmd, self._dat_oe, self._dat = self.card.edge(cmd, dat)
        return (self._cmd if self._cmd_oe else 1), self._card_dat()


def _check_range(what: str, value, low: int, high: int | None) -> tuple[int, int]:
    if isinstance(value, int) and not isinstance(value, bool):
        value = (value, value)
    ok = (isinstance(value, tuple) and len(value) == 2
          and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
          and low <= value[0] <= value[1] and (high is None or value[1] <= high))
    if not ok:
        bound = f"{low}..{high}" if high is not None else f"at least {low}"
        raise ValueError(f"{what} must be an integer or an inclusive (low, high) range, "
                         f"{bound}, not {value!r}")
    return value


def _csd_v1_fields(capacity_blocks: int) -> dict:
    """C_SIZE, C_SIZE_MULT and READ_BL_LEN of the largest CSD 1.0 capacity up to
    ``capacity_blocks`` 512-byte blocks, and that capacity in blocks ("blocks")."""
    best = None
    for read_bl_len in (9, 10):                 # 512 bytes; 1024 only for 2 GB (§4.3.2)
        for c_size_mult in range(7, -1, -1):
            unit = (1 << (c_size_mult + 2)) << (read_bl_len - 9)    # 512-byte blocks
            c_size = min(capacity_blocks // unit, 1 << 12) - 1
            if c_size < 0:
                continue
            blocks = (c_size + 1) * unit
            if best is None or blocks > best["blocks"]:
                best = dict(read_bl_len=read_bl_len, c_size_mult=c_size_mult, c_size=c_size,
                            blocks=blocks)
    if best is None:
        raise ValueError(f"A CSD 1.0 card holds at least 4 blocks, not {capacity_blocks!r}")
    return best


def _register_with_crc(fields: list[tuple[int, int]]) -> int:
    """A 128-bit CID/CSD: fields for bits 127..8, then CRC7 over them, then bit 0 = 1."""
    value = 0
    width = 0
    for bits, field in fields:
        assert 0 <= field < 1 << bits, (bits, field)
        value = (value << bits) | field
        width += bits
    assert width == 120, width
    return (value << 8) | (crc7(_bits(value, 120)) << 1) | 1
