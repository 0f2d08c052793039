"""The Avalon-MM logger in the Amaranth simulator, driven by an Avalon-MM master model.

The master honours ``waitrequest`` (holds its command until it is low), takes read data on
``readdatavalid`` in order, drives ``byteenable``, and keeps count of what it saw: cycles
waited per command, reads in flight, data arriving in the cycle a read was accepted. Those
observations are checked against the timing the component's ``_hw.tcl`` declares.
"""

import random
import re
from collections import deque
from dataclasses import dataclass, field

import pytest
from amaranth.hdl import Shape

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.hw.platform.avalon import (AVS_TIMING, AvalonLogger, avalon_slave_signature,
                                       verilog_ports)
from maglog.hw.platform.component import hw_tcl
from maglog.hw.top import LOGGER_ID
from maglog.sim.backends.amaranth import run_simulation
from maglog.sw.regmap import RegisterMap

CLK_FREQ = 1e6
CHANNELS = [ChannelConfig(ChannelKind.PMAG, 62500), ChannelConfig(ChannelKind.NMEA, 62500),
            ChannelConfig(ChannelKind.CESIUM, 62500)]
ALL_BYTES = 0b1111


def make_logger():
    return AvalonLogger(CHANNELS, clk_freq=CLK_FREQ, max_frame=100, fifo_depth=128,
                        ring_capacity=4096, debounce_s=0.001)


@dataclass
class Transfer:
    """One Avalon command and what became of it."""
    write: bool
    address: int
    data: int = 0
    byteenable: int = ALL_BYTES
    waited: int = 0              # cycles the command was held under waitrequest
    result: int = None           # read data
    accepted_at: int = None
    data_at: int = None


@dataclass
class Observed:
    max_pending: int = 0
    data_in_accept_cycle: int = 0
    unexpected_data: int = 0
    cycles: int = 0
    transfers: list = field(default_factory=list)


class AvalonMaster:
    """Runs transfers on ``avs`` back to back (or with seeded idle cycles between them)."""
    def __init__(self, ctx, avs, *, idle=0.0, seed=0):
        self._ctx, self._avs = ctx, avs
        self._idle, self._rng = idle, random.Random(seed)
        self.observed = Observed()

    def _present(self, t):
        ctx, avs = self._ctx, self._avs
        ctx.set(avs.address, t.address if t else self._rng.randrange(1 << len(avs.address)))
        ctx.set(avs.writedata, t.data if t else self._rng.getrandbits(32))
        ctx.set(avs.byteenable, t.byteenable if t else self._rng.randrange(16))
        ctx.set(avs.read, t is not None and not t.write)
        ctx.set(avs.write, t is not None and t.write)

    async def run(self, transfers):
        obs = self.observed
        queue, pending, current = deque(transfers), deque(), None
        while queue or pending or current is not None:
            if current is None and queue and self._rng.random() >= self._idle:
                current = queue.popleft()
            self._present(current)
            _, _, waitrequest, valid, data = await self._ctx.tick().sample(
                self._avs.waitrequest, self._avs.readdatavalid, self._avs.readdata)
            cycle = obs.cycles
            obs.cycles += 1
            if pending and cycle - pending[0].accepted_at > 64:
                raise AssertionError(f"no readdatavalid for {pending[0]} in 64 cycles "
                                     f"({obs.unexpected_data} with no read pending)")
            if valid:
                if not pending:
                    obs.unexpected_data += 1
                else:
                    done = pending.popleft()
                    done.result, done.data_at = data, cycle
                    if done.accepted_at == cycle:
                        obs.data_in_accept_cycle += 1
            if current is None:
                continue
            if waitrequest:
                current.waited += 1
                if current.waited > 64:
                    raise AssertionError(f"waitrequest held for 64 cycles on {current}")
                continue
            current.accepted_at = cycle
            obs.transfers.append(current)
            if not current.write:
                pending.append(current)
                obs.max_pending = max(obs.max_pending, len(pending))
            current = None
        self._present(None)
        self._ctx.set(self._avs.read, 0)
        self._ctx.set(self._avs.write, 0)
        return transfers


