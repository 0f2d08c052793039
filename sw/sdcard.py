"""SD card driver: identification, 4-bit mode, block reads and (multi-)block writes.

Runs on any backend through :class:`~maglog.sw.bus.RegisterBus` and
:class:`~maglog.sw.bus.BlockPort`; register addresses and fields come from the host's memory
map (:class:`~maglog.sw.regmap.RegisterMap`). Every failure ends in an :class:`SdError`
subclass that says what happened; a write is reported as done only when the card accepted
every block, and the number of blocks accepted is always known.
"""

from dataclasses import dataclass

from ..hw.arch import sd as arch
from ..hw.arch.sd import DataPhase, ResponseKind
from ..hw.arch.units import hertz
from .bus import BusTimeout


__all__ = ["SdError", "SdTimeout", "SdCrcError", "SdCardError", "SdWriteError", "SdNoCard",
           "SdCardDriver", "CardInfo"]


class SdError(Exception):
    """An SD card operation failed."""


class SdNoCard(SdError):
    """No card answers."""


class SdTimeout(SdError):
    """The card did not answer, send data, or leave busy in time."""


class SdCrcError(SdError):
    """A CRC did not match (response or read data) after every retry."""


class SdCardError(SdError):
    """The card reported an error in its status, or answered out of line."""


class SdWriteError(SdError):
    """A block write failed; ``accepted`` blocks were written before it."""
    def __init__(self, message, accepted):
        super().__init__(message)
        self.accepted = accepted


#: Response type of each command the driver sends, to the CMD engine's kind.
_KIND = {
    arch.Response.NONE: ResponseKind.NONE,
    arch.Response.R1: ResponseKind.SHORT, arch.Response.R1B: ResponseKind.SHORT,
    arch.Response.R6: ResponseKind.SHORT, arch.Response.R7: ResponseKind.SHORT,
    arch.Response.R3: ResponseKind.OCR, arch.Response.R2: ResponseKind.LONG,
}

CMD_RETRIES = 3
WRITE_RETRIES = 2

# Margins over the PLSS's timing minimums (§4.12.4, §6.4.1.1). The spec bounds these gaps
# from below only (or, for N_CR, bounds the card's side from above), so a host may give
# more; cards and card emulators that are slow to turn the line round then still work.
#: Clocks before the first command (PLSS §6.4.1.1: at least 74): twice the minimum.
INIT_CLOCKS_SENT = 2 * arch.INIT_CLOCKS
#: Clocks the driver adds between commands on top of the host's own N_CC gap (the CMD
#: engine stays busy exactly N_CC = N_RC = 8 clocks, the minimum, after a response or a
#: command without one): at least 16 clocks from one command or response to the next.
COMMAND_GAP_EXTRA_CLOCKS = arch.N_CC
#: How long the host waits for a response's start bit (its ``timeouts.response`` setting,
#: N_CR_MAX = 64 clocks at reset): twice the latest a card may answer.
RESPONSE_TIMEOUT_CLOCKS = 2 * arch.N_CR_MAX
#: After a failed write the card may still program (prg) the block whose busy outlasted the
#: host's timeout; it is polled with CMD13 (legal in prg) until it is back in tran for this
#: long, twice the write timeout of PLSS §4.6.2.2 (250 ms), before the write is given up.
RECOVER_LIMIT_S = 0.5
#: Time between two CMD13 polls while waiting for tran.
RECOVER_POLL_S = 100e-6
#: Card status bits that mean this command (or its data) failed. COM_CRC_ERROR and
#: ILLEGAL_COMMAND are about the previous command (PLSS §4.10.1, clear condition B): a
#: command the card did not take got no response, which the driver has already seen.
STATUS_ERRORS = (arch.CardStatus.OUT_OF_RANGE | arch.CardStatus.ADDRESS_ERROR
                 | arch.CardStatus.BLOCK_LEN_ERROR | arch.CardStatus.WP_VIOLATION
                 | arch.CardStatus.CARD_ECC_FAILED | arch.CardStatus.CC_ERROR
                 | arch.CardStatus.ERROR)


