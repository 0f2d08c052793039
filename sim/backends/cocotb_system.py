"""The whole logger under cocotb (Icarus or Verilator): the generated Verilog of the gateware
top (``maglog_logger``) with the SDRAM chip model and the SD card model on its pins, the
scenario's serial lines and button on its inputs, and the firmware on its Wishbone port.

This mirrors :mod:`maglog.sim.backends.amaranth`: the same scenario, the same firmware
(:class:`maglog.sw.app.LoggerApp`) and the same models; only the register bus
(:class:`WishboneBus`) and the simulator differ. :func:`run_system_cocotb` runs in the
caller's process and prepares a JSON stimulus and the card image; the cocotb test
:func:`system` runs in the simulator's process and leaves the card image and a JSON result.

Timing: the clock is the simulator's own (``impl="gpi"``). The reset ends at a falling edge;
that instant is cycle 0 of the scenario
(:meth:`~maglog.sim.stimulus.system.SystemScenario.pin_changes`) and of the firmware's clock
(``now()``). Every pin the test drives changes half a clock
away from a rising edge. Python runs per SDRAM command (and the chip model, which checks
every timing rule, once a clock: see :class:`SkippingChip`), per SD clock edge, per
register access and per pin change.
"""

import dataclasses
import hashlib
import json
import os
import re
import tempfile
import time
import traceback
from pathlib import Path

import cocotb
from cocotb.simtime import get_sim_time

from ...hw.arch.sdram import MT48LC4M32B2
from ...sw.bus import RegisterBus
from ..runners.result import SystemResult
from ..stimulus.system import SystemScenario


__all__ = ["BACKENDS", "WishboneBus", "settings_to_json", "settings_from_json",
           "run_system_cocotb"]

BACKENDS = ("icarus", "verilator")
#: The cocotb test module (this one) and the firmware the runner uses unless told otherwise.
TEST_MODULE = __name__
APP_FIRMWARE = "app"
CARD_CHECK_FIRMWARE = "card_check"
FIRMWARES = (APP_FIRMWARE, CARD_CHECK_FIRMWARE)


class WishboneBus(RegisterBus):
    """The firmware's register bus on the top's ``wb_*`` ports (Wishbone classic, 32-bit,
    word addresses): ``cyc`` and ``stb`` held until ``ack``, as
    :class:`maglog.sim.backends.amaranth.WishboneBus` does. Every access starts and ends at a
    falling edge of ``clk``; ``now()`` counts the clocks the firmware has spent, and time
    converts to clocks at the nominal ``clk_freq`` (as on the Amaranth simulator; the
    simulated period is ``clock_period_ps``, whole picoseconds)."""

    #: An access that is not acknowledged within this many cycles is a gateware fault.
    ACK_LIMIT = 64

    def __init__(self, dut, *, clk_freq, clock_period_ps):
        from cocotb.triggers import FallingEdge, ReadOnly, RisingEdge
        self._dut = dut
        self._clk_freq = clk_freq
        self._period_ps = clock_period_ps
        self._cycles = 0
        self._sel = (1 << len(dut.wb_sel)) - 1
        self._rising, self._falling = RisingEdge(dut.clk), FallingEdge(dut.clk)
        self._read_only = ReadOnly()

    async def _cycle(self, address, write, value=0):
        dut = self._dut
        dut.wb_adr.value = address
        dut.wb_we.value = int(write)
        dut.wb_dat_w.value = value
        dut.wb_sel.value = self._sel
        dut.wb_cyc.value = 1
        dut.wb_stb.value = 1
        for _ in range(self.ACK_LIMIT):
            await self._rising
            self._cycles += 1
            await self._read_only
            if dut.wb_ack.value:
                break
        else:
            raise TimeoutError(f"Wishbone {'write' if write else 'read'} at {address:#x} not "
                               f"acknowledged within {self.ACK_LIMIT} cycles")
        data = int(dut.wb_dat_r.value)
        await self._falling
        dut.wb_cyc.value = 0
        dut.wb_stb.value = 0
        dut.wb_we.value = 0
        return data

    async def read(self, address):
        return await self._cycle(address, False)

    async def write(self, address, value):
        await self._cycle(address, True, value)
        # A CSR field takes the value one cycle after the strobe the bridge gives with its
        # acknowledgement: what the firmware does next sees the write's effect.
        await self._rising
        await self._falling
        self._cycles += 1

    async def wait(self, seconds):
        from cocotb.triggers import Timer
        cycles = max(1, round(seconds * self._clk_freq))
        if cycles > 1:
            # From a falling edge to the falling edge a cycle before the last.
            await Timer((cycles - 1) * self._period_ps, unit="ps")
        await self._rising
        await self._falling
        self._cycles += cycles

    def now(self):
        return self._cycles / self._clk_freq


