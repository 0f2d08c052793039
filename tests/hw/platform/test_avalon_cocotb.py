"""The Avalon logger's generated Verilog (module maglog_logger_avalon) under cocotb on
Icarus: a second, independent Avalon-MM master (written for cocotb, on the Verilog ports)
runs the same kinds of transfers as test_avalon.py's and the results are checked here
against the register map.

This file is both the pytest side (building, stimulus, checks) and the cocotb test module
the simulator imports (:func:`avalon_master`, found through ``sys.path``).
"""

import json
import os
import random
from pathlib import Path

import pytest

pytestmark = pytest.mark.cocotb

TEST_MODULE = Path(__file__).stem
ALL_BYTES = 0b1111
CLOCK_NS = 20


try:
    import cocotb
except ImportError:      # pragma: no cover - the pytest side skips below
    cocotb = None


if cocotb is not None:
    @cocotb.test()
    async def avalon_master(dut):
        """Run the stimulus's transfers ``[write, address, data, byteenable, idle_before]``
        in order; record each read's data and the cycles each command waited."""
        from cocotb.clock import Clock
        from cocotb.triggers import FallingEdge, Timer

        with open(os.environ["MAGLOG_STIMULUS"]) as f:
            stimulus = json.load(f)
        Clock(dut.clk, CLOCK_NS, unit="ns").start()
        for name in ("avs_read", "avs_write", "avs_address", "avs_writedata",
                     "avs_byteenable", "button"):
            getattr(dut, name).value = 0
        dut.uart_rx.value = (1 << len(dut.uart_rx)) - 1
        dut.reset.value = 1
        for _ in range(3):
            await FallingEdge(dut.clk)
        dut.reset.value = 0

        reads, waits, pending = [], [], []
        violations = []
        accepted_cycle = {}
        cycle = 0

        async def step():
            """One clock: inputs are set before this falling edge's settle; outputs are
            read just after it (they hold until the next rising edge)."""
            nonlocal cycle
            await Timer(1, unit="ns")
            sample = (int(dut.avs_waitrequest.value), int(dut.avs_readdatavalid.value),
                      int(dut.avs_readdata.value))
            await FallingEdge(dut.clk)
            cycle += 1
            return sample

        def take(valid, data):
            if valid:
                if not pending:
                    violations.append(f"readdatavalid with no read pending at {cycle}")
                    return
                index = pending.pop(0)
                if accepted_cycle[index] == cycle:
                    violations.append(f"read {index}: data in its accepting cycle")
                reads.append([index, data])

        for index, (write, address, data, byteenable, idle) in enumerate(
                stimulus["transfers"]):
            dut.avs_read.value = 0
            dut.avs_write.value = 0
            for _ in range(idle):
                _, valid, rdata = await step()
                take(valid, rdata)
            dut.avs_address.value = address
            dut.avs_writedata.value = data
            dut.avs_byteenable.value = byteenable
            dut.avs_read.value = int(not write)
            dut.avs_write.value = int(write)
            waited = 0
            while True:
                waitrequest, valid, rdata = await step()
                take(valid, rdata)
                if not waitrequest:
                    accepted_cycle[index] = cycle - 1
                    if not write:
                        pending.append(index)
                        if len(pending) > stimulus["max_pending"]:
                            violations.append(f"{len(pending)} reads in flight")
                    break
                waited += 1
                if waited > 64:
                    violations.append(f"transfer {index}: waitrequest held 64 cycles")
                    break
            waits.append(waited)
        dut.avs_read.value = 0
        dut.avs_write.value = 0
        for _ in range(8):
            _, valid, rdata = await step()
            take(valid, rdata)
        with open(os.environ["MAGLOG_RESULT"], "w") as f:
            json.dump({"reads": reads, "waits": waits, "violations": violations,
                       "mismatches": violations}, f)


# --- the pytest side ---------------------------------------------------------------------

@pytest.fixture(scope="module")
def build(external, tmp_path_factory):
    from maglog.hw.platform.avalon import TOPLEVEL_NAME, AvalonLogger, generate_verilog
    from maglog.sim.backends.cocotb import CocotbBuild
    external.simulator("icarus")
    dut = AvalonLogger()
    build = CocotbBuild("icarus", tmp_path_factory.mktemp("avalon_icarus"), TOPLEVEL_NAME)
    build.build(generate_verilog(dut))
    return build, dut


def _mask(reg):
    return sum(f.mask for f in reg.fields.values())


def test_transfers_on_the_generated_verilog(build, monkeypatch):
    from maglog.hw.platform.avalon import AVS_TIMING
    from maglog.hw.top import LOGGER_ID
    from maglog.sw.regmap import RegisterMap

    build, dut = build
    regs = RegisterMap(dut.csr_memory_map)
    ident, fw = regs["logger_id"], regs["logger_fw_status"]
    # Another read-write register that keeps what is written: the front end's first.
    other = next(r for r in regs if r.access == "rw" and r.name.startswith("frontend_"))
    rng = random.Random(6)
    transfers, expected = [], []     # transfers: [write, address, data, byteenable, idle]

    def write(reg, value, be=ALL_BYTES, idle=0):
        transfers.append([1, reg.address, value, be, idle])

    def read(reg, value, be=ALL_BYTES, idle=0):
        expected.append((len(transfers), value))
        transfers.append([0, reg.address, 0, be, idle])

    read(ident, ident.encode(magic=LOGGER_ID))
    for reg in (fw, other):
        value = 0xC3A5_5A3C & _mask(reg)
        write(reg, value)
        read(reg, value)
        for be in (0b0001, 0b0010, 0b0100, 0b1000, 0b0011, 0b1100, 0b0111, 0b0000):
            write(reg, ~value & 0xFFFF_FFFF, be)
            read(reg, value, be=be)                        # reads ignore byteenable
    # Back to back, then with idle cycles.
    for k in range(6):
        value = rng.getrandbits(32) & _mask(other)
        idle = 0 if k < 3 else rng.randrange(1, 4)
        write(other, value, idle=idle)
        read(other, value, idle=idle)
        read(ident, ident.encode(magic=LOGGER_ID))

    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    result = build.run(TEST_MODULE, {
        "transfers": transfers,
        "max_pending": AVS_TIMING["maximumPendingReadTransactions"]})
    assert result["violations"] == []
    assert [(index, data) for index, data in result["reads"]] == expected
    # A read straight after a write is held under waitrequest (the write's access runs).
    after_write = [result["waits"][k] for k in range(1, len(transfers))
                   if transfers[k - 1][0] == 1 and transfers[k][0] == 0
                   and transfers[k][4] == 0]
    assert after_write and min(after_write) > 0
