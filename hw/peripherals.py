"""SoC peripherals of the logger: LEDs, button, real-time clock, watchdog, events, GPS time.

Each is a :class:`wiring.Component` with its own amaranth-soc CSR bus (32-bit words) and
memory map; the logger's top puts them behind one CSR decoder, one window each.
"""

from amaranth import *
from amaranth.lib import enum, wiring
from amaranth.lib.cdc import FFSynchronizer
from amaranth.lib.wiring import In, Out
from amaranth.utils import ceil_log2

from .arbiter import TaggedFrameByte
from .arch import frames as arch
from .soc import csr


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


def _cycles(clk_freq, seconds, what):
    """Clock cycles in ``seconds`` (at least one)."""
    if not isinstance(seconds, (int, float)) or isinstance(seconds, bool) or seconds <= 0:
        raise ValueError(f"{what} must be a positive number of seconds, not {seconds!r}")
    return max(1, round(clk_freq * seconds))


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
    """A component whose registers sit behind its own CSR bridge."""
    def __init__(self, regs, members):
        self._bridge = csr.Bridge(regs.as_memory_map())
        super().__init__({"bus": _bus_members(regs), **members})
        self.bus.memory_map = self._bridge.bus.memory_map

    def _elaborate_bridge(self):
        m = Module()
        m.submodules.bridge = self._bridge
        wiring.connect(m, wiring.flipped(self.bus), self._bridge.bus)
        return m


