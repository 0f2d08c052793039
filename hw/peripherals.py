"""SoC peripherals of the logger: LEDs, button, real-time clock, watchdog, events, GPS time.

Each is a :class:`wiring.Component` with its own amaranth-soc CSR bus (32-bit words) and
memory map; the logger's top puts them behind one CSR decoder, one window each.
"""

from amaranth import *
from amaranth.lib import wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from .arbiter import TaggedFrameByte
from .arch import frames as arch
from .soc import WordBridge, csr


__all__ = ["RWStrobed", "Leds", "Button", "Rtc", "Watchdog", "Events", "GpsTime",
           "tap_signature"]

#: The RTC and the watchdog count milliseconds.
MILLIS_PER_SECOND = 1000

# Ref: NMEA 0183 v4.11 §6.3 ZDA: `$ccZDA,hhmmss.ss,xx,xx,xxxx,xx,xx*hh`: UTC time, day
#      (01-31), month (01-12), year (4 digits), local zone hours and minutes.
ZDA_ADDRESS = b"ZDA,"                # after the two talker letters
ZDA_TIME_DIGITS = 6                  # hhmmss, then an optional `.` and decimals
ZDA_DATE_DIGITS = (2, 2, 4)          # day, month, year: NMEA's fixed widths


def _check_frequency(clk_freq):
    if not isinstance(clk_freq, (int, float)) or isinstance(clk_freq, bool) or clk_freq <= 0:
        raise ValueError(f"Clock frequency must be a positive number, not {clk_freq!r}")


def _millisecond_prescaler(clk_freq):
    _check_frequency(clk_freq)
    if clk_freq < MILLIS_PER_SECOND:
        raise ValueError(f"Clock frequency must be at least 1 kHz to count milliseconds, "
                         f"not {clk_freq!r}")
    return round(clk_freq / MILLIS_PER_SECOND)


def _bus_members(regs):
    return In(csr.Signature(addr_width=regs.addr_width, data_width=regs.data_width))


def _builder(registers):
    """A builder with room for ``registers`` 32-bit registers."""
    return csr.Builder(addr_width=max(1, ceil_log2(registers)), data_width=32, granularity=8)


class RWStrobed(csr.FieldAction):
    """A read/write field whose storage lives in the component that owns the register.

    Unlike :class:`csr.action.RW`, the component sees both strobes (to act on a read or a
    write, as the RTC latches its sub-second count when the seconds are read) and can change
    the value on its own (the watchdog clears its enable when it fires).

    Members
    -------
    r_data : ``In(shape)``: the value a read returns.
    r_stb : ``Out(1)``: the register is being read.
    w_data : ``Out(shape)``; w_stb : ``Out(1)``: the register is being written.
    """
    def __init__(self, shape):
        super().__init__(shape, access="rw", members={
            "r_data": In(shape),
            "r_stb":  Out(1),
            "w_data": Out(shape),
            "w_stb":  Out(1),
        })

    def elaborate(self, platform):
        m = Module()
        m.d.comb += [
            self.port.r_data.eq(self.r_data),
            self.r_stb.eq(self.port.r_stb),
            self.w_data.eq(self.port.w_data),
            self.w_stb.eq(self.port.w_stb),
        ]
        return m


class _CsrComponent(wiring.Component):
    """A component whose registers (one bus word each) sit behind its own WordBridge."""
    def __init__(self, regs, members):
        self._bridge = WordBridge(regs.as_memory_map())
        super().__init__({"bus": _bus_members(regs), **members})
        self.bus.memory_map = self._bridge.bus.memory_map

    def _elaborate_bridge(self):
        m = Module()
        m.submodules.bridge = self._bridge
        wiring.connect(m, wiring.flipped(self.bus), self._bridge.bus)
        return m


def _tick_members(shared_tick):
    return {"tick": In(1)} if shared_tick else {}


