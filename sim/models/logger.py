"""The transaction-level model of the whole logger: DESIGN.md's third backend, ``model``.

The same registers as the gateware's ``Logger`` (hw/top.py), at register, frame, command
and block level, in simulated time that jumps from event to event. The firmware runs on it
unchanged through :attr:`LoggerModel.bus`, a :class:`~maglog.sw.bus.RegisterBus`.

What is modelled, and at which grain:

- Serial lines: bytes back to back from each fed burst, ten bit times each, at the burst's
  own rate; each channel's receiver samples them at the gateware's divisor after reset, as
  hw/uart.py does (sim/models/logger_uart.py: a burst off its rate gets the framing errors
  and resynchronisations the gateware gives it); the frame filter's decisions come from the
  reference filter (sim/models/logger_frontend.py). A kept frame leaves its channel at the
  stop bit of its line end; channels merge whole frames in that order (ties: lower channel
  first). The ``ch{k}_divisor`` registers are stored, not applied: the receivers keep the
  divisor after reset.
- Record gate and ring: a frame is gated at its first byte (stored or drained whole), then
  takes :data:`RING_BYTE_CYCLES` per byte into the SDRAM ring (``logger.status.in_frame``
  meanwhile) and is committed at its last; a frame that does not fit is dropped whole.
- DMA, SD host and card: registers as in hw/dma.py and hw/sdio/host.py; commands and
  responses whole (bit strings with CRC7, checked as the CMD engine checks them), blocks
  whole, each timed in SD clocks at the current divisor; the card (sim/models/logger_sd.py)
  answers at command level and stores a block when its programming ends.
- SoC: LEDs with hardware activity, debounced button, RTC, watchdog, GPS time capture,
  events (write 1 to clear); a watchdog expiry resets everything but the RTC, the watchdog
  and the card, and the firmware (the bus raises :class:`~maglog.sw.bus.HardwareReset`).

A register access costs :data:`ACCESS_CYCLES` system clocks.

The harness::

    model = LoggerModel(card_image, clk_freq=50e6, channels=DEFAULT_CHANNELS, ...)
    model.feed(channel, data, start=seconds)        # bytes back to back on a line
    model.press_button(at, hold=0.2)
    model.cut_power(after_blocks=N) or model.cut_power(at=seconds)
    model.remove_card(at, reinsert=None)
    result = model.run(firmware, until)             # firmware(bus): restarted after resets
    model.call(coroutine)                           # one coroutine on the bus, outside run
    run_system(scenario, firmware, image)           # a SystemScenario, as on the gateware
"""

from __future__ import annotations

import heapq
import math
import re
import time
from collections import deque
from dataclasses import dataclass, field

from ...hw.arch import frames as arch_frames
from ...hw.arch import sd as arch_sd
from ...hw.arch import sdram as arch_sdram
from ...hw.arch import uart as arch_uart
from ...hw.arch.frames import COUNTER_NAMES
from ...hw.frontend import DEFAULT_CHANNELS, ChannelConfig
from ...hw.top import GPS_CHANNEL, Logger
from ...sw.bus import BusTimeout, HardwareReset, PowerCut, RegisterBus
from ...sw.regmap import RegisterMap
from .logger_frontend import ChannelLine, parse_zda
from ..runners.result import SystemResult
from .logger_sd import ModelCard
from .logger_soc import SocPeripherals
from .logger_storage import StoragePath


__all__ = ["LoggerModel", "ModelBus", "RunResult", "SimulationEnd", "ACCESS_CYCLES",
           "RING_BYTE_CYCLES", "logger_memory_map", "run_system"]

#: System clocks per register access. The Logger's WishboneCSRBridge (32-bit CSRs, a 32-bit
#: Wishbone bus of granularity 32) strobes the CSR bus in the access's first cycle, registers
#: the read data and raises ``ack`` in the second, and the master sees ``ack`` in the third;
#: one more for the master to start its next cycle.
ACCESS_CYCLES = 4
#: System clocks per byte from the frame FIFO through the gate into the SDRAM ring: one
#: masked word write per byte, one a clock while the controller keeps the row open (an
#: activate or a refresh now and then costs a few clocks more, not modelled).
RING_BYTE_CYCLES = 1

