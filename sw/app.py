"""The logger's application loop: card, recording, flushes, clock, LEDs and the watchdog.

The loop is an explicit state machine (:class:`State`). Every pass kicks the watchdog, takes
the pending events (``events.status``, write-1-to-clear), sets the RTC from a new ZDA, runs
the current state's step, and shows the state on the LEDs and in ``logger.fw_status``.
Every register is named through :class:`~maglog.sw.regmap.RegisterMap`; nothing here
imports gateware.

Decisions beyond the specification's letter:

* A flush happens on every ``fix`` event, and also when the ring holds more than
  ``AppSettings.high_water_fraction`` of its capacity (a recording without GPS fixes must
  not overflow the ring).
* After a failed SD operation nothing more is written to the card: no metadata can then
  point at data that is not there. The loop drops the volume, shows the error, and
  initialises the card again every ``init_retry_s``. A recording cut short that way, or by
  a watchdog reset, resumes in a new file once a card mounts and the mount finds the volume
  dirty (the file that was being written is kept as its last sync left it).
* The recording starts at the button: the record gate opens before the file is created,
  so the frames that arrive while ``LOGnnnnn.TXT`` is made (a scan of the root directory,
  perhaps its growth) wait in the ring and are the file's first bytes. A press during a
  mount (a dirty card's repair reads the whole FAT) opens the gate at once, between two
  block reads; the file is created when the mount ends.
* A full card ends the recording: what fitted is kept, the file is closed cleanly, and the
  loop waits in :attr:`State.FULL` for a button press to mount a card again.
* A ring overflow (frames dropped) is counted in :attr:`LoggerApp.overflows` (events) and
  :attr:`LoggerApp.dropped` (frames, from ``dma.dropped``), shown as
  :attr:`FwError.RING_OVERFLOW` and by LED1 blinking; the recording goes on.
"""

import datetime as _dt
import enum
from dataclasses import dataclass, field

from .bus import BusTimeout
from .fat32 import (FAT_CACHE_SECTORS, FAT_EPOCH, FatError, FatFullError, FatNoNumberError,
                    Volume)
from .regmap import RegisterMap
from .sdcard import SdError, SdNoCard
from .storage import DmaStorage, flush_ring


__all__ = ["State", "FwError", "Blink", "AppSettings", "LoggerApp", "LED_RECORDING", "LED_FIX"]

#: LED bits of ``leds.value``: LED1 recording, LED2/LED3 (OR'ed with channel activity in
#: hardware), LED4 GPS fix.
LED_RECORDING, LED_2, LED_3, LED_FIX = 1, 2, 4, 8

UNIX_EPOCH = _dt.datetime(1970, 1, 1)


class State(enum.IntEnum):
    """What the application loop does (``logger.fw_status.state``)."""
    INIT      = 1   # waits for a card that identifies and mounts as FAT32 (a try a second)
    IDLE      = 2   # card mounted; waits for a button press to start recording
    RECORDING = 3   # waits for fix events (flush), a full ring (flush) or a press (stop)
    ERROR     = 4   # an SD operation failed; waits `init_retry_s`, then back to INIT
    FULL      = 5   # the card is full, the file closed; waits for a press to mount again


class FwError(enum.IntEnum):
    """What went wrong last (``logger.fw_status.error``; 0: nothing)."""
    NONE          = 0
    NO_CARD       = 1   # no card answers identification
    SD_INIT       = 2   # a card answers but identification failed
    NOT_FAT32     = 3   # the card mounted nothing: no MBR, not FAT32, insane BPB
    SD_IO         = 4   # a block read or write failed (card removed, card error)
    FS_ERROR      = 5   # the file system is inconsistent (a broken chain, ...)
    CARD_FULL     = 6   # no free cluster (or root directory entry) left
    NO_LOG_NUMBER = 7   # LOG99999.TXT exists
    RING_OVERFLOW = 8   # the ring dropped frames while recording (recording goes on)
    TIMEOUT       = 9   # the hardware did not reach a state in time (frame gate, DMA)


@dataclass(frozen=True)
class Blink:
    """LED bits ``mask`` lit for ``on_s`` of every ``period_s`` (``on_s = period_s``:
    steady)."""
    mask: int
    period_s: float
    on_s: float

    def lit(self, now):
        return (now % self.period_s) < self.on_s


def _default_patterns():
    return {
        FwError.NO_CARD:       Blink(LED_2, 1.0, 0.5),
        FwError.SD_INIT:       Blink(LED_2 | LED_3, 1.0, 0.5),
        FwError.NOT_FAT32:     Blink(LED_2 | LED_3, 2.0, 2.0),
        FwError.SD_IO:         Blink(LED_2 | LED_3, 0.5, 0.25),
        FwError.FS_ERROR:      Blink(LED_3, 0.5, 0.25),
        FwError.CARD_FULL:     Blink(LED_RECORDING, 2.0, 1.0),
        FwError.NO_LOG_NUMBER: Blink(LED_RECORDING | LED_3, 2.0, 1.0),
        FwError.RING_OVERFLOW: Blink(LED_RECORDING, 0.5, 0.4),
        FwError.TIMEOUT:       Blink(LED_3, 1.0, 0.5),
    }


