"""hw/arch/units.py: clocks read as "50 MHz", never 5e+07 Hz; and the messages that name
a clock use it."""

import math

import pytest

from maglog.hw.arch.units import hertz
from maglog.hw.frontend import divisor_for


@pytest.mark.parametrize("value, text", [
    (50e6, "50 MHz"), (50_000_000, "50 MHz"), (1_843_200, "1.8432 MHz"),
    (40e6, "40 MHz"), (12.288e6, "12.288 MHz"), (100e6 / 3, "33.3333 MHz"),
    (25e6, "25 MHz"), (9600, "9.6 kHz"), (115200, "115.2 kHz"), (400e3, "400 kHz"),
    (500, "500 Hz"), (0.5, "0.5 Hz"), (0, "0 Hz"), (1e9, "1 GHz"),
    (999_999.9999, "1 MHz"), (-5e6, "-5 MHz"),
])
def test_hertz(value, text):
    assert hertz(value) == text


@pytest.mark.parametrize("value", [math.nan, math.inf, "fast", None, True])
def test_hertz_of_what_is_no_frequency(value):
    assert hertz(value) == f"{value!r} Hz"


def test_the_baud_message_names_the_clock_in_mhz():
    with pytest.raises(ValueError) as error:
        divisor_for(1.5e6, 115200)
    message = str(error.value)
    assert "Baud rate 115200 from a 1.5 MHz clock is off by" in message
    assert "e+0" not in message and ".0 Hz" not in message
    with pytest.raises(ValueError, match=r"cannot be reached from a 1 kHz clock"):
        divisor_for(1e3, 115200)
