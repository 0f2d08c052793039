"""The storage path of the transaction-level logger model: the SDRAM ring, the DMA and the SD
host (hw/ringbuffer.py, hw/dma.py, hw/sdio/host.py), with their registers (windows ``dma``
and ``sdio``), over the command-level card of sim/models/logger_sd.py.

Commands and responses are whole (the response's bit string, CRC7 included, checked as the
CMD engine checks it) and blocks are whole, each timed in SD clocks at the divisor of the
moment; the card stores a block when its programming (DAT0 busy) ends.
"""

from __future__ import annotations

from collections import deque

from ...hw.arch import sd as arch_sd
from ...hw.dma import DmaSource
from ...hw.sdio.clock import TICK_CLOCKS
from ...hw.sdio.dat import BUSY_TIMEOUT_TICKS, READ_TIMEOUT_TICKS
from .logger_sd import crc7


__all__ = ["StoragePath", "Ring"]

_BLOCK = arch_sd.BLOCK_BYTES
_SOURCE_BUFFER = DmaSource.BUFFER.value
#: The error bits of the SD host's status (hw/sdio/cmd.py CmdStatus, hw/sdio/dat.py
#: WriteStatus and ReadStatus).
_CMD_FLAGS = ("timeout", "crc_error", "format_error", "end_error")
_WRITE_FLAGS = ("crc_rejected", "write_error", "no_token", "bad_token_end", "busy_timeout")
_READ_FLAGS = ("timeout", "crc_error", "end_error")
#: SD clocks of a written block on the bus: N_WR ones, start bit, 1024 nibbles, CRC16, end.
_WRITE_BLOCK_CLOCKS = arch_sd.N_WR + 1 + arch_sd.DATA_NIBBLES + arch_sd.CRC16_BITS + 1
#: From the end bit to the token's end: N_CRC clocks, then start, three status bits, end.
_TOKEN_CLOCKS = arch_sd.N_CRC + 1 + arch_sd.TOKEN_STATUS_BITS + 1
#: A read block after its start bit: 1024 nibbles, CRC16, end bit.
_READ_BLOCK_CLOCKS = arch_sd.DATA_NIBBLES + arch_sd.CRC16_BITS + 1
#: System clocks of commit history the ring keeps for the bytes of a block being sent: at
#: the slowest SD clock (divisor 1023) a block is about 2.2 M system clocks.
_COMMIT_HORIZON = 4 * _WRITE_BLOCK_CLOCKS * 2 * 1024


class Ring:
    """The SDRAM ring's pointers, counters and bytes (hw/ringbuffer.py)."""
    def __init__(self, capacity):
        self.capacity = capacity
        self.data = bytearray(capacity)
        self.reset()

    def reset(self):
        self.high_water = self.kept = self.dropped = 0
        self.clear()

    def clear(self):
        self.commit = self.rd = 0
        self.commits = deque()            # (cycle, commit after) of recent commits
        self._base = 0                    # the commit before the oldest logged one

    @property
    def level(self):
        return self.commit - self.rd

    def fits(self, length):
        return self.level + length <= self.capacity

    def store(self, frame):
        start = self.commit % self.capacity
        first = min(len(frame), self.capacity - start)
        self.data[start:start + first] = frame[:first]
        self.data[:len(frame) - first] = frame[first:]

    def commit_frame(self, now, length):
        self.commit += length
        self.kept += 1
        self.high_water = max(self.high_water, self.level)
        self.commits.append((now, self.commit))
        self.forget_before(now - _COMMIT_HORIZON)

    def forget_before(self, cycle):
        """Drop the commit log up to ``cycle`` (no byte is read before it any more)."""
        while self.commits and self.commits[0][0] <= cycle:
            self._base = self.commits.popleft()[1]

    def _commit_at(self, cycle):
        value = self._base
        for when, commit in self.commits:
            if when > cycle:
                break
            value = commit
        return value

    def sector(self, index, byte_time):
        """Sector ``index`` after the read pointer: each byte as the ring gives it at
        ``byte_time(i)``, committed data or zero."""
        base = self.rd + index * _BLOCK
        start = base % self.capacity
        first = min(_BLOCK, self.capacity - start)
        raw = bytes(self.data[start:start + first]) + bytes(self.data[:_BLOCK - first])
        if not self.commits or self.commits[0][0] > byte_time(_BLOCK - 1):
            committed = max(0, min(_BLOCK, self._commit_at(byte_time(0)) - base))
            return raw[:committed] + bytes(_BLOCK - committed)
        out = bytearray(_BLOCK)
        for i in range(_BLOCK):
            if base + i < self._commit_at(byte_time(i)):
                out[i] = raw[i]
        return bytes(out)


