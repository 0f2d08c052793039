"""Frequencies as a person reads them: every message that names a clock goes through
:func:`hertz` ("50 MHz", "1.8432 MHz"), never ``5e+07 Hz`` or ``40000000.0 Hz``."""

import math
import numbers

__all__ = ["hertz"]

_PREFIXES = ((1e9, "GHz"), (1e6, "MHz"), (1e3, "kHz"))


def hertz(value, digits=6):
    """``value`` (Hz) in the largest unit of GHz, MHz, kHz or Hz that keeps it at 1 or
    more, to ``digits`` significant digits without trailing zeros: 50e6 → "50 MHz",
    1843200 → "1.8432 MHz", 9600 → "9.6 kHz", 0.5 → "0.5 Hz". Anything that is not a
    finite number is shown as given, ``repr`` and " Hz"."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real) \
            or not math.isfinite(value):
        return f"{value!r} Hz"
    value = float(f"{value:.{digits}g}")      # rounded first: 999999.9999 is 1 MHz
    scale, unit = next(((s, u) for s, u in _PREFIXES if abs(value) >= s), (1.0, "Hz"))
    number = value / scale
    decimals = max(0, digits - 1 - int(math.floor(math.log10(abs(number))))) if number else 0
    text = f"{number:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return f"{text} {unit}"
