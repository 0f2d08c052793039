"""System scenarios: what the whole logger sees (serial bytes with their timing, button
presses) and what its card must then hold, independently of the backend that runs it.

A :class:`SystemScenario` is the one input of every system backend (the transaction-level
model, the Amaranth simulator, cocotb): the same scenario and the same firmware must give
the same card image on each. Its :meth:`~SystemScenario.expected_frames` come from the
reference filter (sim/reference/), never from a backend.

Frames of different channels may overlap on their lines, but a backend decides their order
in the log from the instant each one ends, to within a few bit times; a scenario therefore
keeps the ends of any two kept frames at least :data:`MIN_END_GAP_S` apart, and keeps the
lines quiet around each button press, where the instant recording starts or stops differs
between backends by the firmware's speed.
"""

from __future__ import annotations

import bisect
import datetime as _dt
import functools
import random
from dataclasses import dataclass, field

from ...hw.arch import frames as arch_frames
from ...hw.arch import uart as arch_uart
from ...hw.frame_filter import ChannelKind
from ...hw.frontend import ChannelConfig, divisor_for
from . import sentences
from ..reference import ERROR_MARK, Kind, ReferenceFilter, reference_filter
from .uart_line import decode, encode


__all__ = ["Burst", "SystemScenario", "Timeline", "flight_scenario",
           "FLIGHT_CHANNELS", "short_scenario", "MIN_END_GAP_S", "UART_FRAME_BITS"]

#: Bit times of one 8N1 character on the line: start, 8 data, stop.
UART_FRAME_BITS = 10
#: The least time between the ends of two kept frames of different channels.
MIN_END_GAP_S = 200e-6

_KIND = {ChannelKind.PMAG: Kind.PMAG, ChannelKind.NMEA: Kind.NMEA,
         ChannelKind.CESIUM: Kind.CESIUM}


@dataclass(frozen=True)
class Burst:
    """Bytes sent back to back on one channel's line from ``start`` (seconds).

    ``baud``: the line's actual rate for this burst when it differs from the channel's
    nominal one (a baud-error fault; the gateware still samples at the nominal rate), None
    for the nominal rate."""
    channel: int
    start: float
    data: bytes
    baud: float | None = None

    def end(self, baud):
        """When the last stop bit ends, ``baud`` being the channel's nominal rate."""
        return self.start + len(self.data) * UART_FRAME_BITS / (self.baud or baud)


