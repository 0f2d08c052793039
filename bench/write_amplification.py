"""Card writes per flush and write amplification of the firmware's sync scheme.

A calibration flight (``flight_scenario(make_flight(seconds=S))``: magnetometer 20 Hz,
cesium 10 Hz, GGA + ZDA + VTG once a second, so one GGA fix and one flush a second) is
recorded by the firmware (sw/app.py) on the transaction-level logger model. Every block
the card stores is traced with its LBA and sorted into its region (data, FAT 1, FAT 2,
directory, FSInfo, boot) and its phase (the flush it belongs to, or the file's creation
and close). Reported per cluster size:

* card block writes per flush, by region (mean, least, most), over the flushes of the
  recording (the final flush included);
* write amplification: bytes the card stored over the whole recording (creation and close
  included) per byte of the log file, and the same over the flushes alone;
* the floor of the sync scheme, worked out from the bytes a flush moves, ``b`` (bytes
  logged per second times the flush period), the sector ``s = 512`` and the cluster ``c``:

  - data sectors: the flush writes from the synced size's sector to the new end, so the
    partial last sector is written again; for a partial offset uniform over the sector
    that is ``b/s + 1`` sectors on average;
  - one directory sector (the size), every flush;
  - a cluster is allocated in a fraction ``min(1, b/c)`` of the flushes, and then one FAT
    sector in each of the two FATs (and two more, once every 128 clusters, when the
    chain crosses a FAT sector, neglected);
  - FSInfo: the firmware (sw/fat32.py) writes it only when its free count or next-free
    hint changed, i.e. with an allocation; a scheme writing it every sync costs one sector
    a flush more.

  So ``WA_floor = (b + s * (p + 1 + 2a + f)) / b`` with ``a = min(1, b/c)`` (:data:`FORMULA`),
  worked out for the firmware's scheme and two leaner ones (:data:`SCHEMES`); the flush
  period each needs to reach the goal is solved from the same formula.

Run from the repository root: ``.venv/bin/python bench/write_amplification.py``.
"""

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import load, packages, write_report

from maglog.calib.card import read_logs
from maglog.hw.arch import fat32 as arch
from maglog.sim.models.card_image import TracingImage
from maglog.sim.models.logger import LoggerModel
from maglog.sim.stimulus.scenario import make_flight
from maglog.sim.stimulus.system import flight_scenario
from maglog.sw.app import AppSettings, LoggerApp
from maglog.sw.fat32 import ImageFile, Volume, format_image

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results" / "write_amplification.json"
SECTOR = arch.SECTOR_BYTES
REGIONS = ("data", "fat1", "fat2", "directory", "fsinfo", "boot")
#: The issue's goal: bytes written to the card per byte logged.
GOAL = 1.5
#: A 4 GiB card: FAT32 with 32 KiB clusters needs more than 65,524 clusters (2 GiB).
CARD_BYTES = 4 << 30


FORMULA = ("WA_floor = (b + s*(p + 1 + 2*a + f)) / b, a = min(1, b/c): b bytes a flush, "
           "s = 512 bytes a sector, c bytes a cluster; p = 1 the partial last sector "
           "written again (its mean over a uniform offset; 0 when only whole sectors are "
           "written), 1 the directory sector, 2*a one FAT sector in each FAT in the flushes "
           "that allocate a cluster (0 with clusters allocated far ahead), f FSInfo (a only on "
           "allocation as the firmware does, 1 every flush, 0 only at close)")


def layout_of(path):
    """The FAT32 geometry of a card image (the firmware's own mount, on the host)."""
    with ImageFile(path) as device:
        coroutine = Volume.mount(device)
        try:
            coroutine.send(None)
        except StopIteration as stop:
            return stop.value.layout
    raise RuntimeError("mounting on the host awaited something")