_BLOCK = arch_sd.BLOCK_BYTES
_INF = math.inf
_CH_REGISTER = re.compile(r"ch(\d+)_(\w+)\Z")
#: Registers whose read has a side effect (never skipped by a fast poll).
_IMPURE_READS = {("rtc", "seconds"), ("dma", "buffer_read")}

class SimulationEnd(BaseException):
    """The run reached its end time (raised by the model's bus; private to the harness)."""


@dataclass
class RunResult:
    """What a :meth:`LoggerModel.run` ended with.

    ``image`` the card image; ``end`` the simulated time (s) the run ended; ``resets`` the
    watchdog resets during the run; ``power_cut`` whether it ended by a power cut;
    ``blocks_written`` blocks the card stored during the run; ``leds`` the LED outputs as
    ``(t, value)`` at every change since power-up; ``frames`` and ``counters`` per channel,
    what the reference filter keeps and counts over all the bytes fed; ``returned`` whether
    the firmware returned (the hardware then ran on to the end)."""
    image: object
    end: float
    resets: int
    power_cut: bool
    blocks_written: int
    leds: list
    frames: list
    counters: list
    returned: bool = False
    flushes: list = field(default_factory=list)


class ModelBus(RegisterBus):
    """The model's register bus: each access and wait moves the model's time on."""
    def __init__(self, model):
        self._model = model

    async def read(self, address):
        return self._model._bus_read(address)

    async def write(self, address, value):
        self._model._bus_write(address, value)

    async def wait(self, seconds):
        self._model._bus_wait(seconds)

    def now(self):
        return self._model.now_s

    async def wait_event(self, address, predicate, *, timeout, poll=1e-6, what="condition"):
        """As :meth:`RegisterBus.wait_event`, the same reads at the same instants, but the
        polls that cannot see a change (no event of the model falls before them) are
        skipped rather than performed."""
        model = self._model
        deadline = self.now() + timeout
        pure = model._pure_read(address)
        period = ACCESS_CYCLES + model._cycles(poll)
        deadline_cycles = math.ceil(deadline * model.clk_freq - 1e-6)
        while True:
            word = await self.read(address)
            if predicate(word):
                return word
            if self.now() >= deadline:
                raise BusTimeout(f"{what} not reached within {timeout} s")
            if pure:
                # Read j after this one samples at sampled + j * period and ends
                # ACCESS_CYCLES - 1 later; the first that can see a change at `change` is
                # the j with sampled + j * period >= change.
                sampled, done = model._sampled_at, model.now
                change = model._next_event_time(after=sampled)
                late = max(1, math.ceil((deadline_cycles - done) / period))
                skip = late if change == _INF else \
                    max(0, math.ceil((change - sampled) / period) - 1)
                if late <= skip:
                    model._advance(done + late * period)
                    raise BusTimeout(f"{what} not reached within {timeout} s")
                if skip:
                    model._advance(done + skip * period)
            await self.wait(poll)


def _sdram_init_s(chip):
    """The SDRAM controller's initialisation: power-up wait, precharge, auto refreshes."""
    t = chip.timing
    return (t.power_up_us * 1e3 + t.t_rp + t.init_refreshes * t.t_rfc) * 1e-9


