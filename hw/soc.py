"""amaranth-soc for the whole of hw/: the only module that imports it.

amaranth-soc is not published on PyPI (its name holds an empty placeholder); luna-soc ships
the upstream code and, when imported, puts its vendored folder on ``sys.path``. Importing
the same code a second way (``luna_soc.gateware.vendor.amaranth_soc``) would make a second
copy of every class, so everything in hw/ takes ``csr``, ``wishbone`` and ``MemoryMap`` from
here.
"""

import luna_soc

from amaranth_soc import csr, wishbone
from amaranth_soc.csr.wishbone import WishboneCSRBridge
from amaranth_soc.memory import MemoryMap


__all__ = ["csr", "wishbone", "MemoryMap", "WishboneCSRBridge", "VENDOR"]

#: Where amaranth-soc came from (for reports).
VENDOR = luna_soc.__name__
