"""Simulation, grouped by the data flow (DESIGN.md):

- ``stimulus/``: a scenario (TOML, or a :class:`~maglog.sim.stimulus.scenario.Flight`) →
  sentences → sensor byte streams with their timing
  (:class:`~maglog.sim.stimulus.system.SystemScenario`) → UART line levels;
- ``reference/``: the frame filter's rules in plain Python (what the log must hold);
- ``models/``: the devices in plain Python, no simulator imports (SD card and the bus
  between card and host, SDRAM chip, card image, the transaction-level logger);
- ``backends/``: one module per simulator that puts the models on the gateware's pins
  (``amaranth``, ``cocotb`` with its test modules ``cocotb_*``, ``fast``: the Verilator
  harness);
- ``runners/``: backend-agnostic benches (the front end, the whole system), one result out.
"""
