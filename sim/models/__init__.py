"""Device models in plain Python (SD card, SDRAM chip), with thin adapters elsewhere for the
Amaranth simulator and for cocotb."""

from .card_image import CardImage
from .sdcard import BlockEvent, CardState, Faults, SdCard, Transaction
from .sdram import SdramChip, SdramTimingError

__all__ = ["CardImage", "SdCard", "Faults", "CardState", "Transaction", "BlockEvent",
           "SdramChip", "SdramTimingError"]