def _check_seconds(value, what, *, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not \
            (value > 0 if positive else value >= 0) or value == _INF:
        raise ValueError(f"{what} must be a {'positive' if positive else 'non-negative'} "
                         f"number of seconds, not {value!r}")
    return value


def logger_memory_map(*, channels=DEFAULT_CHANNELS, clk_freq=50e6, **parameters):
    """The memory map of the gateware's ``Logger`` (hw/top.py) with these parameters, as its
    Wishbone slave shows it to the firmware."""
    return Logger(channels, clk_freq=clk_freq, **parameters).bus.memory_map


class LoggerModel(SocPeripherals):
    """The logger at transaction level, in simulated time.

    Parameters
    ----------
    card : CardImage
        The card in the slot; blocks are written into it.
    clk_freq : float
        The system clock (Hz): register accesses, the SD clock divisor, the RTC, the
        watchdog and every timer count it.
    channels : sequence of ChannelConfig
        The serial channels, as the gateware's ``channels``.
    chip : arch.sdram.Chip
        The SDRAM chip (its size bounds the ring; its initialisation delays ``sdram_ready``).
    ring_capacity : int or None
        Bytes of ring (a power of two of whole sectors); None: the whole SDRAM chip.
    max_frame : int
        The frame filter's MAX_FRAME.
    debounce_s, led_stretch_s : float
        The button's debounce time and the activity LEDs' stretch.
    seed : int
        Seeds the card's programming and read times.
    memory_map : MemoryMap or None
        The gateware's CSR map; None: :func:`logger_memory_map` of these parameters.
    card_options :
        Passed to :class:`~maglog.sim.models.logger_sd.ModelCard` (``high_capacity``,
        ``version``, ``pre_erase``, ``busy_range``, ``read_range``, ``power_up_s``,
        ``stop_busy_s``).
    """
    def __init__(self, card, *, clk_freq=50e6, channels=DEFAULT_CHANNELS, ring_capacity=None,
                 chip=arch_sdram.MT48LC4M32B2, max_frame=arch_frames.DEFAULT_MAX_FRAME,
                 debounce_s=0.01, led_stretch_s=0.05, seed=0, memory_map=None,
                 **card_options):
        if isinstance(clk_freq, bool) or not isinstance(clk_freq, (int, float)) or \
                not 1e3 <= clk_freq < _INF:
            raise ValueError(f"Clock frequency must be a number of Hz >= 1 kHz, not "
                             f"{clk_freq!r}")
        self.clk_freq = clk_freq
        self.channels = tuple(c if isinstance(c, ChannelConfig) else ChannelConfig(*c)
                              for c in channels)
        if not self.channels:
            raise ValueError("The logger needs at least one channel")
        chip_bytes = chip.geometry.words * chip.geometry.data_width // 8
        if ring_capacity is None:
            ring_capacity = chip_bytes
        if isinstance(ring_capacity, bool) or not isinstance(ring_capacity, int) or \
                ring_capacity & (ring_capacity - 1) or ring_capacity % _BLOCK or \
                not _BLOCK <= ring_capacity <= chip_bytes:
            raise ValueError(f"Ring capacity must be a power of two of whole sectors, at most "
                             f"{chip_bytes} bytes, not {ring_capacity!r}")
        _check_seconds(debounce_s, "Debounce time", positive=True)
        _check_seconds(led_stretch_s, "LED stretch", positive=True)
        self.image = card
        self.card = ModelCard(card, seed=seed, **card_options)
        self.memory_map = memory_map if memory_map is not None else logger_memory_map(
            channels=self.channels, clk_freq=clk_freq, chip=chip, ring_capacity=ring_capacity,
            max_frame=max_frame, debounce_s=debounce_s, led_stretch_s=led_stretch_s)
        # Each receiver at the gateware's divisor after reset (hw/frontend.py's
        # divisor_for: the nearest one to the nominal rate).
        self._lines = [ChannelLine(k, c.kind, max_frame=max_frame, clk_freq=clk_freq,
                                   divisor=max(1, round(clk_freq / (arch_uart.OVERSAMPLING
                                                                    * c.baud))))
                       for k, c in enumerate(self.channels)]
        self.gps_channel = min(GPS_CHANNEL, len(self.channels) - 1)
        self._debounce = max(1, round(debounce_s * clk_freq))
        self._stretch = max(1, round(led_stretch_s * clk_freq))
        self._prescaler = round(clk_freq / 1000)
        self._sdram_init = self._cycles(_sdram_init_s(chip))
        self.bus = ModelBus(self)

        self.now = 0
        self._queue, self._seq = [], 0
        self._next_due = -1             # no event before this cycle (-1: look)
        self._last_event = 0            # the last cycle an event was processed
        self._sampled_at = 0            # the cycle the last register read sampled
        self._epoch = 0
        self._until = None
        self._power_off = False
        self._cut_after = None
        self.resets = 0
        self._fe, self._fe_pos, self._fe_dirty = [], 0, False
        self._fe_taken = [0] * len(self.channels)
        self._leds = [(0.0, 0)]
        self._rtc_base, self._rtc_set, self._rtc_latched = 0, 0, 0
        self._wd_enable, self._wd_timeout, self._wd_cause = 0, 1000, 0
        self._wd_deadline = _INF
        self._btn_sync = 0
        self._btn_gen = 0
        self._flush_times = []
        self.storage = StoragePath(self, ring_capacity)
        self._bind(self.memory_map)
        self._reset_hardware()

    # -- time ---------------------------------------------------------------------------------

    def _cycles(self, seconds):
        return round(seconds * self.clk_freq)

    @property
    def now_s(self):
        """The model's time in seconds since power-up."""
        return self.now / self.clk_freq

    def _schedule(self, when, fn, *args, hardware=True):
        """Call ``fn(*args)`` at cycle ``when``; a ``hardware`` event is forgotten when the
        logger is reset before it (the card's and the world's events are not)."""
        self._seq += 1
        heapq.heappush(self._queue, (when, self._seq, fn, args,
                                     self._epoch if hardware else None))
        self._next_due = min(self._next_due, when)

    def _heads(self):
        """The times of the next front-end decision, gate step, queued event and watchdog
        expiry."""
        if self._fe_dirty:
            self._rebuild_frontend()
        t_fe = self._fe[self._fe_pos].time if self._fe_pos < len(self._fe) else _INF
        path = self._path
        t_path = (path[0][0] if path[0][1] is None else path[0][1]) if path else _INF
        t_queue = self._queue[0][0] if self._queue else _INF
        return t_fe, t_path, t_queue, self._wd_deadline

    def _next_event_time(self, *, after):
        """The first cycle after ``after`` (at most now) at which a register may read
        differently."""
        t = min(self._heads())
        if self._last_event > after:
            t = min(t, self._last_event)
        # Changes that are comparisons with the time rather than events.
        for when in (self._sdram_ready_at, *self.storage.changes()):
            if when > after:
                t = min(t, when)
        if self._until is not None:
            t = min(t, self._until)
        return t

    def _advance(self, target):
        """Process every event up to cycle ``target`` and stand there."""
        if self._power_off:
            raise PowerCut("the power is off")
        if self._until is not None and target >= self._until:
            self._advance_to(self._until)
            raise SimulationEnd(f"the run reached {self.now_s} s")
        if target < self._next_due:         # nothing happens before: a register access
            self.now = max(self.now, target)
            return
        self._advance_to(target)

    def _advance_to(self, target):
        # (The heads of _heads, inlined: this runs twice for every register access.)
        fe, path, queue = self._fe, self._path, self._queue
        while True:
            if self._fe_dirty:
                self._rebuild_frontend()
                fe = self._fe
            t_fe = fe[self._fe_pos].time if self._fe_pos < len(fe) else _INF
            t_path = (path[0][0] if path[0][1] is None else path[0][1]) if path else _INF
            t_queue = queue[0][0] if queue else _INF
            t = min(t_fe, t_path, t_queue, self._wd_deadline)
            if t > target:
                # Until then nothing happens, unless something new is scheduled earlier
                # (_schedule, a kick and feed lower this; lower than true is only slower).
                self._next_due = t
                break
            if t > self.now:
                self.now = t
            self._last_event = t
            if t_fe == t:
                decision = fe[self._fe_pos]
                self._fe_pos += 1
                self._fe_taken[decision.channel] += 1
                self._decide(decision)
            elif t_path == t:
                self._pass_gate()
            elif t_queue == t:
                _, _, fn, args, epoch = heapq.heappop(queue)
                if epoch is None or epoch == self._epoch:
                    fn(*args)
            else:
                self._watchdog_fire()
            path = self._path               # (a reset makes a new one)
        if target > self.now:
            self.now = target

    # -- the harness --------------------------------------------------------------------------

    def feed(self, channel, data, *, start, baud=None):
        """Bytes on channel ``channel``'s line, back to back from ``start`` seconds, at
        ``baud`` (default: the channel's nominal rate). Each channel is fed in time order."""
        if isinstance(channel, bool) or not isinstance(channel, int) or \
                not 0 <= channel < len(self.channels):
            raise ValueError(f"Channel must be in 0..{len(self.channels) - 1}, not {channel!r}")
        _check_seconds(start, "Start")
        if self._cycles(start) < self.now:
            raise ValueError(f"Bytes from {start} s are in the model's past ({self.now_s} s)")
        self._lines[channel].feed(data, start=start,
                                  baud=self.channels[channel].baud if baud is None else baud)
        self._fe_dirty = True
        self._next_due = -1

    def press_button(self, at, *, hold=0.2):
        """The button goes down at ``at`` seconds for ``hold`` seconds."""
        _check_seconds(at, "Press time")
        _check_seconds(hold, "Hold time", positive=True)
        if self._cycles(at) < self.now:
            raise ValueError(f"A press at {at} s is in the model's past ({self.now_s} s)")
        self._schedule(self._cycles(at), self._button_input, 1, hardware=False)
        self._schedule(self._cycles(at + hold), self._button_input, 0, hardware=False)

    def play(self, scenario):
        """Feed a :class:`~maglog.sim.stimulus.system.SystemScenario`'s bursts (each at its
        own rate) and schedule its button presses."""
        for burst in scenario.bursts:
            self.feed(burst.channel, burst.data, start=burst.start, baud=burst.baud)
        for press in scenario.presses:
            self.press_button(press, hold=scenario.hold)

    def cut_power(self, after_blocks=None, at=None):
        """Cut the power after the card has stored ``after_blocks`` more blocks, or at
        ``at`` seconds, whichever comes first; the next bus access raises PowerCut."""
        if after_blocks is None and at is None:
            raise ValueError("A power cut needs after_blocks or at")
        if after_blocks is not None:
            if isinstance(after_blocks, bool) or not isinstance(after_blocks, int) or \
                    after_blocks < 0:
                raise ValueError(f"Blocks before the cut must be an integer >= 0, not "
                                 f"{after_blocks!r}")
            self._cut_after = after_blocks
            if after_blocks == 0:
                self._power_off = True
        if at is not None:
            _check_seconds(at, "Power cut time")
            self._schedule(max(self.now, self._cycles(at)), self._power_cut, hardware=False)

    def remove_card(self, at, *, reinsert=None):
        """The card leaves the slot at ``at`` seconds (commands get no response), and comes
        back, powered up afresh, at ``reinsert`` seconds if given."""
        _check_seconds(at, "Removal time")
        self._schedule(max(self.now, self._cycles(at)), self.card.remove, hardware=False)
        if reinsert is not None:
            _check_seconds(reinsert, "Reinsertion time")
            if reinsert <= at:
                raise ValueError(f"Reinsertion must come after the removal at {at} s, not "
                                 f"{reinsert!r}")
            self._schedule(self._cycles(reinsert), self.card.insert, hardware=False)

    def run(self, firmware, until):
        """Run ``firmware(bus)`` (a coroutine function that never returns) until ``until``
        seconds or a power cut, restarting it after each watchdog reset."""
        _check_seconds(until, "End time")
        end = self._cycles(until)
        if end < self.now:
            raise ValueError(f"The run cannot end at {until} s, before the model's time "
                             f"{self.now_s} s")
        resets, blocks = self.resets, self.card.blocks_written
        returned = power_cut = False
        self._until = end
        try:
            while True:
                try:
                    self._drive(firmware(self.bus))
                except HardwareReset:
                    continue
                returned = True
                self._advance(end)
        except SimulationEnd:
            pass
        except PowerCut:
            power_cut = True
        finally:
            self._until = None
        references = [line.reference() for line in self._lines]
        return RunResult(
            image=self.image, end=self.now_s, resets=self.resets - resets,
            power_cut=power_cut, blocks_written=self.card.blocks_written - blocks,
            leds=list(self._leds), frames=[r.frames for r in references],
            counters=[r.counters for r in references], returned=returned,
            flushes=list(self._flush_times))

    def call(self, coroutine):
        """Run one coroutine on the model's bus to its end (outside :meth:`run`) and return
        its result."""
        return self._drive(coroutine)

    @staticmethod
    def _drive(coroutine):
        try:
            coroutine.send(None)
        except StopIteration as stop:
            return stop.value
        coroutine.close()
        raise RuntimeError("The firmware awaited something other than the model's bus; on "
                           "this backend only the bus moves time")

    @property
    def leds(self):
        """The LED outputs as ``(t, value)`` at every change."""
        return list(self._leds)

    # -- power, resets ------------------------------------------------------------------------

    def _power_cut(self):
        self._power_off = True
        raise PowerCut(f"the power was cut at {self.now_s} s")

    def _reset_hardware(self):
        """The state every reset (power-up, watchdog) sets: all but the RTC, the watchdog
        and the card."""
        self._epoch += 1
        now = self.now
        # Front end: a frame being received is lost with the filter's state.
        self._counters = [dict.fromkeys(COUNTER_NAMES, 0) for _ in self.channels]
        self._divisors = [0] * len(self.channels)
        self._fe_reset_at = now
        # Record gate, ring, SDRAM controller.
        self._record = 0
        # Frames from the front end to the ring: [start, end (None: not at the gate yet),
        # frame, stored, fits, channel].
        self._path = deque()
        self._path_free = now
        self._sdram_ready_at = now + self._sdram_init
        self.storage.reset()
        # SoC.
        self._led_value = 0
        self._act_until = [now, now]
        self._act_pending = [False, False]
        self._events = set()
        self._gps = None
        self._fw_status = {"state": 0, "error": 0, "file": 0}
        self._btn_level = 0
        self._btn_gen += 1
        if self._btn_sync:
            self._schedule(now + self._debounce, self._button_settle, self._btn_gen)
        self._update_leds()

    def _block_stored(self):
        """The card has stored a block: count it towards a power cut."""
        if self._cut_after is not None:
            self._cut_after -= 1
            if self._cut_after <= 0:
                self._cut_after = None
                self._power_cut()

    # -- front end, record gate, ring -----------------------------------------------------------

    def _rebuild_frontend(self):
        self._fe_dirty = False
        remaining = []
        for k, line in enumerate(self._lines):
            remaining.extend(line.decisions()[self._fe_taken[k]:])
        remaining.sort(key=lambda d: (d.time, d.channel))
        self._fe, self._fe_pos = remaining, 0

    def _decide(self, decision):
        if decision.start < self._fe_reset_at:
            return                      # the filter was reset inside this frame
        counters = self._counters[decision.channel]
        counters[decision.outcome] = (counters[decision.outcome] + 1) & 0xFFFFFFFF
        if decision.frame is None:
            return
        frame = decision.frame
        if decision.flush:                  # the filter's flush strobe, at the line end
            self._flush_times.append(self.now_s)
            self._event("fix")
        start = max(self.now, self._path_free)
        self._path_free = start + len(frame) * RING_BYTE_CYCLES
        self._path.append([start, None, frame, False, False, decision.channel])

    def _pass_gate(self):
        """The head frame of the path reaches the gate (its first byte: stored or drained
        whole) or has passed it (its last byte: committed to the ring)."""
        head = self._path[0]
        start, end, frame, stored, fits, channel = head
        if end is None:
            head[1] = start + len(frame) * RING_BYTE_CYCLES
            if self._record:
                head[3] = True
                if self.storage.ring.fits(len(frame)):
                    self.storage.ring.store(frame)
                    head[4] = True
                else:
                    self.storage.ring.dropped = (self.storage.ring.dropped + 1) & 0xFFFFFFFF
                    self._event("ring_overflow")
            return
        self._path.popleft()
        if fits:
            self.storage.ring.commit_frame(self.now, len(frame))
        # The channel's last byte has left it: its kept strobe (activity LEDs), and the GPS
        # time capture that watches the front end's output.
        if channel < 2:
            self._activity(channel)
        if channel == self.gps_channel:
            zda = parse_zda(frame)
            if zda is not None:
                self._gps = zda
                self._event("zda")

    @property
    def _in_frame(self):
        """The gate passes a frame into the ring (from its first byte to its last)."""
        return int(bool(self._path) and self._path[0][0] <= self.now and self._path[0][3])

    # -- registers ------------------------------------------------------------------------------

    def _bind(self, memory_map):
        """Address -> (window, register, read, write), for every register of the map; a
        register the model does not implement is an error here, a field at first access."""
        windows = []
        for info in memory_map.all_resources():
            window = "_".join(str(p) for p in info.path[0])
            if window not in windows:
                windows.append(window)
        self._registers = {}
        self._checked = set()           # registers whose fields have been compared
        for window in windows:
            for reg in RegisterMap(memory_map, window=window):
                read, write = self._handlers(window, reg.name)
                if ("r" in reg.access) != (read is not None) or \
                        ("w" in reg.access) != (write is not None):
                    raise KeyError(f"Register {window}.{reg.name} is {reg.access!r} in the "
                                   f"gateware; the model has "
                                   f"{'r' if read else ''}{'w' if write else ''}")
                self._registers[reg.address] = (window, reg, read, write)

    def _handlers(self, window, name):
        if window == "frontend":
            match = _CH_REGISTER.match(name)
            if match and int(match[1]) < len(self.channels):
                k, what = int(match[1]), match[2]
                if what == "divisor":
                    return (lambda: {"value": self._divisors[k]},
                            lambda f: self._divisors.__setitem__(k, f["value"]))
                if what in COUNTER_NAMES:
                    return (lambda: {"count": self._counters[k][what]}), None
        owner = self.storage if window in ("sdio", "dma") else self
        read = getattr(owner, f"_r_{window}_{name}", None)
        write = getattr(owner, f"_w_{window}_{name}", None)
        if read is None and write is None:
            raise KeyError(f"The logger model has no register {window}.{name}")
        return read, write

    def _pure_read(self, address):
        entry = self._registers.get(address)
        return entry is not None and (entry[0], entry[1].name) not in _IMPURE_READS

    def _register(self, address):
        if self._power_off:
            raise PowerCut("the power is off")
        try:
            return self._registers[address]
        except KeyError:
            raise KeyError(f"No register at word address {address:#x} of the logger's "
                           f"memory map") from None

    def _bus_read(self, address):
        window, reg, read, _ = self._register(address)
        start = self.now
        self._advance(start + 1)            # the CSR strobe's edge
        self._sampled_at = self.now
        fields = read() if read is not None else None
        self._advance(start + ACCESS_CYCLES)
        if fields is None:
            return 0
        if reg.address not in self._checked:
            extra = set(fields) - set(reg.fields)
            if extra:
                raise KeyError(f"The model gives {window}.{reg.name} fields the gateware "
                               f"lacks: {', '.join(sorted(extra))}")
            self._checked.add(reg.address)
        word = 0
        for name, f in reg.fields.items():
            try:
                value = fields[name]
            except KeyError:
                raise KeyError(f"The model lacks field {name!r} of {window}.{reg.name}") \
                    from None
            word |= (int(value) & ((1 << f.width) - 1)) << f.offset
        return word

    def _bus_write(self, address, value):
        window, reg, _, write = self._register(address)
        start = self.now
        self._advance(start + 1)            # the CSR strobe's edge
        if write is not None:
            write(reg.decode(value & 0xFFFFFFFF))
        self._advance(start + ACCESS_CYCLES)

    def _bus_wait(self, seconds):
        _check_seconds(seconds, "Wait")
        self._advance(self.now + self._cycles(seconds))


def run_system(scenario, firmware, image, *, card_seed=0, ring_capacity=None, **card_options):
    """Run a :class:`~maglog.sim.stimulus.system.SystemScenario` on the model, as
    :func:`maglog.sim.backends.amaranth.run_system` runs it on the gateware: ``firmware(bus,
    memory_map, sys_clock_hz)`` until ``scenario.until``, the card holding ``image``
    (changed in place). Returns a :class:`~maglog.sim.runners.result.SystemResult`."""
    model = LoggerModel(image, clk_freq=scenario.clk_freq, channels=scenario.channels,
                        ring_capacity=ring_capacity, max_frame=scenario.max_frame,
                        debounce_s=scenario.debounce_s, seed=card_seed, **card_options)
    for burst in scenario.bursts:
        model.feed(burst.channel, burst.data, start=burst.start)
    for press in scenario.presses:
        model.press_button(press, hold=scenario.hold)
    start = time.perf_counter()
    result = model.run(lambda bus: firmware(bus, model.memory_map, scenario.clk_freq),
                       until=scenario.until)
    return SystemResult(image=image, led=result.leds[-1][1], seconds=result.end,
                        wall_seconds=time.perf_counter() - start)