def region(layout, lba, directory):
    if lba < layout.fat_start:
        return "fsinfo" if lba == layout.partition_start + layout.fsinfo_sector else "boot"
    if lba < layout.fat_start + layout.fat_sectors:
        return "fat1"
    if lba < layout.data_start:
        return "fat2"
    cluster = (lba - layout.data_start) // layout.sectors_per_cluster + \
        arch.FIRST_DATA_CLUSTER
    return "directory" if cluster in directory else "data"


#: Sync schemes, each as the sectors a flush of ``b`` bytes writes at least, by region, with
#: clusters of ``c`` bytes (``a = min(1, b/c)``: the share of flushes that allocate).
SCHEMES = {
    # The firmware's (sw/storage.py, sw/fat32.py): the partial sector written again, the
    # directory sector, FAT sectors and FSInfo on allocation.
    "firmware": lambda b, c, a: {"data": b / SECTOR + 1, "directory": 1.0, "fat1": a,
                                 "fat2": a, "fsinfo": a},
    # The same with FSInfo written at every sync (the firmware before 3ba4cb2).
    "fsinfo_every_sync": lambda b, c, a: {"data": b / SECTOR + 1, "directory": 1.0,
                                          "fat1": a, "fat2": a, "fsinfo": 1.0},
    # Only whole sectors each flush (the partial one stays in the ring, not yet durable),
    # clusters allocated far ahead (FAT amortised to nothing, a chain longer than the size
    # between syncs), FSInfo at close: the directory sector is all that is left.
    "whole_sectors_preallocated": lambda b, c, a: {"data": b / SECTOR, "directory": 1.0,
                                                   "fat1": 0.0, "fat2": 0.0, "fsinfo": 0.0},
}


def floor(scheme, bytes_per_flush, cluster_bytes):
    """Sectors a flush writes at least under ``scheme``, by region, and the write
    amplification."""
    allocating = min(1.0, bytes_per_flush / cluster_bytes)
    sectors = SCHEMES[scheme](bytes_per_flush, cluster_bytes, allocating)
    return sectors, SECTOR * sum(sectors.values()) / bytes_per_flush


def period_for(goal, scheme, bytes_per_second, cluster_bytes):
    """The shortest flush period (s, to 0.1 s) whose floor meets ``goal``."""
    for tenths in range(1, 6000):
        period = tenths / 10
        if floor(scheme, period * bytes_per_second, cluster_bytes)[1] <= goal:
            return period
    return None