def clock_period_ps(clk_freq):
    """The simulated clock's period: whole picoseconds, and even, so that both halves are
    whole too (a cycle count converts to simulated time exactly)."""
    return 2 * round(0.5e12 / clk_freq)


#: The module the cocotb runs simulate: the logger and two observation outputs.
TOPLEVEL = "maglog_system"
#: Rising edges of ``clk`` with ``rst`` high at the start of a run (the power-on reset).
RESET_CYCLES = 4
#: The SDRAM pins packed into the one output ``sim_sdram`` (first = least significant).
SDRAM_PACKED = ("cke", "cs_n", "ras_n", "cas_n", "we_n", "dq_oe", "ba", "a", "dqm", "dq_o")
#: The SD host's outputs packed into ``sim_sd`` (first = least significant).
SD_PACKED = ("cmd_oe", "cmd_o", "dat_oe", "dat_o")

_PORT = re.compile(r"^\s*(input|output)\s+(?:\[(\d+):0\]\s+)?(\w+)\s*;", re.MULTILINE)


def system_verilog(logger_verilog):
    """The logger's Verilog (module ``maglog_logger``) and a wrapper module ``maglog_system``
    for the test: the logger's ports but ``rst``, which a power-on reset holds high for the
    first :data:`RESET_CYCLES` clocks, and three outputs more: ``sim_sdram`` and ``sim_sd``,
    the SDRAM pins of :data:`SDRAM_PACKED` and the SD host's outputs of :data:`SD_PACKED`
    each in one vector (one read an edge instead of ten or four), and ``sim_sdram_command``,
    high unless the SDRAM bus holds a NOP (one signal to wake on).

    Why the reset is inside: every next-state expression of Amaranth's Verilog depends on
    ``rst``; were it a top-level input, Verilator would evaluate all of them again whenever
    the test writes any input (the clock's edges too): five times slower. Only the wrapper's
    ports are public to VPI (``/*verilator public_flat_rw*/``, with
    :data:`VERILATOR_SPEED_ARGS`): the test touches nothing else."""
    from ...hw.top import TOPLEVEL_NAME
    start = logger_verilog.index(f"module {TOPLEVEL_NAME}(")
    body = logger_verilog[start:logger_verilog.index("endmodule", start)]
    ports = [(flow, 1 + int(high) if high else 1, name)
             for flow, high, name in _PORT.findall(body)]
    width = {name: bits for _, bits, name in ports}
    packs = {"sim_sdram": [f"sdram_{pin}" for pin in SDRAM_PACKED],
             "sim_sd": [f"sd_{pin}" for pin in SD_PACKED]}
    missing = [name for name in ("clk", "rst", *packs["sim_sdram"], *packs["sim_sd"])
               if name not in width]
    if missing:
        raise ValueError(f"module {TOPLEVEL_NAME} has no port {', '.join(missing)}")
    logger_ports = [name for _, _, name in ports]
    ports += [("output", sum(width[name] for name in pins), pack)
              for pack, pins in packs.items()]
    ports.append(("output", 1, "sim_sdram_command"))

    def declaration(flow, bits, name):
        vector = f"[{bits - 1}:0] " if bits > 1 else ""
        return f"  {flow} {vector}{name} /*verilator public_flat_rw*/;"


    outer = [port for port in ports if port[2] != "rst"]
    bits = max(2, RESET_CYCLES.bit_length())
    lines = [f"module {TOPLEVEL}({', '.join(name for _, _, name in outer)});"]
    lines += [declaration(*port) for port in outer]
    lines += [f"  reg [{bits - 1}:0] por_count = {bits}'d0;",
              f"  wire rst = por_count != {bits}'d{RESET_CYCLES};",
              "  always @(posedge clk) if (rst) por_count <= por_count + 1'b1;",
              *(f"  assign {pack} = {{{', '.join(reversed(pins))}}};"
                for pack, pins in packs.items()),
              "  assign sim_sdram_command = !(sdram_cke && !sdram_dq_oe && (sdram_cs_n"
              " || sdram_ras_n && sdram_cas_n && sdram_we_n));",
              f"  {TOPLEVEL_NAME} logger (",
              ",\n".join(f"    .{name}({name})" for name in logger_ports),
              "  );",
              "endmodule"]
    return logger_verilog + "\n" + "\n".join(lines) + "\n"


