"""SD card bus protocol constants (SD mode, 4-bit bus).

# Ref: SD Specifications Part 1, Physical Layer Simplified Specification, Version 9.10
#      (SD Association, 2023), cited below as "PLSS".
"""

import enum as _enum

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

class ResponseKind(_enum.IntEnum):
    """What the host's CMD engine expects after a command: the field ``kind`` of the SD
    host's ``command`` register (hw/sdio/cmd.py takes its values from here).

    Ref: PLSS §4.9 (responses R1, R1b, R2, R3, R6, R7).
    """
    NONE   = 0   # CMD0: no response
    SHORT  = 1   # R1, R1b, R6, R7: 48 bits, CRC7 and command index checked
    OCR    = 2   # R3: 48 bits, index field and CRC are all ones, not checked
    LONG   = 3   # R2: 136 bits, CID/CSD with its own CRC7 over bits 127..8


class DataPhase(_enum.IntEnum):
    """What the host's DAT lines do after a command: the field ``data`` of the SD host's
    ``command`` register (hw/sdio/host.py takes its values from here). A host convention,
    not a PLSS term: CMD24/CMD25 write blocks after their response (PLSS §4.3.4), CMD17 reads
    one (PLSS §4.3.3)."""
    NONE  = 0
    WRITE = 1    # after a good response, write `blocks` blocks from the host's `i` stream
    READ  = 2    # read one block to the host's `o` stream; armed when the command starts


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
#: Busy (DAT0 low) begins at once after the CRC status token's end bit, and after the end
#: bit of an R1b response (PLSS §4.12 timing diagrams, block write and stop transmission:
#: the busy's start bit follows the end bit with no gap). The host accepts it up to this
#: many clocks late (it samples DAT0 at the rising edges 1 .. BUSY_START_CLOCKS + 1 after the
#: end bit), and takes a card that shows no busy in that window as having finished. 8 is
#: four times the spec's turnaround times (N_CRC = N_ST = N_WR = 2 clocks) and equal to the
#: longest of its minimum gaps (N_RC = N_CC = 8): a card slower than that to pull DAT0 low
#: is outside any timing the PLSS draws. It costs nothing when busy starts in time (the wait
#: ends at the first low sample) and 9 clocks per block (<1 % of a block's 1,050) on a card
#: that shows no busy at all.
BUSY_START_CLOCKS = 8
# Ref: PLSS §4.6.2 "Read, Write and Erase Timeout Conditions": SDHC write (busy) timeout
#      250 ms, read access timeout 100 ms; in clocks at the 25 MHz default speed.
DEFAULT_SPEED_HZ = 25_000_000
BUSY_TIMEOUT_CLOCKS = DEFAULT_SPEED_HZ // 4
READ_TIMEOUT_CLOCKS = DEFAULT_SPEED_HZ // 10

# -- Card side: commands, responses, states, status, OCR, timing -------------------------------
# Added for the plain-Python card model (sim/models/sdcard.py); usable by the gateware too.


class Command(_enum.IntEnum):
    """Command indices of the SD-mode commands the card model implements.

    Ref: PLSS §4.7.4 "Detailed Command Description" (basic commands class 0, block-oriented
    read class 2, block-oriented write class 4, application-specific commands class 8).
    """
    GO_IDLE_STATE        = 0    # bc,  no response
    ALL_SEND_CID         = 2    # bcr, R2 (CID)
    SEND_RELATIVE_ADDR   = 3    # bcr, R6
    SELECT_CARD          = 7    # ac,  R1b (only from the selected card)
    SEND_IF_COND         = 8    # bcr, R7
    SEND_CSD             = 9    # ac,  R2 (CSD)
    SEND_CID             = 10   # ac,  R2 (CID)
    STOP_TRANSMISSION    = 12   # ac,  R1b
    SEND_STATUS          = 13   # ac,  R1
    GO_INACTIVE_STATE    = 15   # ac,  no response
    SET_BLOCKLEN         = 16   # ac,  R1
    READ_SINGLE_BLOCK    = 17   # adtc, R1
    READ_MULTIPLE_BLOCK  = 18   # adtc, R1
    SET_BLOCK_COUNT      = 23   # ac,  R1 (optional: SCR CMD_SUPPORT bit 33)
    WRITE_BLOCK          = 24   # adtc, R1
    WRITE_MULTIPLE_BLOCK = 25   # adtc, R1
    APP_CMD              = 55   # ac,  R1


