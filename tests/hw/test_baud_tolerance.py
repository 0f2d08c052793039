"""The front end's baud check (hw/frontend.py's divisor_for): the limit on the receiver's own
rate error, what the receiver actually tolerates behind it, and the refusal's message."""

from __future__ import annotations

import math
import random

import pytest

from maglog.cli.main import main
from maglog.hw.arch import uart as arch_uart
from maglog.hw.frontend import MAX_BAUD_ERROR, divisor_for
from maglog.sim.models.logger_uart import UartReceiver, line_changes

_RNG = random.Random(24)
#: Random bytes (both edges at every bit) and ASCII text (a stop bit read a bit early falls
#: in data bit 7, space).
DATA = bytes(_RNG.randrange(256) for _ in range(120)) + b"$GPGGA,1,2,3*00\r\n$PMAG1,4*00\r\n"


def _intact(divisor, bit_cycles, phases=6):
    """Whether the receiver takes DATA sent back to back at ``bit_cycles`` intact at every
    one of ``phases`` tick phases against the first start bit."""
    changes, _ = line_changes(1000, DATA, bit_cycles)
    for origin in range(0, divisor, max(1, divisor // phases)):
        rx = UartReceiver(divisor, origin=origin)
        rx.extend(changes)
        got = rx.run(math.inf)
        if [(c.error, c.data) for c in got] != [(False, b) for b in DATA]:
            return False
    return True


def test_the_readme_component_clock_takes_its_channels():
    # 40 MHz: 115200 baud is divisor 22 (113,636 baud, -1.36 %), 9600 divisor 260 (+0.16 %).
    assert divisor_for(40e6, 115200) == 22
    assert divisor_for(40e6, 9600) == 260
    assert divisor_for(1_843_200, 115200) == 1 and divisor_for(1_843_200, 9600) == 12


@pytest.mark.parametrize("divisor", [12, 22, 326])
def test_the_limit_leaves_the_transmitter_room(divisor):
    """A receiver off by the limit either way still takes a transmitter 2.3 % fast or 3.8 %
    slow (rates), as MAX_BAUD_ERROR's comment says; the receiver's own tolerance ends at bits
    3.75-3.78 % shorter and 5.55-5.58 % longer than its own."""
    own = arch_uart.OVERSAMPLING * divisor          # the receiver's bit, cycles
    for receiver in (-MAX_BAUD_ERROR, MAX_BAUD_ERROR):
        nominal = own * (1 + receiver)              # the nominal bit in the receiver's clocks
        for transmitter in (0.023, -0.038):
            assert _intact(divisor, nominal / (1 + transmitter)), (receiver, transmitter)
    assert _intact(divisor, own * (1 - 0.0370)) and not _intact(divisor, own * (1 - 0.0385))
    assert _intact(divisor, own * (1 + 0.0550)) and not _intact(divisor, own * (1 + 0.0565))


def test_the_limit_is_the_receivers_own_error():
    # 115200 from 30 MHz: divisor 16, +1.73 %: refused; from 29.5 MHz: +0.03 %.
    assert divisor_for(29.5e6, 115200) == 16
    with pytest.raises(ValueError) as error:
        divisor_for(30e6, 115200)
    assert str(error.value) == (
        "Baud rate 115200 from a 30 MHz clock is off by +1.73%: beyond the receiver's ±1.5% "
        "(the rest of what it tolerates is left to the transmitter); 29.4912 MHz or "
        "31.3344 MHz would give it exactly")
    with pytest.raises(ValueError, match=r"off by -45.75%: .*; 1.8432 MHz would give it "
                                         r"exactly\Z"):
        divisor_for(1e6, 115200)
    # Just inside and just outside the limit.
    clk = 16 * 115200 * 20
    assert divisor_for(clk * (1 + 0.0149), 115200) == 20
    assert divisor_for(clk * (1 - 0.0149), 115200) == 20
    for off in (0.0151, -0.0151):
        with pytest.raises(ValueError, match="beyond the receiver's"):
            divisor_for(clk * (1 + off), 115200)


def test_the_refusal_is_one_line_naming_clocks_that_work(capsys):
    assert main(["hdl", "verilog", "--clk-freq", "30e6", "-o", "-"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("maglog: error: Baud rate 115200 from a 30 MHz clock is off by "
                          "+1.73%")
    assert err.endswith("29.4912 MHz or 31.3344 MHz would give it exactly\n")
    assert err.count("\n") == 1