# -- AppSettings across the process boundary ---------------------------------------------------

_PLAIN = (bool, int, float, str)


def settings_to_json(settings):
    """The plain fields of an :class:`~maglog.sw.app.AppSettings` (numbers, flags) as a
    dict. Any other field (the ``fault`` hook, the LED patterns) is left out when it has its
    default value, which the other side rebuilds, and refused otherwise."""
    from ...sw.app import AppSettings
    if not isinstance(settings, AppSettings):
        raise TypeError(f"Settings must be an AppSettings, not {settings!r}")
    default = AppSettings()
    plain = {}
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        if isinstance(value, _PLAIN):
            plain[f.name] = value
        elif value != getattr(default, f.name):
            raise ValueError(f"AppSettings.{f.name} cannot be passed to a cocotb run (only "
                             f"plain numbers and flags can), not {value!r}")
    return plain


def settings_from_json(plain):
    from ...sw.app import AppSettings
    return AppSettings(**plain)


# -- the run from the caller's side -------------------------------------------------------------

#: Builds made in this process, by (backend, build folder).
_BUILDS = {}

#: Verilator options beyond the waivers: cocotb's runner makes every signal public
#: (``--public-flat-rw``), which keeps Verilator from ordering any logic by its inputs and
#: made a clock of this design about 2.7 times slower; :func:`system_verilog` marks the
#: ports of the top public instead, the only signals the test touches.
VERILATOR_SPEED_ARGS = ("--no-public-flat-rw",)


class _SystemBuild:
    """A :class:`~maglog.sim.backends.cocotb.CocotbBuild` of the system top, with
    :data:`VERILATOR_SPEED_ARGS` added to the Verilator build."""

    def __init__(self, backend, folder):
        from .cocotb import CocotbBuild
        self.cocotb = CocotbBuild(backend, folder, TOPLEVEL)

    @property
    def build_dir(self):
        return self.cocotb.build_dir

    def build(self, verilog_text):
        extra = VERILATOR_SPEED_ARGS if self.cocotb.backend == "verilator" else ()
        self.cocotb.build(verilog_text, extra_args=extra)

    def run(self, test_module, stimulus, *, waves=False):
        return self.cocotb.run(test_module, stimulus, waves=waves)


def _build(backend, build_dir, logger_verilog):
    text = system_verilog(logger_verilog)
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    folder = Path(build_dir).resolve() / f"{backend}-{digest}"
    key = (backend, str(folder))
    build = _BUILDS.get(key)
    if build is None:
        build = _SystemBuild(backend, folder)
        build.build(text)
        _BUILDS[key] = build
    return build


def _load_into(image, path):
    """Make ``image`` hold what the raw image at ``path`` holds (in place)."""
    from ..models.card_image import CardImage
    back = CardImage.load(path)
    if back.capacity_blocks != image.capacity_blocks:
        raise RuntimeError(f"the card image came back with {back.capacity_blocks} blocks, "
                           f"not {image.capacity_blocks}")
    after = dict(back.blocks())
    zero = bytes(512)
    for lba, data in list(image.blocks()):
        if lba not in after:
            image.write_block(lba, zero)
        elif after[lba] == data:
            del after[lba]
    for lba, data in after.items():
        image.write_block(lba, data)
    return image


