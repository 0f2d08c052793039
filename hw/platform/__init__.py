"""Board platforms, the board top and the Quartus project writer (Cyclone IV targets).

``boards`` holds the Amaranth platforms (DE0-Nano with an SD/UART breakout, and the
EP4CE6E22C8 logger board), ``top`` the board top (PLL, I/O registers, the NIOS II system
instance and the logger), ``quartus`` the project writer behind ``maglog hdl build``.
``avalon`` and ``component`` hold the Avalon-MM logger and the Platform Designer component.
"""