class Leds(_CsrComponent):
    """The four LEDs: firmware-driven, two of them also lit by hardware activity.

    ``led[0]`` = ``value[0]`` (recording), ``led[3]`` = ``value[3]`` (GPS fix);
    ``led[1]`` = ``value[1]`` or a pulse of ``activity[0]`` in the last ``stretch_s``
    (a kept magnetometer frame), ``led[2]`` likewise with ``activity[1]`` (a kept GPS frame).

    Members
    -------
    bus : ``In(csr.Signature(...))``
    activity : ``In(2)``: one-cycle pulses.
    led : ``Out(4)``
    """

    class Value(csr.Register, access="rw"):
        """The firmware's LED bits: bit 0 LED1 (recording), bit 3 LED4 (GPS fix); bits 1
        and 2 light LED2 and LED3, which the magnetometer's and the GPS's kept frames also
        light for a moment."""
        value: csr.Field(csr.action.RW, 4)

    def __init__(self, clk_freq, stretch_s=0.05):
        _check_frequency(clk_freq)
        self._stretch = _cycles(clk_freq, stretch_s, "Activity stretch")
        regs = _builder(1)
        self._value = regs.add("value", self.Value())
        super().__init__(regs, {"activity": In(2), "led": Out(4)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        value = self._value.f.value.data
        lit = []
        for k in range(2):
            # A pulse lights the LED for `stretch` cycles (a new pulse starts them again).
            remaining = Signal(range(self._stretch + 1), name=f"remaining_{k}")
            with m.If(self.activity[k]):
                m.d.sync += remaining.eq(self._stretch)
            with m.Elif(remaining != 0):
                m.d.sync += remaining.eq(remaining - 1)
            lit.append(remaining != 0)
        m.d.comb += self.led.eq(Cat(value[0], value[1] | lit[0], value[2] | lit[1], value[3]))
        return m


class Button(_CsrComponent):
    """The push button, synchronised and debounced.

    The asynchronous ``button`` (high = pressed) goes through a two-stage synchroniser; the
    debounced ``level`` takes the synchronised value once it has differed from ``level``
    for ``debounce_s`` without a break, so bounce and glitches shorter than that are never
    seen. ``press`` pulses for one cycle as ``level`` rises.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    button : ``In(1)``; level : ``Out(1)``; press : ``Out(1)``
    """

    class Status(csr.Register, access="r"):
        """The debounced button level (1 = pressed)."""
        level: csr.Field(csr.action.R, 1)

    def __init__(self, clk_freq, debounce_s=0.01):
        _check_frequency(clk_freq)
        self._debounce = _cycles(clk_freq, debounce_s, "Debounce time")
        regs = _builder(1)
        self._status = regs.add("status", self.Status())
        super().__init__(regs, {"button": In(1), "level": Out(1), "press": Out(1)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        synced = Signal()
        m.submodules.sync = FFSynchronizer(self.button, synced, stages=2)

        differing = Signal(range(self._debounce))   # cycles synced has differed from level
        m.d.sync += self.press.eq(0)
        with m.If(synced == self.level):
            m.d.sync += differing.eq(0)
        with m.Elif(differing == self._debounce - 1):
            m.d.sync += [self.level.eq(synced), self.press.eq(synced), differing.eq(0)]
        with m.Else():
            m.d.sync += differing.eq(differing + 1)
        m.d.comb += self._status.f.level.r_data.eq(self.level)
        return m


class Rtc(_CsrComponent):
    """Real-time clock: seconds and milliseconds, counted from the system clock.

    A millisecond is ``round(clk_freq / 1000)`` clocks, so the clock runs off by the
    rounding error (none at the boards' 50 MHz).

    Members
    -------
    bus : ``In(csr.Signature(...))``
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
        super().__init__(regs, {})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        prescaler = Signal(range(self._prescaler))
        millis    = Signal(range(MILLIS_PER_SECOND))
        seconds   = Signal(32)
        latched   = Signal(range(MILLIS_PER_SECOND))
        field = self._seconds.f.value

        with m.If(prescaler == self._prescaler - 1):
            m.d.sync += prescaler.eq(0)
            with m.If(millis == MILLIS_PER_SECOND - 1):
                m.d.sync += [millis.eq(0), seconds.eq(seconds + 1)]
            with m.Else():
                m.d.sync += millis.eq(millis + 1)
        with m.Else():
            m.d.sync += prescaler.eq(prescaler + 1)
        with m.If(field.w_stb):
            m.d.sync += [seconds.eq(field.w_data), millis.eq(0), prescaler.eq(0)]
        # The read takes the seconds of this cycle, so the latched milliseconds belong to them.
        with m.If(field.r_stb):
            m.d.sync += latched.eq(millis)
        m.d.comb += [
            field.r_data.eq(seconds),
            self._subsec.f.millis.r_data.eq(latched),
        ]
        return m


class Watchdog(_CsrComponent):
    """Fires when the firmware, having enabled it, stops kicking it.

    While ``enable`` is set, milliseconds are counted since the last kick (or write of
    ``control``); when they reach ``timeout_ms``, ``fire`` pulses for one cycle, ``enable``
    goes back to 0 and ``reset_cause`` is set. The top resets the rest of the logger with
    ``fire``; this component is outside that reset, so ``reset_cause`` tells the restarted
    firmware what happened, until the domain's own reset (the external ``rst``) clears it.

    Members
    -------
    bus : ``In(csr.Signature(...))``
    fire : ``Out(1)``
    """

    class Control(csr.Register, access="rw"):
        """`enable` starts the watchdog (it goes back to 0 when the watchdog fires);
        `timeout_ms`: milliseconds without a kick before it fires (0 fires at once).
        Writing restarts the count."""
        enable:     csr.Field(RWStrobed, 1)
        timeout_ms: csr.Field(csr.action.RW, 16, init=1000)

    class Kick(csr.Register, access="w"):
        """Writing 1 restarts the count."""
        kick: csr.Field(csr.action.W, 1)

    class Status(csr.Register, access="r"):
        """`reset_cause` 1: the watchdog has fired since the last external reset."""
        reset_cause: csr.Field(csr.action.R, 1)

    def __init__(self, clk_freq):
        self._prescaler = _millisecond_prescaler(clk_freq)
        regs = _builder(3)
        self._control = regs.add("control", self.Control())
        self._kick = regs.add("kick", self.Kick())
        self._status = regs.add("status", self.Status())
        super().__init__(regs, {"fire": Out(1)})

    def elaborate(self, platform):
        m = self._elaborate_bridge()
        enable      = Signal()
        reset_cause = Signal()
        prescaler   = Signal(range(self._prescaler))
        elapsed     = Signal(16)                 # milliseconds since the last kick
        control, kick = self._control.f, self._kick.f.kick
        m.d.comb += [
            control.enable.r_data.eq(enable),
            self._status.f.reset_cause.r_data.eq(reset_cause),
        ]

        with m.If(prescaler == self._prescaler - 1):
            m.d.sync += [prescaler.eq(0), elapsed.eq(elapsed + 1)]
        with m.Else():
            m.d.sync += prescaler.eq(prescaler + 1)
        with m.If(control.enable.w_stb | (kick.w_stb & kick.w_data) | ~enable):
            m.d.sync += [prescaler.eq(0), elapsed.eq(0)]
        with m.If(control.enable.w_stb):
            m.d.sync += enable.eq(control.enable.w_data)

        m.d.sync += self.fire.eq(0)
        # (Placed last: firing wins over a write of `control` in the same cycle.)
        with m.If(enable & (elapsed >= control.timeout_ms.data)):
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


class _Zda(enum.Enum, shape=3):
    """Where the ZDA parser is in a frame of the watched channel."""
    START    = 0    # waits for a frame's first byte, `$`
    ADDRESS  = 1    # waits for the talker's two letters and `ZDA,` (position in `digits`)
    TIME     = 2    # waits for the six digits of hhmmss
    DECIMALS = 3    # waits for the `.` of decimal seconds or the `,` ending the time field
    FRACTION = 4    # waits for decimal digits up to the `,` ending the time field
    DATE     = 5    # waits for the digits and `,` of day, month, year (index in `field`)
    DONE     = 6    # waits for the frame's last byte, to commit what was read
    SKIP     = 7    # waits for the last byte of a frame that is not a good ZDA


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
        hour, minute, second = (Signal(5), Signal(6), Signal(6))
        day, month, year = (Signal(5), Signal(4), Signal(12))
        valid = Signal()
        m.d.comb += [
            time.hour.r_data.eq(hour), time.minute.r_data.eq(minute),
            time.second.r_data.eq(second),
            date.day.r_data.eq(day), date.month.r_data.eq(month), date.year.r_data.eq(year),
            self._status.f.valid.r_data.eq(valid),
        ]

        # Values as read (wide enough for any digits, checked against their ranges at the end).
        read = {name: Signal(7, name=f"read_{name}")
                for name in ("hour", "minute", "second", "day", "month")}
        read["year"] = Signal(range(10 ** max(ZDA_DATE_DIGITS)), name="read_year")
        time_fields = [read["hour"], read["minute"], read["second"]]
        date_fields = [read["day"], read["month"], read["year"]]

        state  = Signal(_Zda)
        digits = Signal(range(8))           # characters read in the current field
        field  = Signal(range(len(ZDA_DATE_DIGITS)))
        acc    = Signal.like(read["year"])  # the current number, digit by digit

        byte = self.i.payload.data
        is_digit = (byte >= ord("0")) & (byte <= ord("9"))
        shifted = Signal.like(acc)
        m.d.comb += shifted.eq(acc * 10 + (byte - ord("0")))
        is_letter = (byte >= ord("A")) & (byte <= ord("Z"))

        in_range = ((read["hour"] < 24) & (read["minute"] < 60) & (read["second"] < 60) &
                    (read["day"] >= 1) & (read["day"] <= 31) &
                    (read["month"] >= 1) & (read["month"] <= 12) & (read["year"] < 1 << 12))

        m.d.sync += self.zda.eq(0)
        taken = self.i.valid & self.i.ready & (self.i.payload.channel == self._channel)
        with m.If(taken):
            with m.Switch(state):
                with m.Case(_Zda.START):
                    with m.If(byte == arch.DOLLAR):
                        m.d.sync += [state.eq(_Zda.ADDRESS), digits.eq(0)]
                    with m.Else():
                        m.d.sync += state.eq(_Zda.SKIP)
                with m.Case(_Zda.ADDRESS):
                    m.d.sync += digits.eq(digits + 1)
                    with m.Switch(digits):
                        with m.Case(0, 1):
                            with m.If(~is_letter):
                                m.d.sync += state.eq(_Zda.SKIP)
                        for k, char in enumerate(ZDA_ADDRESS):
                            with m.Case(2 + k):
                                with m.If(byte != char):
                                    m.d.sync += state.eq(_Zda.SKIP)
                                with m.Elif(k == len(ZDA_ADDRESS) - 1):
                                    m.d.sync += [state.eq(_Zda.TIME), digits.eq(0), acc.eq(0)]
                with m.Case(_Zda.TIME):
                    # hh, mm, ss: each pair's value is stored at its second digit.
                    with m.If(~is_digit):
                        m.d.sync += state.eq(_Zda.SKIP)
                    with m.Elif(digits[0]):
                        m.d.sync += acc.eq(0)
                        with m.Switch(digits[1:]):
                            for k, target in enumerate(time_fields):
                                with m.Case(k):
                                    m.d.sync += target.eq(shifted)
                    with m.Else():
                        m.d.sync += acc.eq(shifted)
                    m.d.sync += digits.eq(digits + 1)
                    with m.If(is_digit & (digits == ZDA_TIME_DIGITS - 1)):
                        m.d.sync += state.eq(_Zda.DECIMALS)
                with m.Case(_Zda.DECIMALS, _Zda.FRACTION):
                    with m.If(byte == arch.COMMA):
                        m.d.sync += [state.eq(_Zda.DATE), field.eq(0), digits.eq(0), acc.eq(0)]
                    with m.Elif((state == _Zda.DECIMALS) & (byte == arch.PERIOD)):
                        m.d.sync += state.eq(_Zda.FRACTION)
                    with m.Elif((state == _Zda.DECIMALS) | ~is_digit):
                        m.d.sync += state.eq(_Zda.SKIP)
                with m.Case(_Zda.DATE):
                    # The field's width from a constant, not an Array: Yosys writes an
                    # Array's lookup as an `always @*` that Icarus -g2012 (cocotb's flags)
                    # never runs while `field` keeps its initial 0, so the width stayed x
                    # and no ZDA was ever taken there.
                    width = Cat(C(w, 3) for w in ZDA_DATE_DIGITS).word_select(field, 3)
                    with m.If(is_digit & (digits < width)):
                        m.d.sync += [acc.eq(shifted), digits.eq(digits + 1)]
                    with m.Elif((byte == arch.COMMA) & (digits == width)):
                        m.d.sync += [field.eq(field + 1), digits.eq(0), acc.eq(0)]
                        with m.Switch(field):
                            for k, target in enumerate(date_fields):
                                with m.Case(k):
                                    m.d.sync += target.eq(acc)
                        with m.If(field == len(ZDA_DATE_DIGITS) - 1):
                            m.d.sync += state.eq(_Zda.DONE)
                    with m.Else():
                        m.d.sync += state.eq(_Zda.SKIP)
            # Every frame ends here, good or not; a good ZDA is committed whole.
            with m.If(self.i.payload.last):
                m.d.sync += state.eq(_Zda.START)
                with m.If((state == _Zda.DONE) & in_range):
                    m.d.sync += [
                        hour.eq(read["hour"]), minute.eq(read["minute"]),
                        second.eq(read["second"]),
                        day.eq(read["day"]), month.eq(read["month"]), year.eq(read["year"]),
                        valid.eq(1), self.zda.eq(1),
                    ]
        return m