def run_system_cocotb(scenario, image, *, backend, build_dir, settings=None,
                      firmware=APP_FIRMWARE, chip=MT48LC4M32B2, card_seed=0, ring_capacity=None,
                      sdram_every_clock=False, waves=False):
    """Run ``scenario`` on the logger's Verilog under cocotb (``backend``: ``icarus`` or
    ``verilator``) until ``scenario.until``, the firmware being
    :class:`~maglog.sw.app.LoggerApp` with ``settings`` (an AppSettings; its plain fields
    cross to the simulator's process). The SD card model holds ``image`` (a
    :class:`~maglog.sim.models.card_image.CardImage`, changed in place, as on the other
    backends). The Verilog is built once per backend, build folder and design.

    ``firmware="card_check"`` runs a short check instead of the application (the logger's
    identification, card initialisation, one block written and read back through the DMA's
    sector buffer; the block is LBA 1, which the image must be able to lose).
    ``sdram_every_clock`` runs the SDRAM model with a simulator callback every clock
    (:func:`maglog.sim.backends.cocotb_sdram.run_chip`) instead of :class:`SkippingChip`. Returns a
    :class:`~maglog.sim.runners.result.SystemResult`; a firmware that stops with an exception, or
    a check that fails, raises RuntimeError with the firmware's message."""
    from ...hw.top import Logger, generate_verilog
    if backend not in BACKENDS:
        raise ValueError(f"cocotb system backend must be one of {', '.join(BACKENDS)}, "
                         f"not {backend!r}")
    if firmware not in FIRMWARES:
        raise ValueError(f"Firmware must be one of {', '.join(FIRMWARES)}, not {firmware!r}")
    if not isinstance(scenario, SystemScenario):
        raise TypeError(f"Scenario must be a SystemScenario, not {scenario!r}")
    chip_name = next((name for name, preset in _chips().items() if preset == chip), None)
    if chip_name is None:
        raise ValueError(f"Chip must be one of the presets of hw.arch.sdram, not {chip!r}")
    if settings is None:
        from ...sw.app import AppSettings
        settings = AppSettings()
    plain_settings = settings_to_json(settings)
    logger = Logger(channels=scenario.channels, clk_freq=scenario.clk_freq,
                    debounce_s=scenario.debounce_s, max_frame=scenario.max_frame,
                    ring_capacity=ring_capacity, chip=chip)
    build = _build(backend, build_dir, generate_verilog(logger))
    cards = Path(tempfile.mkdtemp(prefix="card-", dir=build.build_dir))
    card_in, card_out = cards / "in.img", cards / "out.img"
    image.save(card_in)
    start = time.perf_counter()
    raw = build.run(TEST_MODULE, {
        "scenario": scenario.to_json(), "settings": plain_settings, "firmware": firmware,
        "chip": chip_name, "ring_capacity": ring_capacity, "card_seed": card_seed,
        "card_in": str(card_in), "card_out": str(card_out),
        "sdram_every_clock": bool(sdram_every_clock),
    }, waves=waves)
    wall = time.perf_counter() - start
    card_in.unlink()
    if raw["firmware_error"]:
        raise RuntimeError(f"the firmware stopped on {backend}: {raw['firmware_error']}")
    if firmware == CARD_CHECK_FIRMWARE and raw["firmware_returned"] is None:
        raise RuntimeError(f"the card check did not end within {scenario.until} s on "
                           f"{backend}")
    _load_into(image, card_out)
    card_out.unlink()
    cards.rmdir()
    return SystemResult(image=image, led=raw["led"], seconds=raw["cycles"] / scenario.clk_freq,
                        wall_seconds=wall, sdram_errors=raw["sdram_errors"],
                        card_errors=raw["card_errors"])


def _chips():
    from ...hw.arch import sdram as arch_sdram
    return arch_sdram.CHIPS


# -- the run in the simulator's process ----------------------------------------------------------

def _unpacker(dut):
    """A function from the value of ``sim_sdram`` to the SDRAM model's keyword arguments."""
    fields, offset = [], 0
    for pin in SDRAM_PACKED:
        bits = len(getattr(dut, f"sdram_{pin}"))
        fields.append((pin if pin != "dq_o" else "dq", offset, (1 << bits) - 1))
        offset += bits

    def unpack(word):
        return {name: word >> shift & mask for name, shift, mask in fields}
    return unpack