def _free_running_tick(m, clk_freq):
    """A one-cycle pulse every millisecond, from a prescaler of the component's own."""
    cycles = _millisecond_prescaler(clk_freq)
    tick = Signal(name="tick")
    if cycles == 1:
        m.d.comb += tick.eq(1)
        return tick
    # A down-counter reaching zero: a narrow equality, no compare against the period.
    count = Signal(range(cycles), init=cycles - 1, name="prescaler")
    m.d.comb += tick.eq(count == 0)
    m.d.sync += count.eq(Mux(tick, cycles - 1, count - 1))
    return tick


class _Ticked(_CsrComponent):
    """A component counting the RTC's milliseconds (``shared_tick``) or its own."""
    def __init__(self, clk_freq, shared_tick, regs, members):
        self._clk_freq = clk_freq
        self._shared_tick = bool(shared_tick)
        _millisecond_prescaler(clk_freq)
        super().__init__(regs, {**members, **_tick_members(shared_tick)})

    def _millisecond(self, m):
        if self._shared_tick:
            return self.tick
        return _free_running_tick(m, self._clk_freq)


def _milliseconds(seconds, what):
    """Whole milliseconds in ``seconds`` (at least one)."""
    if not isinstance(seconds, (int, float)) or isinstance(seconds, bool) or seconds <= 0:
        raise ValueError(f"{what} must be a positive number of seconds, not {seconds!r}")
    return max(1, round(seconds * MILLIS_PER_SECOND))


_SHARED_TICK_DOC = """
    shared_tick : bool
        Count the milliseconds of a ``tick`` input (the RTC's ``tick``, shared by the
        logger's peripherals) instead of a prescaler of its own."""