def run(dut, transfers_or_script, *, idle=0.0, seed=0):
    """Run the transfers (a list) or ``script(master)`` (an async function) on ``dut``;
    return the master's observations."""
    out = {}

    async def bench(ctx):
        master = AvalonMaster(ctx, dut.avs, idle=idle, seed=seed)
        if callable(transfers_or_script):
            await transfers_or_script(master)
        else:
            await master.run(transfers_or_script)
        out["observed"] = master.observed

    run_simulation(dut, [bench], name="avalon_logger", clock_period=1 / CLK_FREQ,
                   deadline=0.01)
    return out["observed"]


def read(address):
    return Transfer(False, address)


def write(address, data, byteenable=ALL_BYTES):
    return Transfer(True, address, data, byteenable)


@pytest.fixture(scope="module")
def regs():
    return RegisterMap(make_logger().csr_memory_map)


def test_signature_members_and_widths():
    sig = avalon_slave_signature(7)
    widths = {name: Shape.cast(m.shape).width for name, m in sig.members.items()}
    assert widths == {"address": 7, "read": 1, "write": 1, "writedata": 32, "byteenable": 4,
                      "readdata": 32, "waitrequest": 1, "readdatavalid": 1}
    with pytest.raises(ValueError, match="Address width must be a positive integer, not 0"):
        avalon_slave_signature(0)


def test_the_logger_keeps_its_pins_and_gets_avs():
    dut = make_logger()
    members = dut.signature.members
    assert set(members) == {"uart_rx", "sd", "sdram", "led", "button", "avs"}
    for name in ("uart_rx", "sd", "sdram", "led", "button"):
        assert members[name] == dut.logger.signature.members[name], name
    assert len(dut.avs.address) == len(dut.logger.bus.adr)


def test_reads_the_id_register(regs):
    dut = make_logger()
    reg = regs["logger_id"]
    obs = run(dut, [read(reg.address)])
    (t,) = obs.transfers
    assert reg.decode(t.result)["magic"] == LOGGER_ID
    # docs/platform-designer.md's timing: two cycles under waitrequest, the word one
    # cycle after acceptance.
    assert t.waited == 2 and t.data_at == t.accepted_at + 1


def _mask(reg):
    return sum(f.mask for f in reg.fields.values())


def _second_register(regs):
    """Another read-write register that keeps what is written (no counter): the front
    end's first one (a baud divisor); logger_fw_status spans all four byte lanes."""
    return next(r for r in regs if r.access == "rw" and r.name.startswith("frontend_"))


PARTIALS = [0b0000, 0b0001, 0b0010, 0b0100, 0b1000, 0b0011, 0b1100, 0b0110, 0b0111, 0b1110,
            0b1011, 0b1101]


@pytest.mark.parametrize("which", ["fw_status", "frontend"])
def test_full_and_partial_writes(regs, which):
    """A whole-word write lands; a write with any other byteenable changes no byte."""
    dut = make_logger()
    reg = regs["logger_fw_status"] if which == "fw_status" else _second_register(regs)
    mask = _mask(reg)
    first, second = 0x9E37_79B9 & mask, 0x7F4A_7C15 & mask
    transfers = [write(reg.address, first), read(reg.address)]
    for be in PARTIALS:
        transfers += [write(reg.address, ~first & 0xFFFF_FFFF, be), read(reg.address)]
    transfers += [write(reg.address, second | ~mask & 0xFFFF_FFFF), read(reg.address)]
    obs = run(dut, transfers)
    results = [t.result for t in obs.transfers if not t.write]
    assert results[0] == first
    assert results[1:-1] == [first] * len(PARTIALS)
    assert results[-1] == second      # bits outside the fields read as zero


def test_reads_ignore_byteenable(regs):
    dut = make_logger()
    reg = regs["logger_fw_status"]
    value = reg.encode(state=0x6, error=0x81, file=99999)
    transfers = [write(reg.address, value)]
    for be in (0b0001, 0b1000, 0b0000, 0b1111):
        t = read(reg.address)
        t.byteenable = be
        transfers.append(t)
    obs = run(dut, transfers)
    assert [t.result for t in obs.transfers[1:]] == [value] * 4


