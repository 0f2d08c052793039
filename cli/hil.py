"""Hardware in the loop over serial ports: ``maglog replay`` and ``maglog record``.

:func:`replay` streams a scenario's sensor bytes (a
:class:`~maglog.sim.stimulus.system.SystemScenario`'s bursts) to open serial ports, each
burst written at its own start time (divided by ``speed``), one thread per channel so that a
slow line never holds up another. The port's baud rate is the channel's nominal one; the
operating system's UART then clocks the bytes out back to back, as the scenario has them.

:func:`record` reads open serial ports, runs each channel's bytes through the project's
reference frame filter (:mod:`maglog.sim.reference`, the rules the gateware applies) and
appends every kept frame to a log file as soon as it is complete, in arrival order across
channels: the ``LOGnnnnn.TXT`` format the firmware writes, which ``maglog calibrate`` reads.

Both take open pyserial objects (``serial.Serial``, ``serial.serial_for_url``, including
``loop://``), so the command line only parses, opens and prints (:func:`open_port`).

What software cannot see: a UART framing error or break arrives from the operating system
as a NUL byte (counted as ``bad_byte``, not ``uart_error``), and the order of frames of
different channels that end within a few milliseconds of each other is the order in which
they were read, not the instant their last stop bit ended.
"""

from __future__ import annotations

import errno
import math
import select
import threading
import time
from dataclasses import dataclass, field

from ..sim.reference import COUNTER_NAMES, DEFAULT_MAX_FRAME, Kind, ReferenceFilter
from ..sim.reference import reference_filter
from ..sim.stimulus.config import CHANNEL_NAMES, shorten
from ..sim.stimulus.system import FLIGHT_CHANNELS, UART_FRAME_BITS as UART_BITS


__all__ = ["CHANNEL_NAMES", "CHANNEL_KINDS", "DEFAULT_BAUDS", "BAUD_RANGE", "HilError",
           "open_port", "replay", "ReplayResult", "ChannelReplay", "record", "RecordResult",
           "ChannelRecord"]

#: The rule set of each channel, in the logger's ``uart_rx`` order.
CHANNEL_KINDS = {name: Kind(config.kind.value)
                 for name, config in zip(CHANNEL_NAMES, FLIGHT_CHANNELS)}
#: Each channel's nominal baud rate (the built-in scenarios' and the gateware's default).
DEFAULT_BAUDS = {name: config.baud for name, config in zip(CHANNEL_NAMES, FLIGHT_CHANNELS)}
#: Baud rates a port is opened at: what common UARTs and USB adapters can be set to.
BAUD_RANGE = (50, 4_000_000)
#: How long the record loop waits for input before it looks at the clock again.
POLL_S = 0.02
#: ``replay --speed``'s range: beyond 10,000x a scenario of hours passes in a second and the
#: bursts go out back to back whatever their times (the lines' own rate is the limit).
SPEED_RANGE = (1e-3, 1e4)
#: A write may wait for the operating system's buffer (a few KiB) to drain onto the line:
#: its timeout is this much plus twice the line time of the buffer and the burst together,
#: so that only a port nobody reads (or one held by flow control) times out.
WRITE_SLACK_S = 2.0
OS_BUFFER_BYTES = 4096


class HilError(Exception):
    """A port that cannot be used; the message is one line."""


def open_port(device, baud):
    """Open ``device`` (a path or a pyserial URL such as ``loop://``) at ``baud``, 8N1,
    exclusively, non-blocking reads; :class:`HilError` with the reason if it cannot be."""
    import serial
    name = shorten(device)                # a device name repeated in errors, cut short
    if not BAUD_RANGE[0] <= baud <= BAUD_RANGE[1]:
        raise HilError(f"{name}: the baud rate must be from {BAUD_RANGE[0]} to "
                       f"{BAUD_RANGE[1]}, not {baud!r}")
    try:
        return serial.serial_for_url(device, baudrate=baud, timeout=0, write_timeout=None,
                                     exclusive=True)
    except ValueError as error:           # an unknown URL scheme, a baud pyserial refuses
        raise HilError(f"{name}: {shorten(error, 120)}") from None
    except (serial.SerialException, OSError) as error:
        code = getattr(error, "errno", None)
        if code == errno.ENOENT:
            reason = "no such port"
        elif code in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EBUSY):
            reason = "busy: another program has it open"
        elif code == errno.EACCES:
            reason = "permission denied (is the user in the dialout group?)"
        elif code == errno.ENOTTY or "Inappropriate ioctl" in str(error):
            reason = "not a serial port"
        elif code == errno.ENAMETOOLONG:
            reason = "the name is too long"
        else:
            reason = f"cannot use it as a serial port ({shorten(error, 120)})"
        raise HilError(f"{name}: {reason}") from None


