"""Multi-block write throughput of the SD host against the 4-bit bus limit.

The firmware's driver writes N blocks with one CMD25 through the SdioHost (Amaranth
simulator) to the card model. Every SD clock edge is recorded: the data phase runs from the
first block's start bit to the end of the last block's busy; the card's busy clocks are
excluded. The 4-bit bus limit is 1024 clocks per 512-byte block, so

    efficiency = 1024 * N / (data-phase clocks - busy clocks)

It also counts the clock's pauses in the data phase: the host holds the SD clock low when
the next bit is not ready (``SdClock.run``), so every SD clock period (rising edge to rising
edge, in system clock cycles) longer than the divisor's period is a pause for data.

Run from the repository root: ``.venv/bin/python bench/sdio_throughput.py``.
"""

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import load, packages, write_report

from maglog.hw.arch import sd as arch
from maglog.hw.sdio.host import SdioHost
from maglog.sim.backends.amaranth import run_simulation
from maglog.sim.models.card_image import CardImage
from maglog.sim.models.sdcard import SdCard
from maglog.sim.backends.amaranth import CsrBus, StreamBlockPort, run_card
from maglog.sw.regmap import RegisterMap
from maglog.sw.sdcard import SdCardDriver

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results" / "sdio_throughput.json"


class RecordingCard:
    """The card model, with a record of (host drives DAT, card busy, system clock cycle) at
    every rising edge of the SD clock."""
    def __init__(self, card):
        self._card = card
        self.edges = []
        self.host_dat_oe = 0
        self.cycle = 0

    def edge(self, cmd, dat):
        result = self._card.edge(cmd, dat)
        self.edges.append((self.host_dat_oe, self._card.busy, self.cycle))
        return result

    def report(self, message):
        self._card.report(message)


def measure(blocks, *, sys_clock_hz, busy_clocks, seed):
    host = SdioHost()
    regs = RegisterMap(host.bus.memory_map)
    # The simulation runs at the clock the driver is told (one figure for both).
    port = StreamBlockPort(host, clock_period=1 / sys_clock_hz)
    card = SdCard(CardImage(1 << 16), seed=seed, busy_clocks=busy_clocks)
    recorder = RecordingCard(card)
    data = bytes((k * 7) & 0xFF for k in range(blocks * arch.BLOCK_BYTES))
    marks = {}

    async def firmware(ctx):
        bus = CsrBus(ctx, host.bus, clock_period=1 / sys_clock_hz)
        port.attach(ctx)
        driver = SdCardDriver(bus, regs, port, sys_clock_hz=sys_clock_hz)
        await driver.initialise()
        marks["sd_clock_hz"] = driver.sd_clock_hz
        marks["start"] = len(recorder.edges)
        await driver.write_blocks(1000, data, pre_erase=False)
        marks["end"] = len(recorder.edges)

    async def card_side(ctx):
        await run_card(ctx, host.sd, recorder)

    async def cycle_count(ctx):
        async for _ in ctx.tick():
            recorder.cycle += 1

    async def dat_watch(ctx):
        while True:
            await ctx.changed(host.sd.dat_oe)
            recorder.host_dat_oe = ctx.get(host.sd.dat_oe)

    start = time.perf_counter()
    run_simulation(host, [firmware], background=[card_side, dat_watch, cycle_count, port.source, port.sink],
                   name="sdio_throughput", clock_period=1 / sys_clock_hz)
    wall = time.perf_counter() - start
    if card.errors:
        raise RuntimeError(f"the card model reported: {card.errors[:3]}")
    edges = recorder.edges[marks["start"]:marks["end"]]
    first = next(i for i, (oe, _, _) in enumerate(edges) if oe)
    last_busy = max(i for i, (_, busy, _) in enumerate(edges) if busy)
    phase = edges[first:last_busy + 1]
    busy = sum(1 for _, b, _ in phase if b)
    clocks = len(phase) - busy
    # SD clock periods in system clock cycles through the data phase: any longer than the
    # divisor's period is a pause (the clock held low for data).
    period = round(sys_clock_hz / marks["sd_clock_hz"])
    periods = [b[2] - a[2] for a, b in zip(phase, phase[1:])]
    long_periods = [p for p in periods if p > period]
    # Where each pause was: the SD clock edge (from the first start bit), whether the card
    # was busy, and the pause's length in system cycles.
    starts = [k for k in range(1, len(phase)) if phase[k][0] and not phase[k - 1][0]]
    pauses = [{"edge": k + 1, "block": 1 + sum(1 for s in starts if s <= k + 1),
               "host_drives_dat": bool(phase[k + 1][0]), "card_busy": bool(phase[k + 1][1]),
               "edges_since_host_released_dat": next(
                   (k + 1 - j for j in range(k + 1, 0, -1)
                    if phase[j - 1][0] and not phase[j][0]), None),
               "extra_cycles": p - period}
              for k, p in enumerate(periods) if p > period]
    return {
        "blocks": blocks,
        "data_phase_clocks": len(phase),
        "busy_clocks": busy,
        "clocks_excluding_busy": clocks,
        "bus_limit_clocks": blocks * arch.DATA_NIBBLES,
        "efficiency": blocks * arch.DATA_NIBBLES / clocks,
        "clocks_per_block": clocks / blocks,
        "sd_clock_hz": marks["sd_clock_hz"],
        "sys_clock_hz": sys_clock_hz,
        "sd_clock_period_cycles": period,
        "sd_clock_periods_checked": len(periods),
        "shortest_period_cycles": min(periods),
        "clock_pauses": len(long_periods),
        "paused_cycles": sum(p - period for p in long_periods),
        "pauses": pauses,
        "pauses_while_host_drives_dat": sum(1 for p in pauses if p["host_drives_dat"]),
        "wall_seconds": wall,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--blocks", type=int, default=16, help="blocks in the CMD25 (16)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    result = measure(args.blocks, sys_clock_hz=4e6, busy_clocks=(8, 64), seed=1)
    print(f"{result['blocks']} blocks: {result['clocks_excluding_busy']} SD clocks outside busy "
          f"for {result['bus_limit_clocks']} data clocks: efficiency "
          f"{100 * result['efficiency']:.2f} % ({result['clocks_per_block']:.1f} clocks a "
          f"block; busy {result['busy_clocks']} clocks excluded); the clock paused "
          f"{result['clock_pauses']} times ({result['paused_cycles']} system "
          f"cycles) over {result['sd_clock_periods_checked']} periods, "
          f"{result['pauses_while_host_drives_dat']} of them while the host drove DAT")
    write_report(args.output, "sdio_throughput", argv, load_start, packages("amaranth"),
                 result=result)
    return 0 if result["efficiency"] >= 0.95 else 1


if __name__ == "__main__":
    sys.exit(main())