def test_back_to_back_transfers_and_a_read_under_waitrequest(regs):
    """Commands follow each other with no idle cycle: a read presented right after a write
    is held under waitrequest and still returns the right word, in order."""
    dut = make_logger()
    fw, ident, control = regs["logger_fw_status"], regs["logger_id"], regs["logger_control"]
    values = [fw.encode(state=k, error=17 * k, file=1000 * k + 7) for k in range(1, 6)]
    transfers = []
    for value in values:
        transfers += [write(fw.address, value), read(fw.address), read(ident.address)]
    transfers += [write(control.address, control.encode(record=1)), read(control.address)]
    obs = run(dut, transfers)
    reads = [t for t in obs.transfers if not t.write]
    expected = []
    for value in values:
        expected += [value, ident.encode(magic=LOGGER_ID)]
    expected.append(control.encode(record=1))
    assert [t.result for t in reads] == expected
    after_write = [t for prev, t in zip(obs.transfers, obs.transfers[1:])
                   if prev.write and not t.write]
    assert after_write and all(t.waited > 0 for t in after_write)
    # Back to back: each command is presented the cycle after the previous was accepted.
    for prev, t in zip(obs.transfers, obs.transfers[1:]):
        assert t.accepted_at == prev.accepted_at + 1 + t.waited
    assert obs.unexpected_data == 0


def test_random_traffic_with_idle_cycles(regs):
    """Seeded random reads and writes (some partial) with idle cycles, against a model of
    the three RW words: the control, fw_status and a channel divisor."""
    dut = make_logger()
    names = ["logger_control", "logger_fw_status", _second_register(regs).name]
    model = {}
    rng = random.Random(14)
    transfers, expected = [], []
    mask = {n: _mask(regs[n]) for n in names}
    for _ in range(40):
        name = rng.choice(names)
        reg = regs[name]
        if rng.random() < 0.5:
            be = ALL_BYTES if rng.random() < 0.7 else rng.randrange(15)
            value = rng.getrandbits(32)
            transfers.append(write(reg.address, value, be))
            if be == ALL_BYTES:
                model[name] = value & mask[name]
        elif name in model:
            transfers.append(read(reg.address))
            expected.append(model[name])
    obs = run(dut, transfers, idle=0.3, seed=5)
    assert [t.result for t in obs.transfers if not t.write] == expected


def _tcl_properties(text, interface):
    return dict(re.findall(rf"^set_interface_property {interface} (\w+) (\S+)$", text, re.M))


def test_observed_timing_matches_the_hw_tcl(regs):
    """What the master saw agrees with the _hw.tcl: reads are pipelined with variable
    latency (readdatavalid, never in the accepting cycle when readLatency is 0), no more in
    flight than maximumPendingReadTransactions, waitrequest used."""
    dut = make_logger()
    props = _tcl_properties(hw_tcl(dut), "avs")
    assert props["addressUnits"] == "WORDS"
    roles = set(re.findall(r"^add_interface_port avs \w+ (\w+) ", hw_tcl(dut), re.M))
    assert {"waitrequest", "readdatavalid"} <= roles
    ident = regs["logger_id"]
    obs = run(dut, [read(ident.address) for _ in range(6)], idle=0.2, seed=1)
    assert obs.max_pending <= int(props["maximumPendingReadTransactions"])
    assert int(props["readLatency"]) == 0 and obs.data_in_accept_cycle == 0
    assert all(t.data_at > t.accepted_at for t in obs.transfers)
    assert int(props["readWaitTime"]) == AVS_TIMING["readWaitTime"]


def test_verilog_ports_cover_the_signature():
    dut = make_logger()
    names = [p.name for p in verilog_ports(dut)]
    assert len(names) == len(set(names))
    assert names[:2] == ["clk", "reset"]
    avs = [p for p in verilog_ports(dut) if p.interface == "avs"]
    assert {p.role: p.direction for p in avs} == {
        "address": "input", "read": "input", "write": "input", "writedata": "input",
        "byteenable": "input", "readdata": "output", "waitrequest": "output",
        "readdatavalid": "output"}
