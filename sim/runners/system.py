"""The system runner: one scenario, the firmware and the whole logger on a chosen backend,
to a card image.

Backends (:data:`BACKENDS`):

``model``
    the transaction-level model of the logger (sim/models/logger.py): no RTL, seconds.
``amaranth``
    the gateware in Amaranth's simulator, device models on the pins (per pin, in Python).
``icarus``, ``verilator-cocotb``
    the generated Verilog under cocotb, device models on the pins (per pin, in Python).
``verilator``
    the generated Verilog under Verilator with the C++ harness of
    :mod:`maglog.sim.backends.fast` (Python per frame, command and block): the one fast
    enough for whole flights.

Every backend runs the same firmware (:class:`~maglog.sw.app.LoggerApp`) and must leave
the same card image for the same scenario (tests/system).
"""

import importlib.util
import shutil
import time
from pathlib import Path

from ...hw.arch.sdram import MT48LC4M32B2
from ..stimulus.system import SystemScenario
from .result import SystemResult


__all__ = ["BACKENDS", "RTL_BACKENDS", "BackendUnavailable", "available",
           "run_system"]

BACKENDS = ("model", "amaranth", "icarus", "verilator", "verilator-cocotb")
#: The backends that run the gateware itself, fastest first.
RTL_BACKENDS = ("verilator", "verilator-cocotb", "icarus", "amaranth")
#: Measured clocks a second on the whole logger (bench/system_speed.py, observations
#: for the per-pin ones), for the estimate a run prints before it starts.
CLOCKS_PER_SECOND = {"verilator": 1.6e6, "verilator-cocotb": 6e4, "icarus": 2e4,
                     "amaranth": 4e3}


class BackendUnavailable(RuntimeError):
    """A backend's simulator or compiler is not installed."""


def _missing(backend):
    """Why ``backend`` cannot run here, or None."""
    from ..backends.cocotb import verilator_bin_dir
    if backend in ("model", "amaranth"):
        return None
    if backend in ("icarus", "verilator-cocotb") and importlib.util.find_spec("cocotb") is None:
        return "cocotb is not installed (pip install 'maglog[sim]')"
    if backend == "icarus":
        return None if shutil.which("iverilog") else ("iverilog (Icarus Verilog) is not on "
                                                      "PATH (Debian/Ubuntu: apt-get install "
                                                      "iverilog)")
    try:
        verilator_bin_dir()
    except RuntimeError as error:
        return str(error)
    if not (shutil.which("c++") or shutil.which("g++")):
        return "no C++ compiler on PATH (Debian/Ubuntu: apt-get install build-essential)"
    return None


def available():
    """``{backend: None or why it cannot run here}``."""
    return {backend: _missing(backend) for backend in BACKENDS}


def estimate_seconds(scenario, backend):
    """A rough wall-clock estimate of a run (from :data:`CLOCKS_PER_SECOND`)."""
    if backend == "model":
        return None
    return scenario.until * scenario.clk_freq / CLOCKS_PER_SECOND[backend]


def run_system(scenario, image, *, backend, build_dir="build/sim", settings=None,
               card_seed=0, card_options=None, busy_spikes=(), chip=MT48LC4M32B2,
               progress=None, log=None):
    """Run ``scenario`` on ``backend`` with the application firmware (``settings``: an
    :class:`~maglog.sw.app.AppSettings`), the card model holding ``image`` (a
    :class:`~maglog.sim.models.card_image.CardImage`, changed in place). Returns a
    :class:`~maglog.sim.runners.result.SystemResult` with ``backend`` set and, where the backend
    reads them, the front end's ``counters``.

    ``busy_spikes`` (card programming slowed in time windows) are modelled by the
    ``verilator`` and ``model`` backends and refused by the others. Bursts off their
    channel's nominal rate (:attr:`~maglog.sim.stimulus.system.Burst.baud`) run at that rate on
    every backend (the model's receivers sample them as the gateware's do)."""
    from ...sw.app import AppSettings, LoggerApp
    if backend not in BACKENDS:
        raise ValueError(f"Backend must be one of {', '.join(BACKENDS)}, not {backend!r}")
    if not isinstance(scenario, SystemScenario):
        raise TypeError(f"Scenario must be a SystemScenario, not {scenario!r}")
    why = _missing(backend)
    if why is not None:
        raise BackendUnavailable(f"backend {backend} cannot run here: {why}")
    if busy_spikes and backend not in ("verilator", "model"):
        raise ValueError(f"card busy spikes run on the verilator and model backends only, "
                         f"not {backend}")
    settings = settings if settings is not None else AppSettings()

    async def firmware(bus, memory_map, sys_clock_hz):
        await LoggerApp(bus, memory_map, sys_clock_hz=sys_clock_hz, settings=settings).run()

    build_dir = Path(build_dir)
    if backend == "verilator":
        from ..backends.fast import run_system_fast
        return run_system_fast(scenario, image, build_dir=build_dir, settings=settings,
                               chip=chip, card_seed=card_seed, card_options=card_options,
                               busy_spikes=busy_spikes, progress=progress, log=log)
    if backend == "model":
        result = _run_model(scenario, firmware, image, card_seed=card_seed,
                            card_options=card_options, busy_spikes=busy_spikes)
    elif backend == "amaranth":
        from ..backends.amaranth import run_system as run_amaranth
        result = run_amaranth(scenario, firmware, image, chip=chip, card_seed=card_seed)
    else:
        from ..backends.cocotb_system import run_system_cocotb
        simulator = "verilator" if backend == "verilator-cocotb" else "icarus"
        result = run_system_cocotb(scenario, image, backend=simulator,
                                   build_dir=build_dir / f"cocotb-{simulator}",
                                   settings=settings, chip=chip, card_seed=card_seed)
    result.backend = backend
    return result


def _run_model(scenario, firmware, image, *, card_seed, card_options, busy_spikes):
    from ..models.logger import LoggerModel
    from ..backends.fast import CHANNEL_NAMES
    options = dict(card_options or {})
    model = LoggerModel(image, clk_freq=scenario.clk_freq, channels=scenario.channels,
                        max_frame=scenario.max_frame, debounce_s=scenario.debounce_s,
                        seed=card_seed, **options)
    if busy_spikes:
        # A written block's programming takes longer inside each spike's window.
        spikes = [tuple(map(float, spike)) for spike in busy_spikes]
        base = model.card.busy_s

        def busy_s():
            now = model.now_s
            return base() + sum(extra for start, end, extra in spikes if start <= now < end)
        model.card.busy_s = busy_s
    model.play(scenario)
    start = time.perf_counter()
    run = model.run(lambda bus: firmware(bus, model.memory_map, scenario.clk_freq),
                    until=scenario.until)
    result = SystemResult(image=image, led=run.leds[-1][1], seconds=run.end,
                          wall_seconds=time.perf_counter() - start)
    names = (CHANNEL_NAMES if len(scenario.channels) == len(CHANNEL_NAMES)
             else [f"ch{k}" for k in range(len(scenario.channels))])
    result.counters = {name: dict(counters) for name, counters in zip(names, run.counters)}
    return result