def _check_response(kind, index, value):
    """The CMD engine's checks of a received response (hw/sdio/cmd.py)."""
    flags = {"end_error": int(value & 1 != 1)}
    received = (value >> 1) & 0x7F
    if kind == arch_sd.ResponseKind.LONG:
        flags["crc_error"] = int(crc7(value >> 8, 120) != received)
    elif kind == arch_sd.ResponseKind.SHORT:
        flags["crc_error"] = int(crc7(value >> 8, arch_sd.CMD_CRC_LAST) != received)
        flags["format_error"] = int((value >> 40) & 0x3F != index or (value >> 46) & 1 != 0)
    return flags


class StoragePath:
    """Ring, DMA and SD host state, on the model ``m``'s clock and event queue.

    Parameters
    ----------
    m : LoggerModel
    ring_capacity : int
    """
    def __init__(self, m, ring_capacity):
        self.m = m
        self.ring = Ring(ring_capacity)
        self._buffer = [0] * (_BLOCK // 4)     # a memory: survives resets
        self._dat0_low_until = 0               # the card's busy: survives resets
        # The SD host's settings but the clock's survive resets too (write-only, reset-less;
        # the firmware writes the argument and block count before each use). The timeouts
        # are in SD clocks here: the host counts the long ones in ticks of TICK_CLOCKS and
        # ends them N to N + 1 ticks after their start; the model takes the shortest, N.
        self._argument, self._blocks = 0, 1
        self._response_timeout = arch_sd.N_CR_MAX
        self._busy_timeout = BUSY_TIMEOUT_TICKS * TICK_CLOCKS
        self._read_timeout = READ_TIMEOUT_TICKS * TICK_CLOCKS
        self.reset()

    def reset(self):
        """The state after a reset of the logger."""
        now = self.m.now
        self.ring.reset()
        self._dma_busy, self._dma_source, self._dma_sectors = 0, 0, 0
        self._dma_sent, self._dma_first = 0, 0
        self._buf_index, self._fill = 0, 0
        self._sd_divisor, self._sd_run = 0, 0
        self._cmd_status = dict.fromkeys(_CMD_FLAGS, 0)
        self._write_status = dict.fromkeys(_WRITE_FLAGS, 0)
        self._read_status = dict.fromkeys(_READ_FLAGS, 0)
        self._r1b_timeout = 0
        self._response, self._accepted = 0, 0
        self.cmd_free = now
        self._writer = None
        self._writer_stalled = False
        self._reader_busy = self._r1b_busy = False

    def changes(self):
        """Instants at which a register reads differently without an event: the CMD
        engine's end, the end of DAT0 busy."""
        return (self.cmd_free, self._dat0_low_until)

    # -- SD host ----------------------------------------------------------------------------

    @property
    def _period(self):
        """System clocks per SD clock."""
        return 2 * (self._sd_divisor + 1)

    def _sd_command(self, index, kind, r1b, phase):
        if self.m.now < self.cmd_free:
            return                      # the CMD engine is busy: the write is ignored
        p, start = self._period, self.m.now
        self._cmd_status = dict.fromkeys(_CMD_FLAGS, 0)
        if phase == arch_sd.DataPhase.READ:
            self._reader_busy = True
            self._read_status = dict.fromkeys(_READ_FLAGS, 0)
        sent = start + (arch_sd.CMD_BITS + 1) * p
        answer = self.m.card.command(sent / self.m.clk_freq, index, self._argument)
        status, value = dict.fromkeys(_CMD_FLAGS, 0), None
        if kind == arch_sd.ResponseKind.NONE:
            done = sent
        elif answer.response in (None, arch_sd.Response.NONE) or \
                arch_sd.N_CR_MIN > self._response_timeout:
            status["timeout"] = 1
            done = sent + (self._response_timeout + 1) * p
        else:
            length = arch_sd.R2_BITS if kind == arch_sd.ResponseKind.LONG else arch_sd.CMD_BITS
            bits, count = answer.bits()
            if count >= length:
                value = bits >> (count - length)
            else:           # the line is high after the card's last bit
                value = (bits << (length - count)) | ((1 << (length - count)) - 1)
            status.update(_check_response(kind, index, value))
            done = sent + (arch_sd.N_CR_MIN + length) * p
        self.cmd_free = done + arch_sd.N_CC * p
        self.m._schedule(done, self._sd_command_done, status, value, phase, r1b, answer)
        if phase == arch_sd.DataPhase.READ:
            limit = start + (self._read_timeout + 1) * p
            if answer.read is not None:
                begin = done + max(arch_sd.N_AC_MIN * p, self.m._cycles(self.m.card.read_s()))
                if begin <= limit:
                    end = begin + _READ_BLOCK_CLOCKS * p
                    self.m._schedule(end, self._card_sent_block, answer.read, self.m._epoch,
                                     hardware=False)
                    return
                self.m._schedule(begin + _READ_BLOCK_CLOCKS * p, self._card_sent_block,
                                 answer.read, None, hardware=False)
            self.m._schedule(limit, self._reader_done, "timeout")

    def _sd_command_done(self, status, value, phase, r1b, answer):
        self._cmd_status = status
        if value is not None:
            self._response = value & ((1 << arch_sd.R2_CONTENT_BITS) - 1)
        if any(status.values()):
            self.m._event("sd_error")
        elif phase == arch_sd.DataPhase.WRITE:
            if self._blocks:
                self._writer = {"left": self._blocks}
                self._write_status = dict.fromkeys(_WRITE_FLAGS, 0)
                self._accepted = 0
                self._block_start()
        elif r1b:
            p = self._period
            self._r1b_busy, self._r1b_timeout = True, 0
            end = self.m.now + max((arch_sd.BUSY_START_CLOCKS + 1) * p,
                                 self.m._cycles(answer.busy_s))
            limit = self.m.now + max(arch_sd.BUSY_START_CLOCKS + 1, self._busy_timeout) * p
            self._dat0_low_until = end
            self.m._schedule(min(end, limit), self._r1b_done, int(end > limit))

    def _r1b_done(self, timed_out):
        self._r1b_busy = False
        self._r1b_timeout = timed_out
        if timed_out:
            self.m._event("sd_error")

    def _card_sent_block(self, lba, epoch):
        data = self.m.card.block(lba)
        if epoch != self.m._epoch or not self._reader_busy:
            return
        for byte in data:
            if self._fill >= _BLOCK:
                break
            word, lane = divmod(self._fill, 4)
            self._buffer[word] = (self._buffer[word] & ~(0xFF << 8 * lane)) | byte << 8 * lane
            self._fill += 1
        self._reader_done(None)

    def _reader_done(self, flag):
        if not self._reader_busy:
            return
        self._reader_busy = False
        if flag:
            self._read_status[flag] = 1
            self.m._event("sd_error")

    def _block_start(self):
        """The writer wants the next block's bytes (the clock stops until the DMA has
        them)."""
        if not self._dma_busy:
            self._writer_stalled = True
            return
        self._writer_stalled = False
        self.ring.forget_before(self.m.now)
        self._writer["t0"] = self.m.now
        self.m._schedule(self.m.now + _WRITE_BLOCK_CLOCKS * self._period, self._block_sent)

    def _block_sent(self):
        p, t0 = self._period, self._writer["t0"]
        first_nibble = t0 + (arch_sd.N_WR + 1) * p
        data = self._dma_take(lambda i: first_nibble + 2 * i * p)
        if not self.m.card.receiving():
            self.m._schedule(self.m.now + (arch_sd.TOKEN_TIMEOUT_CLOCKS + 1) * p,
                             self._writer_done, "no_token")
            return
        self.m.card.start_programming()
        token = self.m.now + _TOKEN_CLOCKS * p
        end = token + max((arch_sd.BUSY_START_CLOCKS + 1) * p, self.m._cycles(self.m.card.busy_s()))
        limit = token + max(arch_sd.BUSY_START_CLOCKS + 1, self._busy_timeout) * p
        self._dat0_low_until = end
        self.m._schedule(end, self._card_programmed, data, self.m._epoch, end <= limit,
                         self.m.card.insertions, hardware=False)
        if end > limit:
            self.m._schedule(limit, self._writer_done, "busy_timeout")

    def _card_programmed(self, data, epoch, in_time, insertions):
        # (A card that left meanwhile lost the block; the host saw DAT0 high, pulled up.)
        if insertions == self.m.card.insertions:
            self.m.card.program(data)
            self.m._block_stored()
        if not in_time or epoch != self.m._epoch or self._writer is None:
            return
        self._accepted = (self._accepted + 1) & 0xFFFF
        self._writer["left"] -= 1
        if self._writer["left"]:
            self._block_start()
        else:
            self._writer_done(None)

    def _writer_done(self, flag):
        if self._writer is None:
            return
        self._writer = None
        self._writer_stalled = False
        if flag:
            self._write_status[flag] = 1
            self.m._event("sd_error")

    # -- DMA ----------------------------------------------------------------------------------

    def _dma_take(self, byte_time):
        """The writer takes the DMA's next sector (the DMA is busy)."""
        if self._dma_source == _SOURCE_BUFFER:
            data = b"".join(word.to_bytes(4, "little") for word in self._buffer)
        else:
            data = self.ring.sector(self._dma_first + self._dma_sent, byte_time)
        self._dma_sent = (self._dma_sent + 1) & 0xFFFF
        if self._dma_sent == self._dma_sectors:
            self._dma_busy = 0
            self.m._event("dma_done")
        return data

    # -- registers: window sdio (the settings are write-only)
    def _w_sdio_clock(self, f):
        self._sd_divisor, self._sd_run = f["divisor"], f["run"]

    def _w_sdio_argument(self, f):
        self._argument = f["value"]

    def _w_sdio_command(self, f):
        self._sd_command(f["index"], f["kind"], f["r1b"], f["data"])

    def _w_sdio_blocks(self, f):
        self._blocks = f["count"]

    def _w_sdio_timeouts(self, f):
        self._response_timeout = f["response"]

    def _w_sdio_busy_timeout(self, f):
        self._busy_timeout = f["ticks"] * TICK_CLOCKS

    def _w_sdio_read_timeout(self, f):
        self._read_timeout = f["ticks"] * TICK_CLOCKS

    def _r_sdio_status(self):
        fields = {"cmd_busy": int(self.m.now < self.cmd_free),
                  "dat_busy": int(self._writer is not None or self._reader_busy
                                  or self._r1b_busy),
                  "busy_timeout": self._r1b_timeout,
                  "dat_level": 0xF if self.m.now >= self._dat0_low_until or
                  not self.m.card.present else 0xE}
        for prefix, flags in (("cmd", self._cmd_status), ("write", self._write_status),
                              ("read", self._read_status)):
            fields.update((f"{prefix}.{name}", value) for name, value in flags.items())
        return fields

    def _r_sdio_accepted(self):
        return {"count": self._accepted}

    def _response_word(self, word):
        return {"value": (self._response >> (32 * word)) & 0xFFFFFFFF}

    def _r_sdio_response0(self):
        return self._response_word(0)

    def _r_sdio_response1(self):
        return self._response_word(1)

    def _r_sdio_response2(self):
        return self._response_word(2)

    def _r_sdio_response3(self):
        return self._response_word(3)

    # -- registers: window dma
    def _w_dma_control(self, f):
        busy = self._dma_busy
        if f["start"] and not busy and f["sectors"]:
            self._dma_busy, self._dma_source = 1, f["source"]
            self._dma_sectors = 1 if f["source"] == _SOURCE_BUFFER else f["sectors"]
            self._dma_sent, self._dma_first = 0, f["first"]
            if self._writer_stalled and self._writer is not None:
                self._block_start()
        if f["abort"] and busy:
            self._dma_busy = 0
            self.m._event("dma_done")
        if f["arm_read"]:
            self._fill = 0
        if f["clear"]:
            self.ring.clear()

    def _w_dma_release(self, f):
        self.ring.rd += f["sectors"] * _BLOCK

    def _r_dma_status(self):
        return {"busy": self._dma_busy, "sent": self._dma_sent}

    def _r_dma_level(self):
        return {"bytes": self.ring.level}

    def _r_dma_high_water(self):
        return {"bytes": self.ring.high_water}

    def _r_dma_kept(self):
        return {"frames": self.ring.kept}

    def _r_dma_dropped(self):
        return {"frames": self.ring.dropped}

    def _w_dma_buffer_seek(self, f):
        self._buf_index = f["index"] % len(self._buffer)

    def _w_dma_buffer_write(self, f):
        self._buffer[self._buf_index] = f["word"]
        self._buf_index = (self._buf_index + 1) % len(self._buffer)

    def _r_dma_buffer_read(self):
        word = self._buffer[self._buf_index]
        self._buf_index = (self._buf_index + 1) % len(self._buffer)
        return {"word": word}