@dataclass
class SystemScenario:
    """The logger's inputs over one run.

    ``channels`` and ``clk_freq`` are the gateware's build parameters (every baud rate must
    be reachable from the clock, see :func:`maglog.hw.frontend.divisor_for`); ``presses``
    are the instants the button goes down, each held for ``hold`` seconds; the run ends at
    ``until``.
    """
    channels: tuple
    clk_freq: float
    bursts: list
    presses: list
    until: float
    hold: float = 2e-3
    debounce_s: float = 0.5e-3
    max_frame: int = arch_frames.DEFAULT_MAX_FRAME
    timestamp: _dt.datetime | None = None
    notes: list = field(default_factory=list)

    def __post_init__(self):
        self.channels = tuple(c if isinstance(c, ChannelConfig) else ChannelConfig(*c)
                              for c in self.channels)
        for burst in self.bursts:
            if not 0 <= burst.channel < len(self.channels):
                raise ValueError(f"Burst channel must be in 0..{len(self.channels) - 1}, not "
                                 f"{burst.channel!r}")
        for k in range(len(self.channels)):
            ordered = sorted(self.channel_bursts(k), key=lambda b: b.start)
            baud = self.channels[k].baud
            for a, b in zip(ordered, ordered[1:]):
                if b.start < a.end(baud):
                    raise ValueError(f"Bursts of channel {k} overlap at {b.start:.6f} s")

    def to_json(self):
        """A JSON-able dict (for a simulator run in another process); see
        :meth:`from_json`."""
        return {"channels": [[c.kind.value, c.baud] for c in self.channels],
                "clk_freq": self.clk_freq,
                "bursts": [[b.channel, b.start, b.data.hex()]
                           + ([] if b.baud is None else [b.baud]) for b in self.bursts],
                "presses": list(self.presses), "until": self.until, "hold": self.hold,
                "debounce_s": self.debounce_s, "max_frame": self.max_frame,
                "timestamp": None if self.timestamp is None else self.timestamp.isoformat()}

    @classmethod
    def from_json(cls, data):
        return cls(channels=tuple(ChannelConfig(ChannelKind(kind), baud)
                                  for kind, baud in data["channels"]),
                   clk_freq=data["clk_freq"],
                   bursts=[Burst(k, start, bytes.fromhex(text), *baud)
                           for k, start, text, *baud in data["bursts"]],
                   presses=list(data["presses"]), until=data["until"], hold=data["hold"],
                   debounce_s=data["debounce_s"], max_frame=data["max_frame"],
                   timestamp=None if data["timestamp"] is None
                   else _dt.datetime.fromisoformat(data["timestamp"]))

    def channel_bursts(self, channel):
        return sorted((b for b in self.bursts if b.channel == channel), key=lambda b: b.start)

    def channel_bytes(self, channel):
        """Every byte channel ``channel`` carries, in order."""
        return b"".join(b.data for b in self.channel_bursts(channel))

    def off_nominal(self, channel):
        """Whether some burst of ``channel`` runs at a rate other than the nominal one."""
        baud = self.channels[channel].baud
        return any(b.baud is not None and b.baud != baud for b in self.channel_bursts(channel))

    def sampling_bit_cycles(self, channel):
        """The bit time the gateware's receiver samples with, in clock cycles (16 ticks of
        its whole-cycle divisor)."""
        return arch_uart.OVERSAMPLING * divisor_for(self.clk_freq,
                                                    self.channels[channel].baud)

    def received(self, channel):
        """``(events, times)``: what the channel's receiver reports, as ``(byte, error)``
        pairs, and when (seconds, the end of each character's stop bit on the line).

        A burst at the nominal rate is received as sent. A burst at another rate is encoded
        at its own bit time (:func:`~maglog.sim.stimulus.uart_line.encode`, idle before and after)
        and decoded at the gateware's (:meth:`sampling_bit_cycles`) by the ideal receiver
        :func:`~maglog.sim.stimulus.uart_line.decode`; when that gives one character per byte each
        keeps its byte's time, otherwise all of them take the burst's end."""
        nominal = self.channels[channel].baud
        events, times = [], []
        for burst in self.channel_bursts(channel):
            per_byte = UART_FRAME_BITS / (burst.baud or nominal)
            got = self.burst_events(burst)
            if len(got) == len(burst.data):
                times += [burst.start + (i + 1) * per_byte for i in range(len(got))]
            else:
                times += [burst.end(nominal)] * len(got)
            events += got
        return events, times

    def burst_events(self, burst):
        """What the receiver of ``burst``'s channel reports for it (see :meth:`received`),
        as ``(byte, error)`` pairs."""
        nominal = self.channels[burst.channel].baud
        baud = burst.baud or nominal
        if baud == nominal:
            return [(byte, False) for byte in burst.data]
        return list(_decoded(burst.data, self.clk_freq / baud,
                             self.sampling_bit_cycles(burst.channel)))

    def received_filter(self, channel):
        """The reference filter's result over what ``channel``'s receiver reports
        (:meth:`received`)."""
        kind = _KIND[self.channels[channel].kind]
        if not self.off_nominal(channel):
            return reference_filter(kind, self.channel_bytes(channel), max_frame=self.max_frame)
        ref = ReferenceFilter(kind, self.max_frame)
        for burst in self.channel_bursts(channel):
            events = self.burst_events(burst)
            if len(events) == len(burst.data) and not any(e for _, e in events):
                ref.feed_all(bytes(b for b, _ in events))
            else:
                for byte, error in events:
                    ref.feed(byte, error)
        return ref.result

    def kept_frames(self, channel):
        """``(end_time, frame)`` for each frame the reference filter keeps on a channel;
        the end time is that of the frame's stop bit of its last byte."""
        if self.off_nominal(channel):
            return self._kept_received(channel)
        baud = self.channels[channel].baud
        kind = _KIND[self.channels[channel].kind]
        stream = self.channel_bytes(channel)
        kept = reference_filter(kind, stream, max_frame=self.max_frame).frames
        # Map each kept frame back to its place in the stream (kept frames are verbatim and
        # in order), and that place to a time.
        starts, offset = [], 0
        for burst in self.channel_bursts(channel):
            starts.append((offset, burst))
            offset += len(burst.data)
        offsets = [s[0] for s in starts]
        result, search = [], 0
        for frame in kept:
            at = stream.index(frame, search)
            last = at + len(frame) - 1
            search = last + 1
            base, burst = starts[bisect.bisect_right(offsets, last) - 1]
            result.append((burst.start + (last - base + 1) * UART_FRAME_BITS / baud, frame))
        return result

    def _kept_received(self, channel):
        events, times = self.received(channel)
        kept = self.received_filter(channel).frames
        text = "".join(ERROR_MARK if error else chr(byte) for byte, error in events)
        result, search = [], 0
        for frame in kept:
            at = text.index(frame.decode("latin-1"), search)
            search = at + len(frame)
            result.append((times[search - 1], frame))
        return result

    def log_frames(self, start, stop):
        """The frames a log recorded from ``start`` to ``stop`` holds, in order: those that
        end in that window, by end time. Refuses a scenario whose kept frames end too close
        together for their order to be certain."""
        ends = sorted((t, k, frame) for k in range(len(self.channels))
                      for t, frame in self.kept_frames(k))
        for (t0, k0, _), (t1, k1, _) in zip(ends, ends[1:]):
            if k0 != k1 and t1 - t0 < MIN_END_GAP_S:
                raise ValueError(f"Frames of channels {k0} and {k1} end {t1 - t0:.2e} s "
                                 f"apart at {t0:.6f} s: closer than {MIN_END_GAP_S} s")
        return [frame for t, _, frame in ends if start <= t < stop]

    def recorded_frames(self):
        """The frames the log of a recording between the first two presses holds: the
        lines are quiet around both presses, so the window is the presses themselves."""
        if len(self.presses) < 2:
            raise ValueError("A recording needs two button presses (start and stop)")
        return self.log_frames(self.presses[0], self.presses[1])

    def bit_cycles(self, channel):
        return self.clk_freq / self.channels[channel].baud

    def pin_changes(self):
        """The logger's input pins over the run, as ``(cycle, uart_rx, button)`` at every
        cycle where one of them changes (``uart_rx`` a bit per channel, idle high;
        ``button`` high while pressed), starting with their levels at cycle 0."""
        changes = {}             # cycle -> list of (pin, bit, level)
        for k in range(len(self.channels)):
            for burst in self.channel_bursts(k):
                bit_cycles = self.clk_freq / (burst.baud or self.channels[k].baud)
                trace = encode(burst.data, bit_cycles=bit_cycles, lead_idle_bits=1.0,
                               tail_idle_bits=0.0)
                cycle = round(burst.start * self.clk_freq) - trace.byte_starts[0]
                if cycle < 0:
                    raise ValueError(f"A burst of channel {k} starts before the run")
                for level, cycles in trace.segments:
                    changes.setdefault(cycle, []).append(("uart_rx", k, level))
                    cycle += cycles
                changes.setdefault(cycle, []).append(("uart_rx", k, 1))
        for press in self.presses:
            changes.setdefault(round(press * self.clk_freq), []).append(("button", 0, 1))
            changes.setdefault(round((press + self.hold) * self.clk_freq), []).append(
                ("button", 0, 0))
        uart_rx, button = (1 << len(self.channels)) - 1, 0
        result = [(0, uart_rx, button)]
        for cycle in sorted(changes):
            for pin, bit, level in changes[cycle]:
                if pin == "uart_rx":
                    uart_rx = uart_rx & ~(1 << bit) | (level << bit)
                else:
                    button = level
            if cycle == 0:
                result[0] = (0, uart_rx, button)
            elif (uart_rx, button) != result[-1][1:]:
                result.append((cycle, uart_rx, button))
        return result

    def check_quiet(self, margin):
        """Raise unless no line carries a byte within ``margin`` seconds of a press."""
        for press in self.presses:
            for k in range(len(self.channels)):
                baud = self.channels[k].baud
                for burst in self.channel_bursts(k):
                    if burst.start - margin < press < burst.end(baud) + margin:
                        raise ValueError(f"Channel {k} is busy within {margin} s of the "
                                         f"press at {press} s")


