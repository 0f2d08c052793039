"""FrameFilter on the Amaranth simulator against the reference filter (sim/reference/)."""

import random

import pytest

from maglog.hw.arch.frames import COUNTER_NAMES
from maglog.hw.frame_filter import ChannelKind, FrameFilter
from maglog.sim.backends.amaranth import feed_stream, run_simulation
from maglog.sim.stimulus import sentences
from maglog.sim.runners.frontend import run_frame_filter as run_filter
from maglog.sim.reference import Kind, reference_filter
from maglog.sim.stimulus.streams import demo_streams


def check_against_reference(kind, events, **kwargs):
    frames, counters, flushes = run_filter(kind, events, **kwargs)
    ref = reference_filter(Kind(kind.value), events, max_frame=kwargs.get("max_frame", 128))
    assert frames == ref.frames
    assert counters == ref.counters
    assert flushes == len(ref.flushes)
    return ref


NMEA = ChannelKind.NMEA
PMAG = ChannelKind.PMAG
CESIUM = ChannelKind.CESIUM

GGA = sentences.gga(45296.5, 48.1173, 11.5167, quality=1)
GGA_NOFIX = sentences.gga(45297.5, 48.1173, 11.5167, quality=0)
ZDA = sentences.nmea_sentence("GNZDA,123456.00,21,11,2026,00,00")
VTG = sentences.nmea_sentence("GPVTG,054.7,T,034.4,M,005.5,N,010.2,K")
RMC = sentences.nmea_sentence("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W")
PMAG1 = sentences.pmag1(42, 20123.4, -3012.5, 45678.9)
CS = sentences.cesium(49895.131, 1249)


def padded(length, *, eol=b"\r\n"):
    """A valid GPVTG sentence of exactly ``length`` bytes."""
    base = sentences.nmea_sentence("GPVTG,", eol=eol)
    body = "GPVTG," + "0" * (length - len(base))
    frame = sentences.nmea_sentence(body, eol=eol)
    assert len(frame) == length
    return frame


EDGE_CASES = {
    # name: (kind, stream, expected kept frames, counter that must be non-zero or None)
    "empty frame": (NMEA, b"$\r\n", [], "not_whitelisted"),
    "empty frame bare LF": (CESIUM, b"$\n", [], "not_whitelisted"),
    "maximum length": (NMEA, padded(128), [padded(128)], None),
    "one over maximum": (NMEA, padded(129), [], "overlong"),
    "maximum length bare LF": (NMEA, padded(128, eol=b"\n"), [padded(128, eol=b"\n")], None),
    "back to back": (NMEA, GGA + ZDA + VTG + GGA_NOFIX, [GGA, ZDA, VTG, GGA_NOFIX], None),
    "stray dollar": (NMEA, GGA[:20] + ZDA, [ZDA], "bad_byte"),
    "cr without lf": (NMEA, GGA[:-1] + b"X" + ZDA, [ZDA], "bad_byte"),
    "cr then dollar": (NMEA, GGA[:-1] + ZDA, [ZDA], "bad_byte"),
    "non printable": (NMEA, GGA[:10] + b"\x01" + GGA[10:] + VTG, [VTG], "bad_byte"),
    "delete byte": (PMAG, PMAG1[:10] + b"\x7f" + PMAG1[10:], [], "bad_byte"),
    "bad checksum": (NMEA, sentences.nmea_sentence("GPGGA,1,2", checksum=0) + ZDA, [ZDA],
                     "checksum"),
    "lower case hex": (NMEA, GGA[:-4] + GGA[-4:-2].lower() + b"\r\n", [GGA[:-4] + GGA[-4:-2].lower() + b"\r\n"], None),
    "missing checksum": (NMEA, b"$GPGGA,1,2,3,4\r\n", [], "checksum"),
    "not whitelisted": (NMEA, RMC + ZDA, [ZDA], "not_whitelisted"),
    "lower case talker": (NMEA, b"$gpGGA,1*00\r\n", [], "not_whitelisted"),
    "cut short": (NMEA, b"$GPGG\r\n", [], "not_whitelisted"),
    "garbage between": (NMEA, b"noise\x00\xff" + GGA + b"\r\n\n" + ZDA, [GGA, ZDA], None),
    "pmag": (PMAG, PMAG1 + sentences.nmea_sentence("PMAG2,1") + PMAG1, [PMAG1, PMAG1],
             "not_whitelisted"),
    "cesium": (CESIUM, CS + b"$149895.500,0001\r\n" + b"$ 49895.131,1249\n",
               [CS, b"$149895.500,0001\r\n", b"$ 49895.131,1249\n"], None),
    "cesium short": (CESIUM, b"$ 49895.13,1249\r\n" + CS, [CS], "not_whitelisted"),
    "cesium long": (CESIUM, b"$ 49895.1311,1249\r\n" + CS, [CS], "not_whitelisted"),
    "cesium bad sign": (CESIUM, b"$249895.131,1249\r\n", [], "not_whitelisted"),
    "cesium tail": (CESIUM, b"$ 49895.131,12490\r\n", [], "not_whitelisted"),
}