class AppCommand(_enum.IntEnum):
    """Application-specific command indices (each preceded by CMD55).

    Ref: PLSS §4.7.4, table "Application Specific Commands used/reserved by SD Memory Card".
    """
    SET_BUS_WIDTH          = 6    # ac,  R1
    SD_STATUS              = 13   # adtc, R1
    SEND_NUM_WR_BLOCKS     = 22   # adtc, R1
    SET_WR_BLK_ERASE_COUNT = 23   # ac,  R1
    SD_SEND_OP_COND        = 41   # bcr, R3
    SET_CLR_CARD_DETECT    = 42   # ac,  R1
    SEND_SCR               = 51   # adtc, R1


class Response(_enum.Enum):
    """Response types. Ref: PLSS §4.9 "Responses" (§4.9.1 R1 … §4.9.6 R7)."""
    NONE = "none"
    R1   = "R1"     # 48 bits: index, card status, CRC7
    R1B  = "R1b"    # R1, then busy on DAT0
    R2   = "R2"     # 136 bits: index field 111111, CID or CSD bits 127..1 (own CRC7), end
    R3   = "R3"     # 48 bits: index field 111111, OCR, CRC field 1111111
    R6   = "R6"     # 48 bits: index, new RCA, status bits 23, 22, 19, 12..0, CRC7
    R7   = "R7"     # 48 bits: index, voltage accepted and check pattern echoed, CRC7


#: Length of each response on the CMD line, in bits.
RESPONSE_BITS = {Response.R1: CMD_BITS, Response.R1B: CMD_BITS, Response.R2: R2_BITS,
                 Response.R3: CMD_BITS, Response.R6: CMD_BITS, Response.R7: CMD_BITS}
#: R2 and R3 carry 111111 in the command-index field; R3 also carries 1111111 as its CRC.
RESPONSE_INDEX_ONES = 0b111111
R3_CRC_ONES = 0b1111111


class CardState(_enum.IntEnum):
    """Card states, valued as the CURRENT_STATE field of the card status.

    Ref: PLSS §4.2 and §4.3 (state diagrams), §4.8 "Card State Transition Table", §4.10.1
    "Card Status" (CURRENT_STATE codes 0..8; 9..14 reserved, 15 reserved for I/O mode).
    The inactive state (ina) has no code: a card in it never answers.
    """
    IDLE  = 0
    READY = 1
    IDENT = 2
    STBY  = 3
    TRAN  = 4
    DATA  = 5
    RCV   = 6
    PRG   = 7
    DIS   = 8


class CardStatus(_enum.IntFlag):
    """Card status bits (the 32 bits of R1). Ref: PLSS §4.10.1 "Card Status".

    CURRENT_STATE (bits 12..9) is a field: see :data:`STATUS_STATE_SHIFT`.
    """
    OUT_OF_RANGE       = 1 << 31
    ADDRESS_ERROR      = 1 << 30
    BLOCK_LEN_ERROR    = 1 << 29
    ERASE_SEQ_ERROR    = 1 << 28
    ERASE_PARAM        = 1 << 27
    WP_VIOLATION       = 1 << 26
    CARD_IS_LOCKED     = 1 << 25
    LOCK_UNLOCK_FAILED = 1 << 24
    COM_CRC_ERROR      = 1 << 23
    ILLEGAL_COMMAND    = 1 << 22
    CARD_ECC_FAILED    = 1 << 21
    CC_ERROR           = 1 << 20
    ERROR              = 1 << 19
    CSD_OVERWRITE      = 1 << 16
    WP_ERASE_SKIP      = 1 << 15
    CARD_ECC_DISABLED  = 1 << 14
    ERASE_RESET        = 1 << 13
    READY_FOR_DATA     = 1 << 8
    FX_EVENT           = 1 << 6
    APP_CMD            = 1 << 5
    AKE_SEQ_ERROR      = 1 << 3


STATUS_STATE_SHIFT = 9
STATUS_STATE_MASK = 0xF << STATUS_STATE_SHIFT
#: Clear condition B (§4.10.1): "always related to the previous command; reception of a
#: valid command clears it, with a delay of one command".
STATUS_PREVIOUS_COMMAND = CardStatus.COM_CRC_ERROR | CardStatus.ILLEGAL_COMMAND
#: Clear condition C: cleared by being read (sent in a response).
STATUS_CLEAR_ON_READ = (
    CardStatus.OUT_OF_RANGE | CardStatus.ADDRESS_ERROR | CardStatus.BLOCK_LEN_ERROR
    | CardStatus.ERASE_SEQ_ERROR | CardStatus.ERASE_PARAM | CardStatus.WP_VIOLATION
    | CardStatus.LOCK_UNLOCK_FAILED | CardStatus.CARD_ECC_FAILED | CardStatus.CC_ERROR
    | CardStatus.ERROR | CardStatus.CSD_OVERWRITE | CardStatus.WP_ERASE_SKIP
    | CardStatus.ERASE_RESET | CardStatus.APP_CMD | CardStatus.AKE_SEQ_ERROR)