# --- replay ---------------------------------------------------------------------------------

@dataclass
class ChannelReplay:
    """What :func:`replay` sent on one channel."""
    name: str
    baud: int
    bursts: int = 0
    bytes: int = 0
    #: Bursts the scenario runs at a rate other than the nominal one (a baud fault): sent at
    #: the port's nominal rate unless ``baud_faults`` was given.
    off_nominal: int = 0
    #: How late each burst's write started against its scheduled instant (seconds).
    lateness: list = field(default_factory=list, repr=False)
    #: Scheduled and actual start of each burst's write, seconds from the replay's start.
    times: list = field(default_factory=list, repr=False)
    error: str | None = None

    @property
    def max_late_s(self):
        return max(self.lateness, default=0.0)

    @property
    def mean_late_s(self):
        return sum(self.lateness) / len(self.lateness) if self.lateness else 0.0


@dataclass
class ReplayResult:
    channels: dict
    speed: float
    scenario_s: float
    wall_s: float
    interrupted: bool = False
    #: ``time.monotonic()`` at scenario time 0.
    started: float = 0.0


def replay(system, ports, *, speed=1.0, baud_faults=False, until=None, on_press=None,
           stop=None):
    """Stream ``system``'s bursts to ``ports`` ({channel index: open serial port}) in real
    time divided by ``speed``; channels without a port are not sent. ``until``: stop at this
    scenario time (default: the scenario's end). ``baud_faults``: switch a port to a burst's
    own rate for that burst (the port drained before and after). ``on_press(t)`` is called at
    each of the scenario's button presses. Returns a :class:`ReplayResult`; a Ctrl-C (or
    ``stop`` set) ends it early with ``interrupted`` set."""
    if not speed > 0:
        raise ValueError(f"speed must be > 0, not {speed!r}")
    for k in ports:
        if not 0 <= k < len(system.channels):
            raise ValueError(f"channel must be in 0..{len(system.channels) - 1}, not {k!r}")
    end = system.until if until is None else min(until, system.until)
    stop = stop or threading.Event()
    results = {k: ChannelReplay(CHANNEL_NAMES[k], system.channels[k].baud) for k in ports}
    start = time.monotonic() + 0.05     # the threads start together
    threads = [threading.Thread(target=_send_channel, daemon=True,
                                args=(system, k, ports[k], results[k], start, speed, end,
                                      baud_faults, stop)) for k in sorted(ports)]
    for thread in threads:
        thread.start()
    presses = sorted(t for t in system.presses if t < end)
    try:
        while any(thread.is_alive() for thread in threads):
            if presses and time.monotonic() >= start + presses[0] / speed:
                if on_press is not None:
                    on_press(presses.pop(0))
                else:
                    presses.pop(0)
                continue
            due = start + presses[0] / speed if presses else math.inf
            stop.wait(max(0.0, min(0.05, due - time.monotonic())))
    except KeyboardInterrupt:
        stop.set()
        for thread in threads:
            thread.join()
    interrupted = stop.is_set()
    errors = [r.error for r in results.values() if r.error]
    return ReplayResult(results, speed, end, time.monotonic() - start,
                        interrupted=interrupted and not errors, started=start)


def write_timeout(nbytes, baud):
    """Seconds a write of ``nbytes`` at ``baud`` may take before the port counts as stuck."""
    return WRITE_SLACK_S + 2 * (nbytes + OS_BUFFER_BYTES) * UART_BITS / baud


def line_seconds(system, k):
    """Seconds channel ``k``'s bytes take on its line at the nominal rate, back to back."""
    return len(system.channel_bytes(k)) * UART_BITS / system.channels[k].baud


def _write(port, data, timeout):
    if port.write_timeout != timeout:       # pyserial reconfigures the port on a change
        port.write_timeout = timeout
    written = port.write(data)
    if written is not None and written < len(data):
        raise TimeoutError(f"the port took {written} of {len(data)} bytes")


def _send_channel(system, k, port, result, start, speed, end, baud_faults, stop):
    nominal = system.channels[k].baud
    longest = max((len(b.data) for b in system.channel_bursts(k)), default=0)
    slowest = min([nominal] + [b.baud for b in system.channel_bursts(k) if b.baud])
    timeout = write_timeout(longest, slowest)
    try:
        for burst in system.channel_bursts(k):
            if burst.start >= end:
                break
            due = start + burst.start / speed
            while (left := due - time.monotonic()) > 0:
                if stop.wait(min(left, 0.5)):
                    return
            if stop.is_set():
                return
            own = burst.baud is not None and burst.baud != nominal
            result.off_nominal += own
            now = time.monotonic()
            result.lateness.append(max(0.0, now - due))
            result.times.append((due - start, now - start))
            if own and baud_faults:
                port.flush()
                port.baudrate = round(burst.baud)
                _write(port, burst.data, timeout)
                port.flush()
                port.baudrate = nominal
            else:
                _write(port, burst.data, timeout)
            result.bursts += 1
            result.bytes += len(burst.data)
        port.flush()
    except Exception as error:          # a port that went away: said in the result
        if _timed_out(error):
            result.error = (f"{result.name}: the port took no bytes for "
                            f"{port.write_timeout:.1f} s (write timeout): nothing reads its "
                            "other end, or flow control holds the line")
        else:
            result.error = f"{result.name}: {error or type(error).__name__}"
        stop.set()