@functools.lru_cache(maxsize=4096)
def _decoded(data, bit_cycles, sampling_bit_cycles):
    """The ideal receiver's ``(byte, error)`` pairs for ``data`` sent at ``bit_cycles`` and
    sampled at ``sampling_bit_cycles`` (idle line before and after)."""
    trace = encode(data, bit_cycles=bit_cycles)
    return tuple((e.data, e.error) for e in decode(trace.segments,
                                                    bit_cycles=sampling_bit_cycles))


def _pmag_frames(rng, count, seq0):
    frames = []
    for n in range(count):
        x, y, z = (rng.uniform(-50_000, 50_000) for _ in range(3))
        frames.append(sentences.pmag1((seq0 + n) % 100_000, x, y, z))
    return frames


class Timeline:
    """Places frames on their lines so that no two end closer than :data:`MIN_END_GAP_S`
    (a frame is moved later until it fits, never earlier)."""
    def __init__(self, channels):
        self.channels = channels
        self.bursts = []
        self._ends = []
        self._free = [0.0] * len(channels)

    def add(self, channel, start, frame, baud=None):
        """Place ``frame`` on ``channel`` at ``start`` or later; ``baud`` the line's actual
        rate when not the nominal one (see :class:`Burst`). Returns when it ends."""
        duration = len(frame) * UART_FRAME_BITS / (baud or self.channels[channel].baud)
        start = max(start, self._free[channel])
        while True:             # any end within MIN_END_GAP_S of this one? (ends sorted)
            end = start + duration
            near = bisect.bisect_right(self._ends, end - MIN_END_GAP_S)
            if near == len(self._ends) or not self._ends[near] < end + MIN_END_GAP_S:
                break
            start += MIN_END_GAP_S
        self.bursts.append(Burst(channel, start, frame, baud))
        bisect.insort(self._ends, start + duration)
        self._free[channel] = start + duration
        return start + duration


