"""What the gateware's own receiver (hw.uart.UartRx on the Amaranth simulator) makes of a
line, for the tests that judge a model or a prediction of it."""

from maglog.hw.uart import UartRx
from maglog.sim.backends.amaranth import collect_payloads, drive_line, run_simulation


def uartrx_receives(segments, divisor, *, name, deadline):
    """``[(error, byte or None)]`` for each character UartRx reports on a line given as
    ``[(level, cycles)]`` segments: ``error`` for a framing error, break or overrun, the
    byte None where the frame or break leaves no value."""
    dut = UartRx(divisor_init=divisor)
    got = []

    async def line(ctx):
        await drive_line(ctx, dut.rx, segments)

    async def sink(ctx):
        await collect_payloads(ctx, dut.o, got)

    run_simulation(dut, [line], background=[sink], name=name, deadline=deadline)
    return [(bool(p.framing_error or p.brk or p.overrun),
             None if p.framing_error or p.brk else p.data) for p in got]