@pytest.mark.parametrize("name", EDGE_CASES)
def test_edge_case(name):
    kind, stream, expected, counter = EDGE_CASES[name]
    frames, counters, _ = run_filter(kind, list(stream))
    assert frames == expected
    if counter is not None:
        assert counters[counter] >= 1
    ref = reference_filter(Kind(kind.value), stream)
    assert frames == ref.frames and counters == ref.counters


def test_uart_error_inside_and_outside_frames():
    events = ([(0x55, True)] + list(GGA[:30]) + [(0x24, True)] + list(GGA[30:]) + list(ZDA)
              + [(0, True)])
    frames, counters, _ = run_filter(NMEA, events)
    assert frames == [ZDA]
    assert counters["uart_error"] == 1
    check_against_reference(NMEA, events)


@pytest.mark.parametrize("quality,flush", [("1", 1), ("2", 1), ("9", 1), ("0", 0), ("", 0),
                                          ("12", 0), ("A", 0)])
def test_flush_event_follows_gga_fix_quality(quality, flush):
    frame = sentences.nmea_sentence(f"GNGGA,120000.00,4807.0,N,01131.0,E,{quality},08,0.9,"
                                    f"545.4,M,46.9,M,,")
    frames, _, flushes = run_filter(NMEA, list(frame + VTG))
    assert frames == [frame, VTG]
    assert flushes == flush
    check_against_reference(NMEA, list(frame))


def test_gga_with_too_few_fields_raises_no_flush():
    frame = sentences.nmea_sentence("GPGGA,1,2,3,4,5")
    _, _, flushes = run_filter(NMEA, list(frame))
    assert flushes == 0


def test_max_frame_parameter():
    frames, counters, _ = run_filter(NMEA, list(padded(82) + padded(83)), max_frame=82)
    assert frames == [padded(82)]
    assert counters["overlong"] == 1


def test_fifo_full_drops_whole_frames_and_keeps_the_rest():
    frames_in = [sentences.pmag1(i, i, -i, 2 * i) for i in range(12)]
    stream = b"".join(frames_in)
    depth = 256
    # The sink is stalled while the stream arrives: the FIFO fills, then drops.
    stall = len(stream) + 64
    frames, counters, _ = run_filter(PMAG, list(stream), fifo_depth=depth,
                                     ready=lambda cycle: cycle > stall, tail_cycles=1000)
    fit = depth // len(frames_in[0])
    assert frames == frames_in[:fit]
    assert counters["overflow"] == len(frames_in) - fit
    assert counters["kept"] == fit


def test_fifo_accepts_frames_again_after_draining():
    frames_in = [sentences.pmag1(i, i, 0.5, 1.5) for i in range(10)]
    stream = b"".join(frames_in)
    depth = 256
    cycles_per_frame = len(frames_in[0])
    # Stall for the first eight frames' arrival, then drain; the last two get in again.
    stall = 8 * cycles_per_frame
    frames, counters, _ = run_filter(PMAG, list(stream), fifo_depth=depth,
                                     ready=lambda cycle: cycle > stall, tail_cycles=1000)
    fit = depth // cycles_per_frame
    assert frames == frames_in[:fit] + frames_in[8:]
    assert counters["overflow"] == 8 - fit


def test_sink_backpressure_keeps_frames_whole():
    stream = b"".join([GGA, ZDA, VTG] * 5)
    rng = random.Random(7)
    pattern = [rng.random() < 0.6 for _ in range(4096)]
    frames, _, _ = run_filter(NMEA, list(stream), ready=lambda cycle: pattern[cycle % 4096],
                              tail_cycles=4000)
    assert frames == [GGA, ZDA, VTG] * 5


def test_demo_streams():
    streams = demo_streams(seconds=1.0, seed=3)
    for kind, name in ((PMAG, "mag"), (NMEA, "gps"), (CESIUM, "cesium")):
        ref = check_against_reference(kind, list(streams[name]))
        assert ref.counters["kept"] > 0


# --- seeded random fuzz -------------------------------------------------------------------

def _valid_frames(kind, rng):
    if kind == NMEA:
        talker = rng.choice(["GP", "GN", "GL", "GA", "BD"])
        t = rng.uniform(0, 86400)
        choice = rng.randrange(6)
        if choice == 0:
            return sentences.gga(t, rng.uniform(-89, 89), rng.uniform(-179, 179),
                                 quality=rng.randrange(10), talker=talker)
        if choice == 1:
            return sentences.vtg(rng.uniform(0, 359), rng.uniform(0, 50), talker=talker)
        if choice == 2:
            return sentences.nmea_sentence(f"{talker}ZDA,{t:09.2f},21,11,2026,00,00")
        if choice == 3:
            return sentences.nmea_sentence(f"{talker}GSV,3,1,11,03,03,111,00,04,15,270,00")
        if choice == 4:
            return RMC
        return sentences.nmea_sentence(f"{talker}GGA," + ",".join(
            str(rng.randrange(10)) * rng.randrange(3) for _ in range(rng.randrange(20))))
    if kind == PMAG:
        return sentences.pmag1(rng.randrange(100000), rng.uniform(-99999, 99999),
                               rng.uniform(-99999, 99999), rng.uniform(-99999, 99999))
    return sentences.cesium(rng.uniform(0, 199999.999), rng.randrange(10000))


