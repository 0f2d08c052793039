"""SD card bus protocol constants (SD mode, 4-bit bus).

# Ref: SD Specifications Part 1, Physical Layer Simplified Specification, Version 9.10
#      (SD Association, 2023), cited below as "PLSS".
"""

#: CRC7 for commands and responses: G(x) = x^7 + x^3 + 1, register starts at 0, bits MSB first.
# Ref: PLSS §4.5 "Cyclic Redundancy Code (CRC)", CRC7.
CRC7_POLY = 0x09
CRC7_BITS = 7

#: CRC16 for data blocks, one per DAT line in 4-bit mode: G(x) = x^16 + x^12 + x^5 + 1
#: (CRC-16-CCITT), register starts at 0, bits MSB first.
# Ref: PLSS §4.5, CRC16.
CRC16_POLY = 0x1021
CRC16_BITS = 16

#: Golden values from PLSS §4.5: CMD0 (argument 0) ends 0x95; CMD17 (argument 0) ends 0x55;
#: a 512-byte block of 0xFF sent on one line has CRC16 0x7FA1.
CMD0_LAST_BYTE = 0x95
CMD17_LAST_BYTE = 0x55
CRC16_512_FF = 0x7FA1
