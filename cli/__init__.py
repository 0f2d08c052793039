"""The command line on top of maglog: the only layer that imports hw, sw, sim and calib
together (nothing imports it)."""
