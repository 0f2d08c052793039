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

# -- Data blocks on the 4-bit bus ------------------------------------------------------------
# Ref: PLSS §4.3.4 (block write), §7.1.3.2/§4.9 (data packet format, wide bus): start bit 0
#      on every line, 512 bytes as 1024 nibbles high nibble first, a CRC16 per line, end bit.
BLOCK_BYTES = 512
DATA_NIBBLES = 2 * BLOCK_BYTES
#: N_WR: at least 2 clocks between the end of the response (or of busy) and a data block.
N_WR = 2
# Ref: PLSS §4.3.4, §7.3.2.5 (CRC status token on DAT0 after a written block: start 0, three
#      status bits, end 1): 010 accepted, 101 CRC error, 110 write error.
TOKEN_STATUS_BITS = 3
TOKEN_ACCEPTED = 0b010
TOKEN_CRC_ERROR = 0b101
TOKEN_WRITE_ERROR = 0b110
#: The token starts 2 clocks after the block's end bit (N_CRC); give a card some slack.
TOKEN_TIMEOUT_CLOCKS = 16
#: Busy (DAT0 low) may begin up to 2 clocks after the token's end bit.
BUSY_START_CLOCKS = 2
# Ref: PLSS §4.6.2 "Read, Write and Erase Timeout Conditions": SDHC write (busy) timeout
#      250 ms, read access timeout 100 ms; in clocks at the 25 MHz default speed.
DEFAULT_SPEED_HZ = 25_000_000
BUSY_TIMEOUT_CLOCKS = DEFAULT_SPEED_HZ // 4
READ_TIMEOUT_CLOCKS = DEFAULT_SPEED_HZ // 10