def _timed_out(error):
    import queue
    import serial
    return isinstance(error, (serial.SerialTimeoutException, queue.Full, TimeoutError))


# --- record ---------------------------------------------------------------------------------

@dataclass
class ChannelRecord:
    """What :func:`record` read on one channel: its counters as the gateware counts them."""
    name: str
    kind: Kind
    bytes: int = 0
    counters: dict = field(default_factory=lambda: dict.fromkeys(COUNTER_NAMES, 0))
    #: Why the port stopped delivering before the end (None: it was open to the end).
    closed: str | None = None


@dataclass
class RecordResult:
    channels: dict
    frames: int
    log_bytes: int
    wall_s: float
    #: Why the recording ended: "seconds", "stopped", "interrupted" or "closed".
    reason: str


def record(ports, out, *, kinds=None, seconds=None, max_frame=DEFAULT_MAX_FRAME, stop=None,
           on_frame=None):
    """Read ``ports`` ({channel name: open serial port}) and write each kept frame to the
    binary file ``out`` as it completes (flushed at once), until ``seconds`` have passed,
    ``stop`` is set, Ctrl-C, or every port has closed. ``kinds``: {name: Kind} (default:
    :data:`CHANNEL_KINDS`). A frame still open at the end is neither written nor counted.
    Returns a :class:`RecordResult`."""
    kinds = {**CHANNEL_KINDS, **(kinds or {})}
    for name in ports:
        if name not in kinds:
            raise ValueError(f"channel must be one of {', '.join(kinds)}, not {name!r}")
    stop = stop or threading.Event()
    filters = {name: ReferenceFilter(kinds[name], max_frame) for name in ports}
    results = {name: ChannelRecord(name, kinds[name]) for name in ports}
    open_ports = dict(ports)
    frames = log_bytes = 0
    started = time.monotonic()
    deadline = None if seconds is None else started + seconds
    use_select = _all_have_fileno(ports.values())
    reason = "closed"

    def take(name, chunk):
        nonlocal frames, log_bytes
        results[name].bytes += len(chunk)
        filters[name].feed_all(chunk)
        if b"\n" not in chunk and b"$" not in chunk:
            return                      # no candidate can have closed
        kept = filters[name].take_frames()
        for frame in kept:
            out.write(frame)
            if on_frame is not None:
                on_frame(name, frame)
        if kept:
            out.flush()
            frames += len(kept)
            log_bytes += sum(map(len, kept))

    try:
        while open_ports:
            if stop.is_set():
                reason = "stopped"
                break
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                reason = "seconds"
                break
            wait = POLL_S if deadline is None else max(0.0, min(POLL_S, deadline - now))
            got = False
            if use_select:
                by_fd = {port.fileno(): name for name, port in open_ports.items()}
                ready, _, _ = select.select(list(by_fd), [], [], wait)
                names = [by_fd[fd] for fd in ready]
            else:
                names = list(open_ports)
            for name in names:
                port = open_ports[name]
                try:
                    chunk = port.read(max(1, port.in_waiting)) if use_select \
                        else port.read(port.in_waiting)
                except Exception as error:       # unplugged, hung up, closed
                    results[name].closed = str(error) or type(error).__name__
                    del open_ports[name]
                    continue
                if chunk:
                    got = True
                    take(name, chunk)
            if not use_select and not got:
                time.sleep(min(wait, 0.002))
    except KeyboardInterrupt:
        reason = "interrupted"
    finally:
        out.flush()
    for name in ports:
        results[name].counters = filters[name].result.counters
    return RecordResult(results, frames, log_bytes, time.monotonic() - started, reason)


def _all_have_fileno(ports):
    try:
        for port in ports:
            port.fileno()
    except (AttributeError, OSError, ValueError):
        return False
    return True


def expected_counters(system, k, max_frame=None):
    """The reference filter's counters over every byte channel ``k`` of ``system`` carries
    (what a :func:`record` of a whole :func:`replay` of it gives)."""
    kind = Kind(system.channels[k].kind.value)
    return reference_filter(kind, system.channel_bytes(k),
                            max_frame=max_frame or system.max_frame).counters