class Leds(_Ticked):
    """The four LEDs: firmware-driven, two of them also lit by hardware activity.

    ``led[0]`` = ``value[0]`` (recording), ``led[3]`` = ``value[3]`` (GPS fix);
    ``led[1]`` = ``value[1]`` or a pulse of ``activity[0]`` in the last ``stretch_s``
    (a kept magnetometer frame), ``led[2]`` likewise with ``activity[1]`` (a kept GPS frame).
    The stretch is counted in whole milliseconds: a pulse lights its LED for ``stretch_s``
    (rounded to the millisecond) up to a millisecond more.

    Parameters
    ----------
    clk_freq : float
    stretch_s : float
        How long an activity pulse lights its LED (at least a millisecond).""" + \
        _SHARED_TICK_DOC + """

    Members
    -------
    bus : ``In(csr.Signature(...))``
    activity : ``In(2)``: one-cycle pulses.
    led : ``Out(4)``
    tick : ``In(1)`` (with ``shared_tick``): a one-cycle pulse every millisecond.
    """

    class Value(csr.Register, access="rw"):
        """The firmware's LED bits: bit 0 LED1 (recording), bit 3 LED4 (GPS fix); bits 1
        and 2 light LED2 and LED3, which the magnetometer's and the GPS's kept frames also
        light for a moment."""
        value: csr.Field(csr.action.RW, 4)

    def __init__(self, clk_freq, stretch_s=0.05, *, shared_tick=False):
        _check_frequency(clk_freq)
        self._stretch = _milliseconds(stretch_s, "Activity stretch")
        regs = _builder(1)
        self._value = regs.add("value", self.Value())
        super().__init__(clk_freq, shared_tick, regs, {"activity": In(2), "led": Out(4)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        tick = self._millisecond(m)
        value = self._value.f.value.data
        lit = []
        for k in range(2):
            # A pulse lights the LED for `stretch` + 1 ticks, the first of which may come at
            # once (a new pulse starts them again).
            remaining = Signal(range(self._stretch + 2), name=f"remaining_{k}")
            with m.If(self.activity[k]):
                m.d.sync += remaining.eq(self._stretch + 1)
            with m.Elif(tick & (remaining != 0)):
                m.d.sync += remaining.eq(remaining - 1)
            lit.append(remaining != 0)
        m.d.comb += self.led.eq(Cat(value[0], value[1] | lit[0], value[2] | lit[1], value[3]))
        return m


class Button(_Ticked):
    """The push button, synchronised and debounced.

    The asynchronous ``button`` (high = pressed) goes through a two-stage synchroniser; the
    debounced ``level`` takes the synchronised value once it has differed from ``level``
    for ``debounce_s`` without a break, so bounce and glitches shorter than that are never
    seen. The time is counted in whole milliseconds: ``level`` follows a settled input
    after ``debounce_s`` (rounded to the millisecond) up to a millisecond more. ``press``
    pulses for one cycle as ``level`` rises.

    Parameters
    ----------
    clk_freq : float
    debounce_s : float""" + _SHARED_TICK_DOC + """

    Members
    -------
    bus : ``In(csr.Signature(...))``
    button : ``In(1)``; level : ``Out(1)``; press : ``Out(1)``
    tick : ``In(1)`` (with ``shared_tick``): a one-cycle pulse every millisecond.
    """

    class Status(csr.Register, access="r"):
        """The debounced button level (1 = pressed)."""
        level: csr.Field(csr.action.R, 1)

    def __init__(self, clk_freq, debounce_s=0.01, *, shared_tick=False):
        _check_frequency(clk_freq)
        self._debounce = _milliseconds(debounce_s, "Debounce time")
        regs = _builder(1)
        self._status = regs.add("status", self.Status())
        super().__init__(clk_freq, shared_tick, regs,
                         {"button": In(1), "level": Out(1), "press": Out(1)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        tick = self._millisecond(m)
        synced = Signal()
        m.submodules.sync = FFSynchronizer(self.button, synced, stages=2)

        # Ticks seen while synced has differed from level: the first may come at once, so
        # `debounce` + 1 of them make at least `debounce` milliseconds.
        differing = Signal(range(self._debounce + 1))
        m.d.sync += self.press.eq(0)
        with m.If(synced == self.level):
            m.d.sync += differing.eq(0)
        with m.Elif(tick):
            with m.If(differing == self._debounce):
                m.d.sync += [self.level.eq(synced), self.press.eq(synced), differing.eq(0)]
            with m.Else():
                m.d.sync += differing.eq(differing + 1)
        m.d.comb += self._status.f.level.r_data.eq(self.level)
        return m


class Rtc(_CsrComponent):
    """Real-time clock: seconds and milliseconds, counted from the system clock.

    A millisecond is ``round(clk_freq / 1000)`` clocks, so the clock runs off by the
    rounding error (none at the boards' 50 MHz). ``tick`` pulses at each millisecond, for
    the peripherals that count milliseconds (built with ``shared_tick``).

    Members
    -------
    bus : ``In(csr.Signature(...))``
    tick : ``Out(1)``: a one-cycle pulse every millisecond (a write of the seconds starts
        the millisecond again).
    """

    class Seconds(csr.Register, access="rw"):
        """Seconds (the firmware's epoch: since 1970-01-01 UTC). Reading latches the
        millisecond count into `subsec`; writing sets the seconds and zeroes the
        millisecond count."""
        value: csr.Field(RWStrobed, 32)

    class Subsec(csr.Register, access="r"):
        """Milliseconds (0-999) into the second, as they were at the last `seconds` read."""
        millis: csr.Field(csr.action.R, 10)

    def __init__(self, clk_freq):
        self._prescaler = _millisecond_prescaler(clk_freq)
        regs = _builder(2)
        self._seconds = regs.add("seconds", self.Seconds())
        self._subsec = regs.add("subsec", self.Subsec())
        super().__init__(regs, {"tick": Out(1)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        cycles    = self._prescaler
        prescaler = Signal(range(cycles), init=cycles - 1)   # counts down to the tick
        millis    = Signal(range(MILLIS_PER_SECOND))
        seconds   = Signal(32)
        latched   = Signal(range(MILLIS_PER_SECOND), reset_less=True)
        field = self._seconds.f.value

        # seconds + 1 with a short carry path: which bytes of the seconds are all ones is
        # registered (the seconds stand still for a whole second before they count on).
        full_bytes = Signal(4)
        m.d.sync += full_bytes.eq(Cat(seconds[8 * k:8 * k + 8].all() for k in range(4)))
        next_seconds = Cat(
            (seconds[8 * k:8 * k + 8] + full_bytes[:k].all())[:8] for k in range(4))

        # `tick` is high while the prescaler is at 0, from a flip-flop of its own (it starts
        # the RTC's longer paths).
        m.d.sync += prescaler.eq(Mux(self.tick, cycles - 1, prescaler - 1))
        if cycles == 1:
            m.d.comb += self.tick.eq(1)
        else:
            tick = Signal()
            m.d.sync += tick.eq(prescaler == 1)
            with m.If(field.w_stb):
                m.d.sync += tick.eq(0)
            m.d.comb += self.tick.eq(tick)
        with m.If(self.tick):
            with m.If(millis == MILLIS_PER_SECOND - 1):
                m.d.sync += [millis.eq(0), seconds.eq(next_seconds)]
            with m.Else():
                m.d.sync += millis.eq(millis + 1)
        with m.If(field.w_stb):
            m.d.sync += [seconds.eq(field.w_data), millis.eq(0), prescaler.eq(cycles - 1)]
        # The read takes the seconds of this cycle, so the latched milliseconds belong to them.
        with m.If(field.r_stb):
            m.d.sync += latched.eq(millis)
        m.d.comb += [
            field.r_data.eq(seconds),
            self._subsec.f.millis.r_data.eq(latched),
        ]
        return m


class Watchdog(_Ticked):
    """Fires when the firmware, having enabled it, stops kicking it.

    While ``enable`` is set, milliseconds are counted down from ``timeout_ms`` since the
    last kick (or write of ``control``); when they have run out, ``fire`` pulses for one
    cycle, ``enable`` goes back to 0 and ``reset_cause`` is set. The milliseconds are whole
    ones of a free-running count, so it fires between ``timeout_ms`` and ``timeout_ms`` + 1
    milliseconds after the kick. The top resets the rest of the logger with ``fire``; this
    component is outside that reset, so ``reset_cause`` tells the restarted firmware what
    happened, until the domain's own reset (the external ``rst``) clears it.

    Parameters
    ----------
    clk_freq : float""" + _SHARED_TICK_DOC + """

    Members
    -------
    bus : ``In(csr.Signature(...))``
    fire : ``Out(1)``
    tick : ``In(1)`` (with ``shared_tick``): a one-cycle pulse every millisecond.
    """

    class Control(csr.Register, access="rw"):
        """`enable` starts the watchdog (it goes back to 0 when the watchdog fires);
        `timeout_ms`: milliseconds without a kick before it fires (up to one more; 0 fires
        within a millisecond). Writing restarts the count."""
        enable:     csr.Field(RWStrobed, 1)
        timeout_ms: csr.Field(csr.action.RW, 16, init=1000)

    class Kick(csr.Register, access="w"):
        """Writing 1 restarts the count."""
        kick: csr.Field(csr.action.W, 1)

    class Status(csr.Register, access="r"):
        """`reset_cause` 1: the watchdog has fired since the last external reset."""
        reset_cause: csr.Field(csr.action.R, 1)

    def __init__(self, clk_freq, *, shared_tick=False):
        regs = _builder(3)
        self._control = regs.add("control", self.Control())
        self._kick = regs.add("kick", self.Kick())
        self._status = regs.add("status", self.Status())
        super().__init__(clk_freq, shared_tick, regs, {"fire": Out(1)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        tick        = self._millisecond(m)
        enable      = Signal()
        reset_cause = Signal()
        # Whole milliseconds left before it fires; loaded while disabled (as after a reset),
        # so it needs no reset of its own.
        remaining   = Signal(16, reset_less=True)
        control, kick = self._control.f, self._kick.f.kick
        m.d.comb += [
            control.enable.r_data.eq(enable),
            self._status.f.reset_cause.r_data.eq(reset_cause),
        ]

        # A write of `control` stores its timeout at the write's edge: the count restarts
        # from it in the next cycle too.
        written = Signal()
        m.d.sync += written.eq(control.enable.w_stb)
        restart = written | control.enable.w_stb | (kick.w_stb & kick.w_data) | ~enable
        with m.If(restart):
            m.d.sync += remaining.eq(control.timeout_ms.data)
        with m.Elif(tick & (remaining != 0)):
            m.d.sync += remaining.eq(remaining - 1)
        with m.If(control.enable.w_stb):
            m.d.sync += enable.eq(control.enable.w_data)

        m.d.sync += self.fire.eq(0)
        # The tick that finds nothing left fires: the first tick after a restart may come at
        # once, so `timeout_ms` + 1 ticks make at least `timeout_ms` milliseconds.
        # (Placed last: firing wins over a write of `control` in the same cycle.)
        with m.If(enable & tick & (remaining == 0)):
            m.d.sync += [self.fire.eq(1), enable.eq(0), reset_cause.eq(1)]
        return m


class Events(_CsrComponent):
    """Sticky event flags for the firmware to poll.

    A one-cycle pulse on ``sources[k]`` sets field ``names[k]`` of ``status``; writing 1 to
    a field clears it. A pulse in the cycle of the clear wins, so no event is lost.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    sources : ``In(len(names))``
    """

    class Status(csr.Register, access="rw"):
        """One bit per event, set by the event; write 1 to clear it."""
        def __init__(self, names):
            super().__init__({name: csr.Field(csr.action.RW1C, 1) for name in names})

    def __init__(self, names):
        names = tuple(names) if isinstance(names, (list, tuple)) else names
        if (not isinstance(names, tuple) or not names
                or not all(isinstance(n, str) and n.isidentifier() for n in names)
                or len(set(names)) != len(names)):
            raise ValueError(f"Event names must be a non-empty sequence of distinct "
                             f"identifiers, not {names!r}")
        if len(names) > 32:
            raise ValueError(f"Events fit one 32-bit register: at most 32 names, not "
                             f"{len(names)!r}")
        self._names = names
        regs = _builder(1)
        self._status = regs.add("status", self.Status(names))
        super().__init__(regs, {"sources": In(len(names))})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        for k, name in enumerate(self._names):
            m.d.comb += self._status.f[name].set.eq(self.sources[k])
        return m


def tap_signature(n_channels):
    """A tagged frame stream seen from a monitor: ``valid``, ``ready`` and ``payload`` all
    flow towards the monitor (``In(tap_signature(n))``), which never drives the stream."""
    return wiring.Signature({
        "valid":   Out(1),
        "ready":   Out(1),
        "payload": Out(TaggedFrameByte(n_channels)),
    })


#: What each position of a ZDA frame, counted from its `$`, must hold (the decimals of the
#: seconds, between the time's digits and its comma, are not counted): a character, a talker
#: letter, a digit, or the end of the time (`.` or `,`). After the year's comma (``DONE``)
#: any bytes may follow until the frame's last.
_LETTER, _DIGIT, _TIME_END = "letter", "digit", "time end"
_ZDA_TEMPLATE = ([arch.DOLLAR, _LETTER, _LETTER] + list(ZDA_ADDRESS)
                 + [_DIGIT] * ZDA_TIME_DIGITS + [_TIME_END]
                 + [c for width in ZDA_DATE_DIGITS for c in [_DIGIT] * width + [arch.COMMA]])
_ZDA_DONE = len(_ZDA_TEMPLATE)
_ZDA_TIME_END = _ZDA_TEMPLATE.index(_TIME_END)


def _zda_field_ends():
    """The position of each field's last digit, by field name."""
    first = _ZDA_TIME_END - ZDA_TIME_DIGITS
    ends = {name: first + 2 * k + 1 for k, name in enumerate(["hour", "minute", "second"])}
    pos = _ZDA_TIME_END                     # the comma before each date field
    for name, width in zip(["day", "month", "year"], ZDA_DATE_DIGITS):
        ends[name] = pos + width
        pos += width + 1
    return ends


_ZDA_FIELD_ENDS = _zda_field_ends()


class GpsTime(_CsrComponent):
    """The UTC time and date of the last good ZDA sentence on one channel's kept frames.

    It watches the stream ``i`` as a tap: a byte counts in a cycle where ``valid`` and
    ``ready`` are both high, and the tap drives nothing (``i``'s members are all inputs:
    connect each from the stream it watches). Bytes of other channels are ignored, and so
    are frames of other sentence types. A ZDA from any two-letter talker
    (``$ccZDA,hhmmss[.s…],dd,mm,yyyy,…``, the year's comma not the frame's last byte)
    whose fields are all digits of NMEA's fixed widths, in range (hour < 24, minute < 60,
    second < 60 — a leap second's 60 is not taken, so the firmware never meets it — day
    1-31, month 1-12, year < 4096), is committed to the registers at its last byte, with a
    one-cycle ``zda`` pulse; any other frame leaves them unchanged.

    Parameters
    ----------
    n_channels : int
        Channels of the tagged stream (its ``channel`` tag's width).
    channel : int
        The GPS channel's tag.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    i : ``In(tap_signature(n_channels))``: ``valid``, ``ready``, ``payload`` (inputs).
    zda : ``Out(1)``
    """

    class Time(csr.Register, access="r"):
        """UTC time of the last good ZDA (binary, not BCD)."""
        second: csr.Field(csr.action.R, 6)
        minute: csr.Field(csr.action.R, 6)
        hour:   csr.Field(csr.action.R, 5)

    class Date(csr.Register, access="r"):
        """UTC date of the last good ZDA (binary; the year in full, e.g. 2024)."""
        day:   csr.Field(csr.action.R, 5)
        month: csr.Field(csr.action.R, 4)
        year:  csr.Field(csr.action.R, 12)

    class Status(csr.Register, access="r"):
        """`valid` 1: a good ZDA has been captured since reset."""
        valid: csr.Field(csr.action.R, 1)

    def __init__(self, n_channels, channel=1):
        if not isinstance(n_channels, int) or isinstance(n_channels, bool) or n_channels < 1:
            raise ValueError(f"Channel count must be a positive integer, not {n_channels!r}")
        if not isinstance(channel, int) or isinstance(channel, bool) or \
                not 0 <= channel < n_channels:
            raise ValueError(f"Channel must be an integer in 0..{n_channels - 1}, "
                             f"not {channel!r}")
        self._channel = channel
        regs = _builder(3)
        self._time = regs.add("time", self.Time())
        self._date = regs.add("date", self.Date())
        self._status = regs.add("status", self.Status())
        super().__init__(regs, {"i": In(tap_signature(n_channels)), "zda": Out(1)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        time, date = self._time.f, self._date.f
        widths = {"hour": 5, "minute": 6, "second": 6, "day": 5, "month": 4, "year": 12}
        # The registers read as zero until the first capture, so they need no reset.
        kept = {name: Signal(width, name=name, reset_less=True)
                for name, width in widths.items()}
        valid = Signal()
        for name in ("hour", "minute", "second"):
            m.d.comb += time[name].r_data.eq(Mux(valid, kept[name], 0))
        for name in ("day", "month", "year"):
            m.d.comb += date[name].r_data.eq(Mux(valid, kept[name], 0))
        m.d.comb += self._status.f.valid.r_data.eq(valid)

        # Fields as read, in the frame being parsed (committed at its last byte if good).
        read = {name: Signal(width, name=f"read_{name}", reset_less=True)
                for name, width in widths.items()}

        pos  = Signal(range(_ZDA_DONE + 1))   # position in _ZDA_TEMPLATE
        frac = Signal()                       # a `.` has ended the time's digits
        skip = Signal()                       # not a good ZDA: wait for the frame's end
        # The current field's digits so far (three of the year's at most: 10 bits). Cleared
        # at every position that is not a digit, so it needs no reset of its own.
        acc  = Signal(10, reset_less=True)

        byte = self.i.payload.data
        digit = byte[:4]
        is_digit  = (byte[4:] == ord("0") >> 4) & (digit <= 9)
        is_letter = (byte >= ord("A")) & (byte <= ord("Z"))
        is_comma  = byte == arch.COMMA
        # acc * 10 + digit, as (acc * 5 + digit // 2) * 2 + digit % 2: shifts and adds.
        next_acc = Signal(14)
        m.d.comb += next_acc.eq(Cat(digit[0], (acc << 2) + acc + digit[1:]))

        # The two-digit fields' ranges, from their digits (acc holds the tens digit).
        tens = acc[:4]
        in_range = {
            "hour":   (tens < 2) | ((tens == 2) & (digit < 4)),
            "minute": tens < 6,
            "second": tens < 6,
            "day":    ((tens < 3) | ((tens == 3) & (digit < 2))) & ((tens != 0) | (digit != 0)),
            "month":  ((tens == 0) & (digit != 0)) | ((tens == 1) & (digit < 3)),
            "year":   next_acc[12:] == 0,
        }

        good    = Signal()     # the byte is what its position needs
        advance = Signal()     # and moves on to the next position
        is_end  = Signal()     # it ends a field (its value is taken from next_acc)
        with m.Switch(pos):
            for k, what in enumerate(_ZDA_TEMPLATE):
                with m.Case(k):
                    if what == _LETTER:
                        m.d.comb += [good.eq(is_letter), advance.eq(1)]
                    elif what == _DIGIT:
                        check = next((in_range[name] for name, end in _ZDA_FIELD_ENDS.items()
                                      if end == k), 1)
                        m.d.comb += [good.eq(is_digit & check), advance.eq(1),
                                     is_end.eq(k in _ZDA_FIELD_ENDS.values())]
                    elif what == _TIME_END:
                        m.d.comb += [
                            good.eq(is_comma | ((byte == arch.PERIOD) & ~frac) |
                                    (frac & is_digit)),
                            advance.eq(is_comma),
                        ]
                    else:
                        m.d.comb += [good.eq(byte == what), advance.eq(1)]
            with m.Default():                  # DONE: anything up to the frame's last byte
                m.d.comb += good.eq(1)

        m.d.sync += self.zda.eq(0)
        taken = self.i.valid & self.i.ready & (self.i.payload.channel == self._channel)
        with m.If(taken):
            with m.If(self.i.payload.last):
                # Every frame ends here, good or not; a good ZDA is committed whole.
                m.d.sync += [pos.eq(0), frac.eq(0), skip.eq(0)]
                with m.If(~skip & (pos == _ZDA_DONE)):
                    m.d.sync += [kept[name].eq(read[name]) for name in widths]
                    m.d.sync += [valid.eq(1), self.zda.eq(1)]
            with m.Elif(~skip):
                with m.If(~good):
                    m.d.sync += skip.eq(1)
                with m.Elif(advance):
                    m.d.sync += pos.eq(pos + 1)
                with m.If(byte == arch.PERIOD):
                    m.d.sync += frac.eq(1)
                is_digit_pos = Cat(pos == k for k, what in enumerate(_ZDA_TEMPLATE)
                                   if what == _DIGIT).any()
                m.d.sync += acc.eq(Mux(is_digit_pos & ~is_end, next_acc, 0))
                for name, end in _ZDA_FIELD_ENDS.items():
                    with m.If(pos == end):
                        m.d.sync += read[name].eq(next_acc)
        return m