#: A flight's channels at the instruments' own rates (DESIGN.md, Formats).
FLIGHT_CHANNELS = (ChannelConfig(ChannelKind.PMAG, 115_200),
                   ChannelConfig(ChannelKind.NMEA, 9_600),
                   ChannelConfig(ChannelKind.CESIUM, 9_600))


def flight_scenario(flight, *, clk_freq=50e6, lead_s=2.0, tail_s=1.0, mag_rate=20.0,
                    cesium_rate=10.0, seed=0):
    """A recording of a :class:`~maglog.sim.stimulus.scenario.Flight`: its log lines (the
    magnetometer's, the cesium's, GGA, ZDA and VTG once a second) sent on their channels at
    the instruments' baud rates from ``lead_s`` on (the GPS lines of a second one after the
    other), the button pressed ``lead_s / 2`` before the first line and ``tail_s / 2`` after
    the last one ends, the run ending ``tail_s`` after it."""
    log = flight.log(mag_rate=mag_rate, cesium_rate=cesium_rate, seed=seed)
    kinds = {b"$PMAG1": 0, b"$ ": 2, b"$1": 2}
    rate = {0: 1 / mag_rate, 2: 1 / cesium_rate}
    counts = {0: 0, 1: 0, 2: 0}
    line = Timeline(FLIGHT_CHANNELS)
    gps_second = None
    end = 0.0
    for frame in log.splitlines(keepends=True):
        channel = next((k for prefix, k in kinds.items() if frame.startswith(prefix)), 1)
        if channel == 1:
            # A GGA opens each second's GPS lines (Flight.log writes GGA, ZDA, VTG).
            if frame[3:6] == b"GGA" or gps_second is None:
                gps_second = counts[1]
                counts[1] += 1
            start = lead_s + gps_second
        else:
            start = lead_s + counts[channel] * rate[channel]
            counts[channel] += 1
        end = max(end, line.add(channel, start, frame))
    presses = [lead_s / 2, end + tail_s / 2]
    return SystemScenario(channels=FLIGHT_CHANNELS, clk_freq=clk_freq, bursts=line.bursts,
                          presses=presses, until=end + tail_s, hold=0.1, debounce_s=0.01,
                          timestamp=flight.start)


