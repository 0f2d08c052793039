"""Sustained sequential bandwidth of the SDRAM controller against the chip's peak.

Sequential word reads, then sequential word writes, go through ``SdramController`` with the
timing-checking chip model on its pins (Amaranth simulator, 50 MHz). The run spans many
refresh intervals and row and bank changes; the peak is one word per clock, so

    efficiency = words / clocks from the first request taken to the last word moved

Run from the repository root: ``.venv/bin/python bench/sdram_bandwidth.py``.
"""

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import load, packages, write_report

from maglog.hw.arch.sdram import IS42S16160, MT48LC4M32B2
from maglog.sim.backends.amaranth import run_requests

BENCH_DIR = Path(__file__).resolve().parent
DEFAULT_OUTPUT = BENCH_DIR / "results" / "sdram_bandwidth.json"
CLK_FREQ = 50e6


def measure(chip, words, *, write, cas_latency=2):
    requests = [(write, k, k * 0x01010101 & ((1 << chip.geometry.data_width) - 1),
                 (1 << chip.geometry.data_width // 8) - 1) for k in range(words)]
    start = time.perf_counter()
    got, info, model = run_requests(chip, requests, clk_freq=CLK_FREQ,
                                    cas_latency=cas_latency)
    wall = time.perf_counter() - start
    if model.errors:
        raise RuntimeError(f"the chip model reported: {model.errors[:3]}")
    if not write and len(got) != words:
        raise RuntimeError(f"{len(got)} words read, {words} expected")
    clocks = info["last"] - info["first"] + 1
    return {"chip": chip.name, "direction": "write" if write else "read", "words": words,
            "clocks": clocks, "refreshes": info["refreshes"], "efficiency": words / clocks,
            "bytes_per_second": words * chip.geometry.data_width / 8 / clocks * CLK_FREQ,
            "wall_seconds": wall}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--words", type=int, default=16384,
                        help="words per run (default: %(default)s)")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    load_start = load()
    results = []
    for chip in (MT48LC4M32B2, IS42S16160):
        for write in (False, True):
            result = measure(chip, args.words, write=write)
            results.append(result)
            print(f"{result['chip']:13s} {result['direction']:5s} {result['words']} words in "
                  f"{result['clocks']} clocks ({result['refreshes']} refreshes): "
                  f"{100 * result['efficiency']:.1f} % of one word a clock, "
                  f"{result['bytes_per_second'] / 1e6:.1f} MB/s at 50 MHz")
    write_report(args.output, "sdram_bandwidth", argv, load_start, packages("amaranth"),
                 results=results)
    return 0 if all(r["efficiency"] >= 0.8 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
