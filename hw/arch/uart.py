"""Asynchronous serial (UART) line constants.

# Ref: TIA-232-F (EIA-232) §2 and the usual 8N1 character format: one start bit (space,
# logic 0), eight data bits LSB first, no parity, one stop bit (mark, logic 1); the idle line
# is mark. A break is a line held at space for longer than one whole character.
"""

#: Line level of an idle line and of the stop bit (mark).
MARK = 1
#: Line level of the start bit (space).
SPACE = 0

#: Data bits per character (8N1).
DATA_BITS = 8
#: Bits per character on the wire: start, data, stop.
CHARACTER_BITS = 1 + DATA_BITS + 1

#: Receiver oversampling: samples per bit.
OVERSAMPLING = 16
#: Width of the receiver's run-time baud divisor (the front end's divisor registers): 9600
#: baud from a 50 MHz clock needs 326, and 16 bits reach 47.7 baud at 50 MHz.
DIVISOR_BITS = 16
#: Oversampling ticks whose samples are voted on to decide a bit: the three around the
#: middle of the bit (tick 0 is the first sample that saw the start bit's falling edge).
VOTE_TICKS = (7, 8, 9)
