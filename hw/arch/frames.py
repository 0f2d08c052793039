"""Serial `$`-frame rules shared by the three channel kinds.

The byte-by-byte reading of these rules, with the counter each dropped frame goes to, is in
docs/frame-rules.md.

# Ref: NMEA 0183 v4.11 §5.2 (sentence structure: `$`, address field of talker and sentence
#      formatter, comma-delimited data, `*hh` checksum: XOR of all characters between `$`
#      and `*`, CR LF); §5.1.3 (valid characters 0x20-0x7E).
# Ref: Geometrics G-882 Operation Manual, RS-232 output: `$ 49895.131,1249` CR LF
#      (`$`, space or `1`, field in nT with three decimals, `,`, signal level).
"""

import enum

DOLLAR = ord("$")
STAR = ord("*")
COMMA = ord(",")
PERIOD = ord(".")
SPACE = ord(" ")
CR = 0x0D
LF = 0x0A

#: Printable range allowed between `$` and the line end.
PRINTABLE_MIN = 0x20
PRINTABLE_MAX = 0x7E

#: Default MAX_FRAME: NMEA 0183 allows 82 bytes, RTK receivers send longer GGA.
DEFAULT_MAX_FRAME = 128
#: Largest MAX_FRAME a build accepts: the position counters of the frame filter are sized
#: for it, and no instrument the logger serves sends longer lines.
MAX_FRAME_LIMIT = 1024
#: Largest frame FIFO per channel, in bytes: 32 M9K blocks at 9 bits, already more than an
#: EP4CE6 has for all channels together (30); a larger one cannot be built on the target.
MAX_FIFO_DEPTH = 1 << 15

#: NMEA sentence formatters the logger keeps, from any two-letter talker.
NMEA_WHITELIST = ("GGA", "ZDA", "VTG")
#: Position of the first formatter letter, and of the comma after the address field.
NMEA_FORMATTER_POS = 3
NMEA_ADDRESS_END_POS = 6
#: The GGA field that holds the fix quality (field 0 is the address `ccGGA`).
# Ref: NMEA 0183 v4.11 §6.3 GGA: time, lat, N/S, lon, E/W, quality indicator, ...
GGA_QUALITY_FIELD = 6

#: Address field of the magnetometer's proprietary sentence, with its comma.
PMAG_HEADER = b"PMAG1,"

#: Shortest NMEA or `$PMAG1` body (between `$` and the line end): 6-byte address field
#: with comma, then `*hh`.
CHECKED_MIN_BODY = 9

#: Cesium frame template after `$` (before the line end): `s` is a space or `1`, `d` a digit.
CESIUM_TEMPLATE = b"sddddd.ddd,dddd"
CESIUM_BODY = len(CESIUM_TEMPLATE)
#: Longest cesium frame: `$`, body, CR, LF.
CESIUM_MAX_FRAME = 1 + CESIUM_BODY + 2


class DropCause(enum.IntEnum):
    """Why a frame was dropped; the counter it goes to is ``cause.counter``."""
    CHECKSUM        = 0
    NOT_WHITELISTED = 1
    OVERLONG        = 2
    BAD_BYTE        = 3
    UART_ERROR      = 4
    OVERFLOW        = 5

    @property
    def counter(self):
        return self.name.lower()


#: Counter names in register order: kept frames first, then drops by cause.
COUNTER_NAMES = ("kept",) + tuple(cause.counter for cause in DropCause)