def measure(seconds, cluster_bytes, work):
    scenario = flight_scenario(make_flight(seconds=seconds))
    blank = work / f"blank-{cluster_bytes}.img"
    format_image(blank, CARD_BYTES, cluster_bytes=cluster_bytes, volume_id=0x4D474C47)
    layout = layout_of(blank)
    card = TracingImage.load(blank)
    model = LoggerModel(card, clk_freq=scenario.clk_freq, channels=scenario.channels,
                        max_frame=scenario.max_frame, debounce_s=scenario.debounce_s)
    for burst in scenario.bursts:
        model.feed(burst.channel, burst.data, start=burst.start)
    for press in scenario.presses:
        model.press_button(press, hold=scenario.hold)
    flush_starts, apps = [], []

    async def fault(app, point):
        if point == "flush":
            flush_starts.append(len(card.lbas))

    async def firmware(bus):
        app = LoggerApp(bus, model.memory_map, sys_clock_hz=model.clk_freq,
                        settings=AppSettings(fault=fault))
        apps.append(app)
        await app.run()

    start = time.perf_counter()
    result = model.run(firmware, until=scenario.until)
    wall = time.perf_counter() - start
    (app,) = apps
    if result.power_cut or result.resets or app.error:
        raise RuntimeError(f"the recording did not run cleanly: resets {result.resets}, "
                           f"error {app.error!r} {app.message}")
    image = work / f"card-{cluster_bytes}.img"
    card.save(image)
    logs = dict(read_logs(image))
    recording = b"".join(scenario.recorded_frames())
    if logs != {"LOG00001.TXT": recording}:
        raise RuntimeError("the card does not hold the recording")
    image.unlink()

    # The root directory's clusters, from the FAT the recording left.
    directory, cluster = set(), layout.root_cluster
    while arch.FIRST_DATA_CLUSTER <= cluster < arch.FAT_EOC_MIN:
        directory.add(cluster)
        lba, offset = divmod(cluster * 4, SECTOR)
        entry = card.read_block(layout.fat_start + lba)[offset:offset + 4]
        cluster = int.from_bytes(entry, "little") & arch.FAT_ENTRY_MASK
    regions = [region(layout, lba, directory) for lba in card.lbas]

    # Flush k's writes run from its start to the next flush's start; the last flush ends at
    # its directory sector (and FSInfo, when it allocated): the close's writes follow
    # (directory, then the clean bit in each FAT).
    bounds = flush_starts + [len(regions)]
    flushes = [regions[a:b] for a, b in zip(bounds, bounds[1:])]
    last = flushes[-1]
    end = last.index("directory") + 1
    if end < len(last) and last[end] == "fsinfo":
        end += 1
    flushes[-1], close = last[:end], last[end:]
    per_flush = {name: [f.count(name) for f in flushes] for name in REGIONS}
    flush_blocks = sum(len(f) for f in flushes)
    logged = len(recording)
    recording_seconds = scenario.presses[1] - scenario.presses[0]
    bytes_per_second = logged / seconds     # the instruments send for the flight's length
    bytes_per_flush = logged / len(flushes)
    floors = {}
    for scheme in SCHEMES:
        sectors, wa = floor(scheme, bytes_per_flush, cluster_bytes)
        floors[scheme] = {"sectors_per_flush": sectors, "write_amplification": wa,
                          "flush_period_for_goal_s": period_for(GOAL, scheme, bytes_per_second,
                                                                cluster_bytes)}
    return {
        "cluster_bytes": cluster_bytes,
        "flight_seconds": seconds,
        "recording_seconds": recording_seconds,
        "bytes_logged": logged,
        "bytes_per_second": bytes_per_second,
        "flushes": len(flushes),
        "bytes_per_flush": bytes_per_flush,
        "blocks_written": len(regions),
        "blocks_by_region": {name: regions.count(name) for name in REGIONS},
        "blocks_before_first_flush": flush_starts[0],
        "blocks_of_close": len(close),
        "per_flush": {name: {"mean": statistics.fmean(counts), "min": min(counts),
                             "max": max(counts)} for name, counts in per_flush.items()},
        "blocks_per_flush": flush_blocks / len(flushes),
        "write_amplification": len(regions) * SECTOR / logged,
        "write_amplification_flushes": flush_blocks * SECTOR / logged,
        "floor": floors,
        "wall_seconds": wall,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=120.0,
                        help="length of the flight (120 s)")
    parser.add_argument("--clusters", type=int, nargs="+", default=[4096, 32768],
                        help="cluster sizes in bytes (4096 32768)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    results = []
    with tempfile.TemporaryDirectory(prefix="maglog-wa-") as work:
        for cluster_bytes in args.clusters:
            r = measure(args.seconds, cluster_bytes, Path(work))
            results.append(r)
            pf = r["per_flush"]
            print(f"{cluster_bytes // 1024} KiB clusters: {r['bytes_logged']} bytes in "
                  f"{r['flushes']} flushes ({r['bytes_per_flush']:.0f} B each); per flush "
                  + ", ".join(f"{name} {pf[name]['mean']:.2f}" for name in REGIONS)
                  + f"; WA {r['write_amplification']:.3f} (flushes alone "
                  f"{r['write_amplification_flushes']:.3f}); floors "
                  + ", ".join(f"{name} {f['write_amplification']:.3f}"
                              for name, f in r["floor"].items()) + f"; goal {GOAL}")
    write_report(args.output, "write_amplification", argv, load_start,
                 packages("amaranth"), goal=GOAL, card_bytes=CARD_BYTES,
                 formula=FORMULA,
                 results=results)
    return 0 if all(r["write_amplification"] <= GOAL for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