class SkippingChip:
    """The SDRAM chip model on the top's ``sdram_*`` pins, as
    :func:`maglog.sim.backends.cocotb_sdram.run_chip` runs it (the model sees the levels every
    rising edge samples, and what it returns is on ``dq_i`` for the next edge), but without a
    simulator callback per clock while the bus is quiet.

    Quiet: the controller holds a NOP (no command, DQ not driven: ``sim_sdram_command`` low)
    and no data is under way (the last READ's data and the last WRITE's burst are over, by
    the mode register's CAS latency and burst length). :meth:`run` then sleeps until
    ``sim_sdram_command`` rises and gives the model one NOP edge for every rising edge that
    passed meanwhile, in plain Python: the model sees every edge, and every command at the
    edge that samples it, as it would per cycle. ``edge_ps``: the time of any rising edge of
    ``clk``; ``period_ps`` its period."""

    def __init__(self, dut, model, *, period_ps, edge_ps):
        self.dut, self.model = dut, model
        self.period_ps, self.edge_ps = period_ps, edge_ps
        self._unpack = _unpacker(dut)
        self._asleep = None             # (edges before the sleep, the NOP's levels)

    def edges_until(self, ps):
        """Rising edges of ``clk`` at or before ``ps`` (counted from ``edge_ps``)."""
        return (ps - self.edge_ps) // self.period_ps

    def catch_up(self):
        """Give the model the NOP edges of a sleep up to now (at the end of a run)."""
        if self._asleep is not None:
            since, levels = self._asleep
            now = self.edges_until(round(get_sim_time(unit="ps")))
            for _ in range(now - since):
                if self.model.edge(**levels) is not None:
                    raise RuntimeError("the SDRAM model drove DQ while the bus was quiet")
            self._asleep = (now, levels)

    async def run(self):
        from cocotb.triggers import ReadOnly, RisingEdge
        dut, model = self.dut, self.model
        packed, dq_i, command = dut.sim_sdram, dut.sdram_dq_i, dut.sim_sdram_command
        rising, read_only, wake = RisingEdge(dut.clk), ReadOnly(), RisingEdge(command)
        busy_until = 0                  # the first edge with no data under way
        while True:
            await read_only
            levels = self._unpack(int(packed.value))
            if (not command.value and model.cycle >= busy_until
                    and not model.mode.get("full_page")):
                self._asleep = (self.edges_until(round(get_sim_time(unit="ps"))), levels)
                await wake
                self.catch_up()
                self._asleep = None
                continue
            if not levels["cs_n"] and levels["ras_n"] and not levels["cas_n"]:
                # READ or WRITE: its data moves for the burst, CAS latency clocks later for
                # a READ (the defaults are the largest the controller may set).
                busy_until = (model.cycle + 1 + model.mode.get("cas_latency", 3)
                              + (model.mode.get("burst_length") or 8))
            await rising
            out = model.edge(**levels)
            dq_i.value = 0 if out is None else out


class PackedSdPins:
    """The top's ``sd_*`` pins as :func:`maglog.sim.backends.cocotb_sdio.run_card` takes
    them (see :class:`~maglog.sim.backends.cocotb_sdio.SdPins`), the host's outputs read in
    one go from ``sim_sd`` (:data:`SD_PACKED`: cmd_oe, cmd_o, dat_oe, dat_o[3:0])."""
    def __init__(self, dut):
        self.clk = dut.sd_clk
        self._packed, self._cmd_i, self._dat_i = dut.sim_sd, dut.sd_cmd_i, dut.sd_dat_i

    def host(self):
        word = int(self._packed.value)
        return word & 1, word >> 1 & 1, word >> 2 & 1, word >> 3 & 0xF

    def drive(self, cmd, dat):
        self._cmd_i.value = cmd
        self._dat_i.value = dat


async def _drive_pins(dut, changes, period_ps):
    """The scenario's input pins, from cycle 0 (now, a falling edge) on."""
    from cocotb.triggers import Timer
    now = 0
    for cycle, uart_rx, button in changes:
        if cycle > now:
            await Timer((cycle - now) * period_ps, unit="ps")
            now = cycle
        dut.uart_rx.value = uart_rx
        dut.button.value = button


async def _card_check(bus, memory_map, sys_clock_hz):
    """A short firmware: the logger answers with its id, the card initialises, a block
    written through the DMA's sector buffer reads back the same."""
    import random
    from ...hw.top import LOGGER_ID
    from ...sw.regmap import RegisterMap
    from ...sw.storage import DmaStorage
    logger = RegisterMap(memory_map, window="logger")
    magic = logger["id"].decode(await bus.read(logger["id"].address))["magic"]
    if magic != LOGGER_ID:
        raise AssertionError(f"logger.id reads {magic:#x}, not {LOGGER_ID:#x}")
    storage = DmaStorage(bus, memory_map, sys_clock_hz=sys_clock_hz)
    await storage.driver.initialise()
    block = random.Random(1).randbytes(512)
    await storage.device.write_block(1, block)
    back = await storage.device.read_block(1)
    if back != block:
        raise AssertionError("block 1 reads back differently from what was written")