def fuzz_events(kind, rng, count):
    """At least ``count`` events: frames, mutated frames, noise, errors."""
    events = []
    printable = bytes(range(0x20, 0x7F))
    while len(events) < count:
        frame = bytearray(_valid_frames(kind, rng))
        roll = rng.random()
        if roll < 0.45:
            pass
        elif roll < 0.55:
            frame[rng.randrange(1, len(frame))] = rng.choice(printable)
        elif roll < 0.6:
            frame.insert(rng.randrange(1, len(frame)), rng.randrange(256))
        elif roll < 0.65:
            del frame[rng.randrange(len(frame)):]
        elif roll < 0.7:
            frame[-2:] = b"\n" if rng.random() < 0.5 else b"\r"
        elif roll < 0.75:
            at = 1 if kind == CESIUM else 7     # past the address field: overlong, not foreign
            frame[at:at] = bytes(rng.choice(printable) for _ in range(rng.randrange(60, 140)))
        elif roll < 0.8:
            frame = bytearray(rng.randrange(256) for _ in range(rng.randrange(1, 40)))
        elif roll < 0.85:
            frame[-4:-2] = frame[-4:-2].lower()
        elif roll < 0.9:
            frame.insert(rng.randrange(1, len(frame)), ord("$"))
        items = [(b, False) for b in frame]
        if rng.random() < 0.05 and items:
            k = rng.randrange(len(items))
            items[k] = (items[k][0], True)
        events.extend(items)
    return events


@pytest.mark.parametrize("kind", [NMEA, PMAG, CESIUM], ids=lambda k: k.value)
def test_random_fuzz_matches_reference(kind):
    rng = random.Random(f"fuzz-{kind.value}")
    events = fuzz_events(kind, rng, 100_000)
    ref = check_against_reference(kind, events, max_frame=128)
    # The fuzz reaches every cause the kind can have (no FIFO overflow at one byte a cycle).
    impossible = {"overflow"} | ({"checksum", "overlong"} if kind == CESIUM else set())
    assert all(ref.counters[name] > 10 for name in COUNTER_NAMES if name not in impossible)


@pytest.mark.parametrize("kwargs,message", [
    ({"max_frame": 10}, "Maximum frame length must be an integer from 11 to 1024, not 10"),
    ({"max_frame": 1025}, "Maximum frame length must be an integer from 11 to 1024, not 1025"),
    ({"fifo_depth": 64}, "FIFO depth must hold at least one frame of 128 bytes, not 64"),
    ({"fifo_depth": 1 << 16}, "FIFO depth must be at most 32768 bytes (the block RAM of the "
                              "target), not 65536"),
])
def test_parameters_the_design_cannot_build(kwargs, message):
    with pytest.raises(ValueError) as error:
        FrameFilter(ChannelKind.PMAG, **kwargs)
    assert str(error.value) == message


@pytest.mark.parametrize("kind", [NMEA, PMAG, CESIUM])
def test_events_strobe_once_per_count_and_width_0_leaves_only_them(kind):
    """``events`` (what a counter bank counts) strobe exactly when the counters count; with
    ``counter_width=0`` there are no counter registers, the same strobes."""
    streams = demo_streams(seconds=1.0, seed=4)
    data = {NMEA: streams["gps"], PMAG: streams["mag"], CESIUM: streams["cesium"]}[kind]
    rng = random.Random(8)
    events = [(b, rng.random() < 0.002) for b in data[:3000]] + [(ord("$"), False)] * 3
    ref = reference_filter(Kind(kind.value), events)
    assert sum(ref.counters.values()) > len(ref.frames) > 0
    for width in (32, 0):
        dut = FrameFilter(kind, counter_width=width)
        assert ("counters" in dut.signature.members) == bool(width)
        strobes = dict.fromkeys(COUNTER_NAMES, 0)

        async def source(ctx):
            await feed_stream(ctx, dut.i, [{"data": b, "framing_error": int(e)}
                                           for b, e in events])
            await ctx.tick().repeat(4)
            if width:
                assert {n: ctx.get(getattr(dut.counters, n)) for n in COUNTER_NAMES} == strobes

        async def count(ctx):
            ctx.set(dut.o.ready, 1)
            async for _, _, value in ctx.tick().sample(dut.events):
                for i, name in enumerate(COUNTER_NAMES):
                    strobes[name] += value >> i & 1

        run_simulation(dut, [source], background=[count], name=f"filter_events_{width}")
        assert strobes == ref.counters, width
