"""Inputs for the summary and papers tests: a synthetic flight's log written into a card
image by the logger's own FAT32 writer (sw.fat32), and a truth dict (truth.json's schema)
made from the same flight (tests/cli/conftest.py makes the fixtures from them)."""

import asyncio
import datetime
import hashlib

import numpy as np

from maglog.cli.summary import CAUSES, log_frames
from maglog.sw.fat32 import ImageFile, Volume, format_image

CARD_BYTES = 64 << 20
T0 = datetime.datetime(2026, 6, 1, 10, 0, 0)


def write_card(path, data):
    """A formatted card image at ``path`` holding one log file with ``data``."""
    format_image(path, CARD_BYTES, cluster_bytes=512, volume_id=0x1234)

    async def work():
        with ImageFile(path) as device:
            volume = await Volume.mount(device)
            log = await volume.create_log(T0)
            for start in range(0, len(data), 4096):
                await log.append(data[start:start + 4096])
            await log.close(T0)
            await volume.close()
    asyncio.run(work())
    return path


def truth_for(flight, data, *, scenario="test"):
    """truth.json's content for ``flight`` logged as ``data``: every frame kept, none
    dropped; the noise floor is the residual of the true parameters on the flight."""
    counts, _ = log_frames(data)
    k, c = flight.errors.truth()
    floor = float(np.sqrt(np.mean((np.linalg.norm(flight.b_meas @ k.T - c, axis=1)
                                   - flight.total) ** 2)))
    a = flight.errors.matrix()
    frames = {ch: {**dict.fromkeys(CAUSES, 0), "kept": counts[ch], "sent_bytes": 0,
                   "flushes": 0} for ch in counts}
    return {"version": 1, "scenario": scenario, "seed": 5, "clk_freq": 1_843_200,
            "channels": [{"name": ch, "kind": kind, "baud": baud, "baud_actual": baud}
                         for ch, kind, baud in (("mag", "pmag", 115200), ("gps", "nmea", 9600),
                                                ("cesium", "cesium", 9600))],
            "frames": frames,
            "recorded": {"frames": sum(counts.values()), "per_channel": counts,
                         "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)},
            "faults": [],
            "errors": {"preset": "default", "K": k.tolist(), "c": c.tolist(),
                       "A": a.tolist(),
                       "b": (a @ np.array(flight.errors.hard_iron)
                             + np.array(flight.errors.bias)).tolist(),
                       "noise_nT": flight.errors.noise,
                       "mounting_deg": list(flight.errors.mounting)},
            "reference": {"cesium_noise_nT": 0.05,
                          "igrf_total_nT_mean": float(np.mean(flight.total))},
            "noise_floor_nT": floor,
            "flight": {"phases": [{"name": "calibration", "start_s": 0.0,
                                   "end_s": float(flight.t[-1])}],
                       "samples": int(flight.t.size), "mag_rate_hz": 20.0,
                       "cesium_rate_hz": 10.0, "attitude_csv": "attitude.csv"}}
