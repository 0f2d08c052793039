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

# -- Command and response framing (host side) ----------------------------------------------
# Ref: PLSS §4.7.2 "Command Format" (48 bits: start 0, transmission 1, index, argument,
#      CRC7, end 1) and §4.9 "Responses" (48 bits; R2 136 bits).
CMD_INDEX_BITS = 6
CMD_ARGUMENT_BITS = 32
CMD_BITS = 48
#: Bits covered by the CRC7 of a command or 48-bit response: start through argument.
CMD_CRC_LAST = 40
#: R2: 136 bits; its CRC7 covers the CID/CSD register bits 127..8 (response bits 8..127).
R2_BITS = 136
R2_CONTENT_BITS = 128
R2_CRC_FIRST = 8
R2_CRC_LAST = 128

# Ref: PLSS §4.12.4 "Timing Values": N_CR (command end to response) 2..64 clocks; N_CC and
#      N_RC (response end to next command) at least 8 clocks.
N_CR_MAX = 64
N_CC = 8