#: R6 carries status bits 23, 22, 19 and 12..0 in its low 16 bits (PLSS §4.9.5).
R6_STATUS_HIGH_BITS = ((23, 15), (22, 14), (19, 13))
R6_STATUS_LOW_MASK = 0x1FFF

# Ref: PLSS §4.3.2 "2 GByte Card", §5.3.2 (CSD 1.0): a standard-capacity (SDSC, CCS = 0)
#      card holds at most 2 GB and takes byte addresses; SDHC/SDXC (CCS = 1) block addresses.
SDSC_MAX_BLOCKS = (2 << 30) // BLOCK_BYTES

# Ref: PLSS §5.1 "OCR register" and §4.7.4 (ACMD41 argument).
OCR_POWER_UP_DONE = 1 << 31      # 0 while the card is busy initialising
OCR_CCS = 1 << 30                # card capacity status: 1 = SDHC/SDXC (block addressing)
OCR_UHS2 = 1 << 29
OCR_S18A = 1 << 24
OCR_VOLTAGE_WINDOW = 0x00FF8000  # bits 23..15: 2.7..3.6 V in 0.1 V steps
ACMD41_HCS = 1 << 30             # host supports high capacity
ACMD41_XPC = 1 << 28
ACMD41_S18R = 1 << 24

# Ref: PLSS §4.3.13 "Send Interface Condition Command (CMD8)": VHS 0001b is
#      2.7..3.6 V; the card echoes VHS and the check pattern in R7.
IF_COND_VHS_SHIFT = 8
IF_COND_VHS_MASK = 0xF << IF_COND_VHS_SHIFT
IF_COND_VHS_2V7_3V6 = 0b0001
IF_COND_PATTERN_MASK = 0xFF
#: The check pattern the host sends (PLSS §4.3.13 recommends 10101010b).
IF_COND_PATTERN = 0xAA
IF_COND_ARGUMENT = (IF_COND_VHS_2V7_3V6 << IF_COND_VHS_SHIFT) | IF_COND_PATTERN
#: The bits of R7 that echo the argument: VHS and the check pattern.
IF_COND_ECHO_MASK = IF_COND_VHS_MASK | IF_COND_PATTERN_MASK

# Ref: PLSS §4.7.4 ACMD6 argument bits 1..0: 00 = 1 bit, 10 = 4 bits.
BUS_WIDTH_1 = 0b00
BUS_WIDTH_4 = 0b10
# Ref: PLSS §4.7.4 ACMD23 argument bits 22..0: number of blocks to pre-erase.
PRE_ERASE_COUNT_MASK = (1 << 23) - 1

# Ref: PLSS §4.12.4 "Timing Values": N_CR 2..64, N_ID = 5 (CMD2 and
#      ACMD41 answers), N_AC ≥ 2 (read command end to data), N_RC ≥ 8 (response end to next
#      command), N_CC ≥ 8 (see above), N_WR ≥ 2 (see above); the CRC status token starts
#      N_CRC = 2 clocks after a written block's end bit; a read stops N_ST = 2 clocks after
#      CMD12's end bit (§4.12 timing diagrams, stop transmission).
N_CR_MIN = 2
N_ID = 5
N_AC_MIN = 2
N_RC = 8
N_CRC = 2
N_ST = 2
# Ref: PLSS §6.4.1.1 "Power Up Time of Host": at least 74 clocks, CMD high, before the first
#      command.
INIT_CLOCKS = 74
# Ref: PLSS §4.2 (card identification mode) and the default-speed bus timing (f_OD): the
#      clock is at most 400 kHz until the card has left identification mode (after CMD3).
IDENT_CLOCK_HZ = 400_000
# Ref: PLSS §4.2.3 "Card Initialization and Identification Process": the card finishes its
#      initialisation (OCR busy bit set in the ACMD41 answer) within 1 s of the first ACMD41.
ACMD41_LIMIT_S = 1.0