@cocotb.test()
async def system(dut):
    """The logger with its models and firmware until the scenario's end."""
    import logging

    from cocotb.clock import Clock
    from cocotb.triggers import FallingEdge, RisingEdge, Timer

    from ...hw.arch import sdram as arch_sdram
    from ...hw.top import Logger
    from ...sw.app import LoggerApp
    from .cocotb_sdio import run_card
    from .cocotb_sdram import run_chip
    from ..models.card_image import CardImage
    from ..models.sdcard import SdCard
    from ..models.sdram import SdramChip

    logging.getLogger("cocotb").setLevel(logging.WARNING)
    with open(os.environ["MAGLOG_STIMULUS"]) as f:
        stimulus = json.load(f)
    scenario = SystemScenario.from_json(stimulus["scenario"])
    clk_freq = scenario.clk_freq
    period_ps = clock_period_ps(clk_freq)
    chip = arch_sdram.CHIPS[stimulus["chip"]]
    logger = Logger(channels=scenario.channels, clk_freq=clk_freq,
                    debounce_s=scenario.debounce_s, max_frame=scenario.max_frame,
                    ring_capacity=stimulus["ring_capacity"], chip=chip)
    image = CardImage.load(stimulus["card_in"])
    card = SdCard(image, seed=stimulus["card_seed"])
    sdram = SdramChip(chip, clk_freq=clk_freq, strict=False)

    changes = scenario.pin_changes()
    _, uart_rx, button = changes[0]
    dut.uart_rx.value = uart_rx
    dut.button.value = button
    dut.sd_cmd_i.value = 1
    dut.sd_dat_i.value = 0xF
    dut.sdram_dq_i.value = 0
    for name in ("adr", "dat_w", "sel", "cyc", "stb", "we"):
        getattr(dut, f"wb_{name}").value = 0
    Clock(dut.clk, period_ps, unit="ps", impl="gpi").start()
    for _ in range(RESET_CYCLES + 1):           # the power-on reset, and one cycle out of it
        await RisingEdge(dut.clk)
    edge_ps = round(get_sim_time(unit="ps"))
    await FallingEdge(dut.clk)
    start_ps = round(get_sim_time(unit="ps"))

    chip_side = None
    if stimulus["sdram_every_clock"]:
        cocotb.start_soon(run_chip(dut, sdram, prefix="sdram_"))
    else:
        chip_side = SkippingChip(dut, sdram, period_ps=period_ps, edge_ps=edge_ps)
        cocotb.start_soon(chip_side.run())
    cocotb.start_soon(run_card(PackedSdPins(dut), card))
    cocotb.start_soon(_drive_pins(dut, changes, period_ps))

    bus = WishboneBus(dut, clk_freq=clk_freq, clock_period_ps=period_ps)
    failure = []
    if stimulus["firmware"] == APP_FIRMWARE:
        settings = settings_from_json(stimulus["settings"])

        async def firmware(bus, memory_map, sys_clock_hz):
            await LoggerApp(bus, memory_map, sys_clock_hz=sys_clock_hz,
                            settings=settings).run()
    else:
        firmware = _card_check

    returned = []

    async def software():
        try:
            await firmware(bus, logger.csr_memory_map, clk_freq)
            returned.append(bus.now())
        except Exception:
            failure.append(f"at {bus.now():.6f} s: {traceback.format_exc()}")
    cocotb.start_soon(software())

    await Timer(round(scenario.until * clk_freq) * period_ps, unit="ps")
    now_ps = round(get_sim_time(unit="ps"))
    cycles = round((now_ps - start_ps) / period_ps)
    if chip_side is not None:
        chip_side.catch_up()
    # The chip model must have seen every rising edge since it started (half a clock
    # before cycle 0).
    edges = (now_ps - edge_ps) // period_ps
    if sdram.cycle != edges:
        sdram.errors.append(f"the SDRAM model saw {sdram.cycle} clock edges, not {edges}")
    result = {"led": int(dut.led.value), "cycles": cycles,
              "sdram_errors": sdram.errors[:50], "card_errors": card.errors[:50],
              "firmware_error": failure[0] if failure else None,
              "firmware_returned": returned[0] if returned else None}
    image.save(stimulus["card_out"])
    with open(os.environ["MAGLOG_RESULT"], "w") as f:
        json.dump(result, f)