@dataclass
class CardInfo:
    """What identification found out.

    ``high_capacity`` is the OCR's CCS bit: True for SDHC/SDXC (block addresses), False for
    a standard-capacity card (SDSC, byte addresses; the driver converts). ``version`` is 2
    when the card answered CMD8 (physical layer 2.00 or later), 1 for a Ver1.X card.
    ``ccs_ignored`` is True when a card that did not answer CMD8 still set CCS in its OCR:
    CCS means something only after CMD8 and an ACMD41 with HCS (PLSS §4.2.3.1, Figure 4-2;
    a Ver1.X card is standard capacity), so the driver uses byte addresses for it
    (``high_capacity`` False) and says so here.
    """
    ocr: int
    cid: int
    rca: int
    high_capacity: bool
    version: int = 2
    ccs_ignored: bool = False


class SdCardDriver:
    """Drives one card through an :class:`~maglog.hw.sdio.host.SdioHost`.

    Parameters
    ----------
    bus : RegisterBus
    regs : RegisterMap
        The host's registers.
    port : BlockPort
        The host's data streams.
    sys_clock_hz : float
        The host's system clock, for the SD clock divisor.
    """
    def __init__(self, bus, regs, port, *, sys_clock_hz):
        self.bus, self.regs, self.port = bus, regs, port
        self.sys_clock_hz = sys_clock_hz
        self.sd_clock_hz = None
        self.info = None
        self.retries = 0                    # how many retries were needed so far
        self._forget_card()
        self._divisor = None                # the SD clock's divisor, once set
        self._gap_owed = False              # a command went out since the last extra gap

    def _forget_card(self):
        """What the driver learnt about the card, back to unknown (at each initialise)."""
        #: Whether the card takes ACMD23 (the pre-erase count before a CMD25): None until a
        #: multi-block write has tried it, True once it answered as ACMD23, False once it
        #: did not (no answer, or taken as CMD23); multi-block writes then go without it
        #: until the card is initialised again. :attr:`pre_erase_note` says why.
        self.pre_erase_supported = None
        self.pre_erase_note = ""
        #: Whether the card answers CMD13 (SEND_STATUS): None until asked, False once it
        #: did not when it was asked first; the driver then waits on DAT0 instead after a
        #: failed write (see :meth:`_wait_tran`). :attr:`status_note` says why.
        self.status_supported = None
        self.status_note = ""
        #: Each decision above that leaves the spec's usual path, once, in plain words.
        self.fallbacks = []

    # -- host primitives --------------------------------------------------------------------

    async def set_clock(self, hz, *, run=False):
        """Set the SD clock to at most ``hz``; returns the frequency set."""
        divisor = max(0, -(-int(self.sys_clock_hz) // (2 * int(hz))) - 1)
        limit = (1 << self.regs["clock"].field("divisor").width) - 1
        if divisor > limit:
            raise ValueError(f"{hertz(hz)} is below the slowest SD clock of this host "
                             f"({hertz(self.sys_clock_hz / (2 * (limit + 1)))})")
        await self.bus.write(self.regs["clock"].address,
                             self.regs["clock"].encode(divisor=divisor, run=int(run)))
        self._divisor = divisor
        self.sd_clock_hz = self.sys_clock_hz / (2 * (divisor + 1))
        return self.sd_clock_hz

    def _clocks_to_s(self, clocks):
        return clocks / self.sd_clock_hz

    async def _status(self):
        return self.regs["status"].decode(await self.bus.read(self.regs["status"].address))

    async def _wait_idle(self, field, timeout_s):
        status = self.regs["status"]
        try:
            word = await self.bus.wait_event(status.address,
                                             lambda w: not status.field(field).extract(w),
                                             timeout=timeout_s, what=f"host {field} to clear")
        except BusTimeout as error:
            raise SdTimeout(f"the SD host stayed busy: {error}") from None
        return status.decode(word)

    async def _keep_command_gap(self):
        """COMMAND_GAP_EXTRA_CLOCKS more clocks after the last command's N_CC gap (which the
        CMD engine has kept by the time it is idle). The host runs the SD clock only while
        it is busy, so idle time alone gives the card no clocks: the clock runs for them."""
        if not self._gap_owed:
            return
        self._gap_owed = False
        clock = self.regs["clock"]
        await self.bus.write(clock.address, clock.encode(divisor=self._divisor, run=1))
        await self.bus.wait(self._clocks_to_s(COMMAND_GAP_EXTRA_CLOCKS))
        await self.bus.write(clock.address, clock.encode(divisor=self._divisor, run=0))

    async def command(self, index, argument, response, *, data=DataPhase.NONE, tries=None,
                      name=None):
        """Send one command; returns the response bits (card status, OCR, CID ...).

        Retries a command without a data phase on a response CRC error (a data command is
        not sent twice: the card may already wait for data), up to ``tries`` times in all
        (default CMD_RETRIES); raises :class:`SdTimeout` when nothing answers,
        :class:`SdCrcError` when every try had a CRC error, :class:`SdCardError` on a
        malformed response or error bits in an R1. ``name`` names the command in those
        (default ``CMD<index>``)."""
        regs = self.regs
        name = name or f"CMD{index}"
        if tries is None:
            tries = CMD_RETRIES if data == DataPhase.NONE else 1
        # The engine is busy for the command, the wait for the response, the longest
        # response and its gap: twice that before the host is taken as stuck.
        engine_clocks = (arch.CMD_BITS + RESPONSE_TIMEOUT_CLOCKS + arch.R2_BITS
                         + arch.N_CC + COMMAND_GAP_EXTRA_CLOCKS)
        for attempt in range(tries):
            await self._keep_command_gap()
            await self.bus.write(regs["argument"].address, argument)
            await self.bus.write(regs["command"].address, regs["command"].encode(
                index=index, kind=_KIND[response],
                r1b=int(response == arch.Response.R1B), data=data))
            status = await self._wait_idle("cmd_busy", self._clocks_to_s(2 * engine_clocks))
            self._gap_owed = True
            if response == arch.Response.NONE:
                return None
            if status["cmd.timeout"]:
                raise SdTimeout(f"{name} got no response")
            if status["cmd.crc_error"]:
                self.retries += 1
                continue
            if status["cmd.format_error"] or status["cmd.end_error"]:
                raise SdCardError(f"{name}: malformed response ({_flags(status, 'cmd.')})")
            bits = 0
            words = 4 if response == arch.Response.R2 else 2
            for word in range(words):
                value = await self.bus.read(regs[f"response{word}"].address)
                bits |= value << (32 * word)
            if response == arch.Response.R2:
                return bits >> 1             # CID/CSD bits 127..1 (its CRC7 in bits 6..0)
            payload = (bits >> 8) & 0xFFFFFFFF
            if response in (arch.Response.R1, arch.Response.R1B):
                errors = arch.CardStatus(payload) & STATUS_ERRORS
                if errors:
                    raise SdCardError(f"{name}: card status reports {errors!r}")
            if response == arch.Response.R1B:
                await self._wait_dat(f"{name} busy")
            return payload
        raise SdCrcError(f"{name}: response CRC error on all {tries} tries")

    async def _wait_dat(self, what):
        timeout = self._clocks_to_s(arch.BUSY_TIMEOUT_CLOCKS) * 2
        status = await self._wait_idle("dat_busy", timeout)
        if status["busy_timeout"]:
            raise SdTimeout(f"{what}: the card stayed busy past the busy timeout")
        return status

    async def _stop_quietly(self):
        """CMD12, where the card's answer may carry the failure's own status bits."""
        try:
            await self.command(arch.Command.STOP_TRANSMISSION, 0, arch.Response.R1B)
        except (SdCardError, SdTimeout):
            pass                    # not in a data state any more: nothing to stop

    async def app_command(self, index, argument, response):
        """CMD55 then ACMD ``index``. A response CRC error sends both again: the ACMD
        alone would reach the card as the regular command of that index (CMD6 is
        SWITCH_FUNC, CMD23 SET_BLOCK_COUNT), and CMD55 applies to the next command only."""
        rca = self.info.rca if self.info else 0
        for attempt in range(CMD_RETRIES):
            await self.command(arch.Command.APP_CMD, rca << 16, arch.Response.R1)
            try:
                return await self.command(index, argument, response, tries=1,
                                          name=f"ACMD{index}")
            except SdCrcError:
                continue                    # counted in self.retries by command()
        raise SdCrcError(f"ACMD{index}: response CRC error on all {CMD_RETRIES} tries")

    # -- identification ---------------------------------------------------------------------

    async def initialise(self):
        """Power-up clocks, CMD0, CMD8, ACMD41 until ready, CMD2, CMD3, CMD7, ACMD6, then the
        25 MHz clock. Returns :class:`CardInfo`.

        As PLSS §4.2.3.1 (Figure 4-2) has it: a card that answers CMD8 gets ACMD41 with HCS
        (it may be SDHC/SDXC or SDSC, the OCR's CCS says which); a card that does not is a
        Ver1.X card (or none) and gets ACMD41 with HCS = 0; no answer to that either means
        no card. A Ver1.X card is standard capacity even if its OCR sets CCS (byte
        addresses; :attr:`CardInfo.ccs_ignored` says so). A standard-capacity card's block
        length is 512 bytes from power-up (PLSS Table 4-22, CMD16), so no CMD16 is needed.

        Everything learnt about the previous card (:attr:`pre_erase_supported`,
        :attr:`status_supported`, :attr:`fallbacks`) is forgotten first: this may be
        another card."""
        self.info = None
        self._forget_card()
        await self.bus.write(self.regs["timeouts"].address,
                             self.regs["timeouts"].encode(response=RESPONSE_TIMEOUT_CLOCKS))
        await self.set_clock(arch.IDENT_CLOCK_HZ, run=True)
        await self.bus.wait(self._clocks_to_s(INIT_CLOCKS_SENT))
        await self.set_clock(arch.IDENT_CLOCK_HZ, run=False)
        self._gap_owed = False              # those clocks were the gap
        await self.command(arch.Command.GO_IDLE_STATE, 0, arch.Response.NONE)
        try:
            echo = await self.command(arch.Command.SEND_IF_COND, arch.IF_COND_ARGUMENT,
                                      arch.Response.R7)
        except SdTimeout:
            version = 1                     # a Ver1.X card, or no card at all
        else:
            version = 2
            if echo & arch.IF_COND_ECHO_MASK != arch.IF_COND_ARGUMENT:
                raise SdCardError(f"CMD8 echo {echo & arch.IF_COND_ECHO_MASK:#05x} does not "
                                  f"match {arch.IF_COND_ARGUMENT:#05x}")
        hcs = arch.ACMD41_HCS if version == 2 else 0
        start = self.bus.now()
        while True:
            try:
                ocr = await self.app_command(arch.AppCommand.SD_SEND_OP_COND,
                                             hcs | arch.OCR_VOLTAGE_WINDOW, arch.Response.R3)
            except SdTimeout:
                if version == 1:
                    raise SdNoCard("no card answers CMD8 or ACMD41") from None
                raise
            if ocr & arch.OCR_POWER_UP_DONE:
                break
            if self.bus.now() - start > arch.ACMD41_LIMIT_S:
                raise SdTimeout(f"the card did not finish power-up within "
                                f"{arch.ACMD41_LIMIT_S} s")
            await self.bus.wait(1e-3)
        cid = await self.command(arch.Command.ALL_SEND_CID, 0, arch.Response.R2)
        rca = (await self.command(arch.Command.SEND_RELATIVE_ADDR, 0, arch.Response.R6)) >> 16
        # CCS is valid only on the version-2 path (a CMD8 answer, then HCS in ACMD41): a
        # Ver1.X card is standard capacity whatever that bit says (PLSS §4.2.3.1). Believing
        # it would send block numbers to a card that reads byte addresses: every block of
        # the first 512 would land on block 0.
        ccs = bool(ocr & arch.OCR_CCS)
        ccs_ignored = ccs and version == 1
        if ccs_ignored:
            self.fallbacks.append("CCS set in the OCR of a card that did not answer CMD8 "
                                  "(a Ver1.X card): ignored, byte addressing")
        self.info = CardInfo(ocr=ocr, cid=cid, rca=rca, high_capacity=ccs and version == 2,
                             version=version, ccs_ignored=ccs_ignored)
        await self.command(arch.Command.SELECT_CARD, rca << 16, arch.Response.R1B)
        await self.app_command(arch.AppCommand.SET_BUS_WIDTH, arch.BUS_WIDTH_4,
                               arch.Response.R1)
        await self.set_clock(arch.DEFAULT_SPEED_HZ)
        return self.info

    async def card_status(self):
        """The card status (CMD13's R1)."""
        status = await self.command(arch.Command.SEND_STATUS, self.info.rca << 16,
                                    arch.Response.R1)
        self.status_supported = True
        return status

    def _no_status(self, why):
        """Record, once, that this card does not answer CMD13."""
        if self.status_supported is None:
            self.status_supported = False
            self.status_note = why
            self.fallbacks.append(f"no card status: {why}; after a failed write the driver "
                                  f"waits for DAT0 instead")

    def _no_pre_erase(self, why):
        """Record, once, that multi-block writes go without ACMD23 on this card."""
        self.pre_erase_supported = False
        self.pre_erase_note = why
        self.fallbacks.append(f"no pre-erase: {why}; multi-block writes go without ACMD23")

    # -- data -------------------------------------------------------------------------------

    def _address(self, lba):
        """The argument of a data command for block ``lba``: the block number on SDHC/SDXC,
        its byte address on a standard-capacity card (PLSS Table 4-24, note 2)."""
        return lba if self.info.high_capacity else lba * arch.BLOCK_BYTES

    async def read_block(self, lba):
        """The 512 bytes of block ``lba`` (retried on a CRC error)."""
        regs = self.regs
        for attempt in range(CMD_RETRIES):
            await self.command(arch.Command.READ_SINGLE_BLOCK, self._address(lba),
                               arch.Response.R1, data=DataPhase.READ)
            data = await self.port.receive(arch.BLOCK_BYTES)
            status = await self._wait_idle("dat_busy", self._clocks_to_s(
                arch.READ_TIMEOUT_CLOCKS) * 2)
            if status["read.timeout"]:
                raise SdTimeout(f"block {lba}: no data within the read timeout")
            if status["read.crc_error"] or status["read.end_error"]:
                self.retries += 1
                continue
            return data
        raise SdCrcError(f"block {lba}: read data CRC error on all {CMD_RETRIES} tries")

    async def write_blocks(self, lba, data, *, pre_erase=True):
        """Write ``data`` (whole blocks), queued on the block port, from block ``lba`` on;
        see :meth:`write_from`."""
        if len(data) % arch.BLOCK_BYTES or not data:
            raise ValueError(f"Write data must be whole {arch.BLOCK_BYTES}-byte blocks, "
                             f"not {len(data)} bytes")

        class PortSource:
            async def arm(source, first, count):
                await self.port.send(data[first * arch.BLOCK_BYTES:
                                          (first + count) * arch.BLOCK_BYTES])

            async def cancel(source):
                await self.port.discard()

        return await self.write_from(lba, len(data) // arch.BLOCK_BYTES, PortSource(),
                                     pre_erase=pre_erase)

    async def write_from(self, lba, count, source, *, pre_erase=True):
        """Write ``count`` blocks from block ``lba`` on, their bytes streamed to the host by
        ``source`` (``await source.arm(first, n)`` sets it up to send blocks first ..
        first+n-1 of the run; ``await source.cancel()`` drops what it has not sent). CMD24
        for one block, else ACMD23 (pre-erase count, a hint: skipped when ``pre_erase`` is
        false or the card did not take it before, see :attr:`pre_erase_supported`; never a
        reason for the write to fail) and CMD25 ended by CMD12. A block the card rejects is
        sent again (after CMD12 and a status check, see :meth:`_wait_tran`), up to a limit;
        raises :class:`SdWriteError` with the count of blocks that are safely
        written. Returns ``count``."""
        done = 0
        failures = 0
        while done < count:
            try:
                accepted, error = await self._write_run(lba + done, done, count - done,
                                                        source, pre_erase)
            except SdError as failure:
                # A command of the run itself failed (no response, error bits): what is
                # written stays written, and the caller learns how much that is.
                raise SdWriteError(f"writing block {lba + done} failed: {failure}",
                                   done) from failure
            done += accepted
            if error is None:
                continue
            failures += 1
            self.retries += 1
            if failures > WRITE_RETRIES:
                raise SdWriteError(f"writing block {lba + done} failed: {error}", done)
            try:
                await self._wait_tran()
            except SdError as failure:
                raise SdWriteError(f"writing block {lba + done} failed: {error}; then "
                                   f"{failure}", done) from failure
        return done

    async def _wait_tran(self):
        """Poll the card status (CMD13) until the card is back in tran, ready for data.

        A card that has never answered CMD13 and does not answer it now (some card models
        answer no CMD13 at all) is not given up: that would cost the blocks still to write
        although every block the card accepted (by its CRC status token) is written. The
        driver then waits for DAT0 to be released instead (the card holds it low while it
        programs, PLSS §4.3.4; the failed run has already had its CMD12 and that R1b's
        busy): the card is back in tran, and if it is not, the next write command goes
        unanswered and the write fails with the count of blocks accepted so far. A card
        that answered CMD13 before and stops answering is in trouble: that ends the write.
        """
        if self.status_supported is False:
            return await self._wait_dat0_released()
        start = self.bus.now()
        while True:
            try:
                status = await self.card_status()
            except SdTimeout as error:
                if self.status_supported is not None:
                    raise
                self._no_status(f"{error} after a failed write")
                return await self._wait_dat0_released()
            state = (status & arch.STATUS_STATE_MASK) >> arch.STATUS_STATE_SHIFT
            if state == arch.CardState.TRAN and status & arch.CardStatus.READY_FOR_DATA:
                return
            if self.bus.now() - start > RECOVER_LIMIT_S:
                name = next((s.name for s in arch.CardState if s == state), str(state))
                raise SdTimeout(f"the card stayed in state {name} for {RECOVER_LIMIT_S:g} s "
                                f"after a failed write")
            await self.bus.wait(RECOVER_POLL_S)

    async def _wait_dat0_released(self):
        """Wait until the card releases DAT0 (no more busy), RECOVER_LIMIT_S at most."""
        status = self.regs["status"]
        level = status.field("dat_level")
        try:
            await self.bus.wait_event(status.address, lambda w: level.extract(w) & 1,
                                      timeout=RECOVER_LIMIT_S, poll=RECOVER_POLL_S,
                                      what="DAT0 high")
        except BusTimeout:
            raise SdTimeout(f"the card held DAT0 low (busy) for {RECOVER_LIMIT_S:g} s after "
                            f"a failed write") from None

    async def _pre_erase(self, count):
        """ACMD23 before a CMD25 of ``count`` blocks, unless this card has shown it does not
        take it; returns True when the card took it for CMD23 (SET_BLOCK_COUNT): that CMD25
        then ends by itself and gets no CMD12.

        Pre-erase only speeds writing up, so nothing here fails a write: whatever does not
        go as the spec says turns it off for this card (until :meth:`initialise`), once,
        recorded in :attr:`pre_erase_supported`, :attr:`pre_erase_note` and
        :attr:`fallbacks`, and the CMD25 goes out without it.

        A card that does not define ACMD23 treats it as the regular CMD23 (PLSS §4.3.9.1):
        with CMD23 it answers an R1 with APP_CMD clear (item 4) and has set the block count
        (to ``count``: the write is the same); without it the command is illegal, no response
        and ILLEGAL_COMMAND in the next status (§4.10.1, condition B). After no response,
        CMD13 asks why: COM_CRC_ERROR (the command was lost on the line) earns one more try.
        ILLEGAL_COMMAND, a status that says neither (cards that clear the flag at the next
        command instead of keeping it until it is reported), no answer to CMD13 either, or
        a second loss: pre-erase off."""
        if self.pre_erase_supported is False:
            return False
        lost = 0
        while True:
            try:
                status = await self.app_command(arch.AppCommand.SET_WR_BLK_ERASE_COUNT, count,
                                                arch.Response.R1)
            except SdTimeout as unanswered:
                why = await self._why_unanswered(unanswered)
                if why is None:
                    lost += 1
                    if lost < 2:
                        self.retries += 1       # lost on the line: once more
                        continue
                    why = f"{unanswered} twice, lost to a CRC error each time"
                self._no_pre_erase(why)
                return False
            except SdError as failure:          # CRC errors throughout, or error bits
                self._no_pre_erase(f"ACMD23 failed: {failure}")
                return False
            if status & arch.CardStatus.APP_CMD:
                self.pre_erase_supported = True
                return False
            self._no_pre_erase("the card took ACMD23 for CMD23 (APP_CMD clear in its R1)")
            return True

    async def _why_unanswered(self, unanswered):
        """Why CMD55 or ACMD23 got no response, from CMD13: None when the command was lost
        to a CRC error (worth another try), else the reason to give up pre-erase."""
        if self.status_supported is False:
            return f"{unanswered}, and this card does not answer CMD13 to say why"
        try:
            status = arch.CardStatus(await self.card_status())
        except SdTimeout as error:
            if self.status_supported is None:
                self._no_status(f"{error} (asked why ACMD23 went unanswered)")
            return f"{unanswered}, and CMD13 got none either"
        except SdError as error:
            return f"{unanswered}; then CMD13: {error}"
        if arch.CardStatus.ILLEGAL_COMMAND in status:
            return f"{unanswered}: an illegal command to this card (ILLEGAL_COMMAND)"
        if arch.CardStatus.COM_CRC_ERROR in status:
            return None
        return (f"{unanswered}, and the card status after it flags neither ILLEGAL_COMMAND "
                f"nor COM_CRC_ERROR")

    async def _write_run(self, lba, first, count, source, pre_erase):
        regs = self.regs
        multi = count > 1
        counted = False
        if multi and pre_erase:
            counted = await self._pre_erase(count)
        await self.bus.write(regs["blocks"].address, count)
        await source.arm(first, count)
        index = arch.Command.WRITE_MULTIPLE_BLOCK if multi else arch.Command.WRITE_BLOCK
        try:
            await self.command(index, self._address(lba), arch.Response.R1,
                               data=DataPhase.WRITE)
        except (SdCrcError, SdCardError) as error:
            # The data phase may have started or not; stop it cleanly and try again.
            await self._wait_dat(f"CMD{index}")
            await source.cancel()
            await self._stop_quietly()
            return 0, str(error)
        status = await self._wait_dat(f"writing from block {lba}")
        accepted = await self.bus.read(regs["accepted"].address)
        failed = {k: v for k, v in status.items() if k.startswith("write.") and v}
        # CMD12 ends a multi-block write (unless CMD23 set its length), and any write that
        # went wrong while the card may still be in rcv. A single block that the card
        # answered with a token (CRC or write error) or a busy has left rcv (for tran, or
        # prg): CMD12 would be an illegal command there.
        left_rcv = not multi and failed and not (failed.keys() & _MAYBE_STILL_RECEIVING)
        if (multi and not counted) or (failed and not left_rcv):
            await self._stop_quietly()
        if failed:
            await source.cancel()
            return accepted, ", ".join(k[len("write."):] for k in failed)
        return accepted, None


#: Write failures after which the card may not have taken the block's end: no token, or
#: a token without its end bit.
_MAYBE_STILL_RECEIVING = {"write.no_token", "write.bad_token_end"}


def _flags(status, prefix):
    return ", ".join(k[len(prefix):] for k, v in status.items() if k.startswith(prefix) and v)