def short_scenario(seed=0):
    """A short recording for comparing backends: all three channels at fast baud rates (a
    3.6864 MHz clock gives 230400 baud at divisor 1), the GPS time and a fix while idle,
    then a recording with four GGA fixes (four flushes) among magnetometer and cesium
    frames, distractors (RMC) and faults (a bad checksum, frames cut short), stopped by the
    button.

    Timeline (ms): 0 power-up; 60 ZDA and a GGA fix (idle); 100 press (start); 120-200
    frames; 240 press (stop); 300 end.
    """
    rng = random.Random(seed)
    channels = (ChannelConfig(ChannelKind.PMAG, 230_400),
                ChannelConfig(ChannelKind.NMEA, 230_400),
                ChannelConfig(ChannelKind.CESIUM, 115_200))
    when = _dt.datetime(2026, 11, 24, 12, 0, 0, tzinfo=_dt.timezone.utc)
    seconds_of_day = when.hour * 3600 + when.minute * 60 + when.second
    lat, lon = 47.3769, 8.5417
    line = Timeline(channels)
    line.add(1, 0.060, sentences.zda(when))
    line.add(1, 0.060, sentences.gga(seconds_of_day, lat, lon))
    # The recording: a GPS group every 20 ms (four GGA with a fix), the magnetometer every
    # 5 ms, the cesium every 10 ms.
    seq = rng.randrange(100_000)
    events = []
    for n in range(4):
        group = [sentences.gga(seconds_of_day + n, lat + 1e-4 * n, lon),
                 sentences.vtg(90.0, 29.0),
                 sentences.rmc(when + _dt.timedelta(seconds=n), lat, lon,
                               speed_knots=29.0, course_deg=90.0)]
        if n == 1:
            # A GGA with a bad checksum: dropped, no flush.
            bad = bytearray(sentences.gga(seconds_of_day + n, lat, lon))
            bad[-3] = ord("0") if bad[-3] != ord("0") else ord("1")
            group.insert(1, bytes(bad))
        events += [(0.120 + n * 0.020, 1, frame) for frame in group]
    t = 0.1213
    while t < 0.200:
        x, y, z = (rng.uniform(-50_000, 50_000) for _ in range(3))
        frame = sentences.pmag1(seq % 100_000, x, y, z)
        seq += 1
        if rng.random() < 0.1:
            frame = frame[:20]          # cut short: the next `$` drops it
        events.append((t, 0, frame))
        t += 0.005
    t = 0.1237
    while t < 0.200:
        events.append((t, 2, sentences.cesium(rng.uniform(48_000, 52_000),
                                               rng.randrange(1000, 2000))))
        t += 0.010
    for start, channel, frame in sorted(events, key=lambda e: (e[0], e[1])):
        line.add(channel, start, frame)
    scenario = SystemScenario(channels=channels, clk_freq=3.6864e6, bursts=line.bursts,
                              presses=[0.100, 0.240], until=0.300, timestamp=when)
    scenario.check_quiet(0.015)
    scenario.recorded_frames()          # refuses frames that end too close together
    return scenario