@dataclass
class AppSettings:
    """Timings and policies of the application loop.

    ``fault`` is a test hook: ``await fault(app, point)`` runs at named points of the loop
    (``"loop"``, ``"flush"``); a hook that never returns makes the firmware hang, as a bug
    would, so that the watchdog has to act."""
    poll_s: float = 0.002               # time between two passes of the loop
    init_retry_s: float = 1.0           # between two tries to initialise and mount a card
    watchdog_timeout_ms: int = 3000     # a flush with write retries takes under 2 s
    fix_led_s: float = 2.0              # LED4 stays on this long after a fix event
    ring_bytes: int = 16 << 20          # the ring's capacity (the logger's SDRAM)
    high_water_fraction: float = 0.5    # flush without a fix event above this fill
    frame_timeout_s: float = 0.5        # for a frame in flight to pass the gate
    dma_timeout_s: float = 2.0          # for the DMA to go idle
    fat_cache_sectors: int = FAT_CACHE_SECTORS
    resume: bool = True                 # resume an interrupted recording in a new file
    patterns: dict = field(default_factory=_default_patterns)
    fault: object = None

    def __post_init__(self):
        for name in ("poll_s", "init_retry_s", "fix_led_s", "frame_timeout_s",
                     "dma_timeout_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"{name} must be a positive number of seconds, not {value!r}")
        if not isinstance(self.watchdog_timeout_ms, int) or not self.watchdog_timeout_ms > 0:
            raise ValueError(f"watchdog_timeout_ms must be a positive integer, not "
                             f"{self.watchdog_timeout_ms!r}")
        if not 0 < self.high_water_fraction <= 1:
            raise ValueError(f"high_water_fraction must be in (0, 1], not "
                             f"{self.high_water_fraction!r}")
        if not isinstance(self.ring_bytes, int) or self.ring_bytes <= 0:
            raise ValueError(f"ring_bytes must be a positive integer, not {self.ring_bytes!r}")


class LoggerApp:
    """The firmware of the logger.

    Parameters
    ----------
    bus : RegisterBus
    memory_map : amaranth_soc MemoryMap
        The logger's CSR map (windows ``logger``, ``leds``, ``rtc``, ``watchdog``, ``gps``,
        ``events``, ``dma``, ``sdio``).
    sys_clock_hz : float
        The system clock, for the SD clock divisor.
    settings : AppSettings
    """
    def __init__(self, bus, memory_map, *, sys_clock_hz, settings=None):
        self.bus = bus
        self.memory_map = memory_map
        self.sys_clock_hz = sys_clock_hz
        self.settings = AppSettings() if settings is None else settings
        self.regs = {name: RegisterMap(memory_map, window=name)
                     for name in ("logger", "leds", "rtc", "watchdog", "gps", "events")}
        self.state = State.INIT
        self.error = FwError.NONE
        #: The message of the last error (an exception's text).
        self.message = ""
        self.storage = None
        self.volume = None
        self.file = None
        #: Ring overflow events seen while recording, and the frames the ring dropped in
        #: this recording (``dma.dropped`` since its start).
        self.overflows = 0
        self.dropped = 0
        self._dropped_at_start = 0
        #: Flushes done (for tests and a debugger), and the last one's result.
        self.flushes = 0
        self.last_flush = None
        self._resume = False
        self._mounting = None           # the storage being mounted (the press watch)
        self._armed = False             # the gate opened by a press during the mount
        self._retry_at = 0.0
        self._last_fix = None
        self._shown = (None, None)

    # -- registers --------------------------------------------------------------------------

    def _reg(self, window, name):
        return self.regs[window][name]

    async def _read(self, window, name):
        register = self._reg(window, name)
        return register.decode(await self.bus.read(register.address))

    async def _write(self, window, name, **values):
        register = self._reg(window, name)
        await self.bus.write(register.address, register.encode(**values))

    async def _wait_field(self, window, name, field_name, value, timeout, what):
        register = self._reg(window, name)
        bits = register.field(field_name)
        await self.bus.wait_event(register.address, lambda word: bits.extract(word) == value,
                                  timeout=timeout, poll=self.settings.poll_s / 4, what=what)

    async def _kick(self):
        await self._write("watchdog", "kick", kick=1)

    async def _fault(self, point):
        if self.settings.fault is not None:
            await self.settings.fault(self, point)

    # -- the loop ---------------------------------------------------------------------------

    async def run(self):
        """The application loop; never returns."""
        await self._boot()
        steps = {State.INIT: self._step_init, State.IDLE: self._step_idle,
                 State.RECORDING: self._step_recording, State.ERROR: self._step_error,
                 State.FULL: self._step_full}
        while True:
            await self._kick()
            await self._fault("loop")
            events = await self._take_events()
            await self._clock_and_fix(events)
            try:
                await steps[self.state](events)
            except FatFullError as full:
                await self._card_full(full)
            except (SdError, FatError, BusTimeout) as failure:
                await self._fail(failure)
            await self._show()
            await self.bus.wait(self.settings.poll_s)

    async def _boot(self):
        cause = await self._read("watchdog", "status")
        # After a watchdog reset a recording may have been cut short: resume it if the card
        # says so (a dirty volume).
        self._resume = self.settings.resume and bool(cause["reset_cause"])
        await self._write("logger", "control", record=0)
        await self._write("watchdog", "control", enable=1,
                          timeout_ms=self.settings.watchdog_timeout_ms)
        await self._kick()
        await self._show()

    async def _take_events(self):
        register = self._reg("events", "status")
        word = await self.bus.read(register.address)
        if word:
            await self.bus.write(register.address, word)     # write 1 to clear what was seen
        return register.decode(word)

    async def _clock_and_fix(self, events):
        if events["fix"]:
            self._last_fix = self.bus.now()
        if events["zda"]:
            time, date = await self._read("gps", "time"), await self._read("gps", "date")
            try:
                moment = _dt.datetime(date["year"], date["month"], date["day"], time["hour"],
                                      time["minute"], time["second"])
            except ValueError:
                return                                  # a date that does not exist
            seconds = int((moment - UNIX_EPOCH).total_seconds())
            if 0 <= seconds < 1 << 32:
                await self._write("rtc", "seconds", value=seconds)

    async def _now(self):
        """The RTC's time as a datetime for file timestamps (the FAT epoch before 1980)."""
        seconds = (await self._read("rtc", "seconds"))["value"]
        moment = UNIX_EPOCH + _dt.timedelta(seconds=seconds)
        return max(moment, FAT_EPOCH)

    # -- states -----------------------------------------------------------------------------

    async def _step_init(self, events):
        if self.bus.now() < self._retry_at:
            return
        self._retry_at = self.bus.now() + self.settings.init_retry_s
        storage = DmaStorage(self.bus, self.memory_map, sys_clock_hz=self.sys_clock_hz,
                             before_block=self._before_block)
        self._mounting = storage
        try:
            await storage.driver.initialise()
        except SdNoCard as failure:
            self._set_error(FwError.NO_CARD, failure)
            return
        except SdError as failure:
            self._set_error(FwError.SD_INIT, failure)
            return
        try:
            volume = await Volume.mount(storage.device,
                                        fat_cache_sectors=self.settings.fat_cache_sectors)
        except SdError as failure:
            await self._disarm()
            self._set_error(FwError.SD_IO, failure)
            return
        except FatError as failure:
            await self._disarm()
            self._set_error(FwError.NOT_FAT32, failure)
            return
        finally:
            self._mounting = None
        self.storage, self.volume = storage, volume
        self._set_error(FwError.NONE)
        self.state = State.IDLE
        resume, self._resume = self._resume and volume.was_dirty, False
        if self._armed:
            # The button was pressed during the mount (a dirty volume's repair takes a
            # while): that press starts the recording, whose first frames are in the ring.
            register = self._reg("events", "status")
            await self.bus.write(register.address, register.encode(button=1))
            await self._start_recording()
        elif resume:
            await self._start_recording()

    async def _before_block(self):
        """Before each block the card path moves: kick the watchdog; during a mount, a
        button press opens the record gate at once (frames wait in the ring until the
        mount ends and the file exists)."""
        await self._kick()
        if self._mounting is None or self._armed:
            return
        register = self._reg("events", "status")
        if register.decode(await self.bus.read(register.address))["button"]:
            await self._mounting.clear()
            self._dropped_at_start = await self._mounting.read("dropped")
            await self._write("logger", "control", record=1)
            self._armed = True

    async def _disarm(self):
        """Close the gate a press during a failed mount opened."""
        if self._armed:
            self._armed = False
            await self._write("logger", "control", record=0)

    async def _step_idle(self, events):
        if events["button"]:
            await self._start_recording()

    async def _step_recording(self, events):
        if events["ring_overflow"]:
            self.overflows += 1
            self.dropped = await self.storage.read("dropped") - self._dropped_at_start
            self._set_error(FwError.RING_OVERFLOW)
        if events["button"]:
            await self._stop_recording()
            return
        if events["fix"] or await self._ring_high():
            await self._flush()

    async def _step_error(self, events):
        if self.bus.now() >= self._retry_at:
            self.state = State.INIT

    async def _step_full(self, events):
        if events["button"]:
            self._retry_at = 0.0
            self.state = State.INIT

    # -- recording --------------------------------------------------------------------------

    async def _ring_high(self):
        level = await self.storage.read("level")
        return level >= self.settings.high_water_fraction * self.settings.ring_bytes

    async def _quiesce(self):
        """Stop frames entering the ring and wait until none is in flight, then for the DMA
        to be idle."""
        await self._write("logger", "control", record=0)
        await self._wait_field("logger", "status", "in_frame", 0,
                               self.settings.frame_timeout_s, "the frame in flight to end")
        status = self.storage.dma["status"]
        busy = status.field("busy")
        await self.bus.wait_event(status.address, lambda word: not busy.extract(word),
                                  timeout=self.settings.dma_timeout_s, poll=self.settings.poll_s,
                                  what="the DMA to be idle")

    async def _start_recording(self):
        """The recording starts now: the ring is emptied and the gate opened first, then
        the file is created, so that the frames arriving meanwhile (creating the file scans
        and may grow the root directory: many block reads on a card with many files) wait
        in the ring and reach the file with the first flush."""
        if self._armed:                 # the gate opened at the press, during the mount
            self._armed = False
        else:
            await self._quiesce()
            await self.storage.clear()
            self._dropped_at_start = await self.storage.read("dropped")
            await self._write("logger", "control", record=1)
        self.dropped = 0
        try:
            self.file = await self.volume.create_log(await self._now())
        except FatNoNumberError as failure:
            await self._quiesce()
            await self.storage.clear()
            self._set_error(FwError.NO_LOG_NUMBER, failure)
            return
        self.state = State.RECORDING
        self._set_error(FwError.NONE)

    async def _flush(self):
        await self._fault("flush")
        self.last_flush = await flush_ring(self.file, self.storage, await self._now())
        self.flushes += 1

    async def _stop_recording(self):
        await self._quiesce()
        self.dropped = await self.storage.read("dropped") - self._dropped_at_start
        await self._flush()
        await self.file.close(await self._now())
        await self.storage.clear()
        self.file = None
        self.state = State.IDLE
        if self.error == FwError.RING_OVERFLOW:
            self._set_error(FwError.NONE)

    # -- failures ---------------------------------------------------------------------------

    def _set_error(self, code, failure=None):
        self.error = code
        self.message = "" if failure is None else str(failure)

    async def _card_full(self, full):
        """The card took what fitted: close the file cleanly and stop recording."""
        self._set_error(FwError.CARD_FULL, full)
        try:
            # The gate is open from the button on, also while the file is created.
            await self._quiesce()
            if self.file is not None:
                await self.file.close(await self._now())
            elif self.volume is not None:
                await self.volume.close()       # the clean bit back (create_log cleared it)
            await self.storage.clear()
        except (SdError, FatError, BusTimeout) as failure:
            await self._fail(failure)
            return
        self.file = None
        self.state = State.FULL
        self._set_error(FwError.CARD_FULL, full)

    async def _fail(self, failure):
        """An SD operation (or the file system) failed: write nothing more to the card,
        drop the volume, and initialise again after ``init_retry_s``."""
        recording = self.file is not None
        await self._write("logger", "control", record=0)
        if self.storage is not None:
            await self.storage.abort()
        code = (FwError.SD_IO if isinstance(failure, SdError)
                else FwError.TIMEOUT if isinstance(failure, BusTimeout) else FwError.FS_ERROR)
        self._set_error(code, failure)
        self.file = self.volume = self.storage = None
        self._resume = self.settings.resume and recording
        self.state = State.ERROR
        self._retry_at = self.bus.now() + self.settings.init_retry_s

    # -- what shows -------------------------------------------------------------------------

    def _file_number(self):
        return int(self.file.name[3:8]) if self.file is not None else 0

    def led_value(self, now):
        """The firmware's LED bits at time ``now``."""
        value = LED_RECORDING if self.state == State.RECORDING else 0
        pattern = self.settings.patterns.get(self.error)
        if pattern is not None:
            value = (value & ~pattern.mask) | (pattern.mask if pattern.lit(now) else 0)
        if self._last_fix is not None and now - self._last_fix < self.settings.fix_led_s:
            value |= LED_FIX
        return value

    async def _show(self):
        status = (self.state, self.error, self._file_number())
        leds = self.led_value(self.bus.now())
        if status != self._shown[0]:
            await self._write("logger", "fw_status", state=self.state, error=self.error,
                              file=status[2])
        if leds != self._shown[1]:
            await self._write("leds", "value", value=leds)
        self._shown = (status, leds)
