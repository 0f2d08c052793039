"""The Platform Designer component folder: the _hw.tcl against the Verilog it packages
(every port once, right direction and width), the Avalon slave's properties, and the C
header against the register map."""

import re

import pytest

from maglog.hw.frame_filter import ChannelKind
from maglog.hw.frontend import ChannelConfig
from maglog.hw.platform.avalon import AVS_TIMING, TOPLEVEL_NAME, AvalonLogger
from maglog.hw.platform.component import (HEADER_NAME, HW_TCL_NAME, QSYS_VERSION, README_NAME,
                                          VERILOG_NAME, write_component)
from maglog.hw.top import LOGGER_ID
from maglog.sw.regmap import RegisterMap

#: Two channels, another clock: nothing in the component may assume the defaults.
KWARGS = {"channels": [ChannelConfig(ChannelKind.NMEA, 9600),
                       ChannelConfig(ChannelKind.CESIUM, 9600)],
          "clk_freq": 40e6}


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("component")
    paths = write_component(out / "maglog", KWARGS)
    assert [p.name for p in paths] == [HW_TCL_NAME, VERILOG_NAME, HEADER_NAME, README_NAME]
    return out / "maglog"


@pytest.fixture(scope="module")
def tcl(folder):
    return (folder / HW_TCL_NAME).read_text()


def verilog_header_ports(text):
    """``{name: (direction, width)}`` from the module's header and declarations."""
    header = re.search(rf"^module {TOPLEVEL_NAME}\(([^)]*)\);", text, re.M)
    assert header, f"no module {TOPLEVEL_NAME}"
    names = [name.strip() for name in header.group(1).split(",")]
    body = text[header.end():text.index("endmodule", header.end())]
    ports = {}
    for name in names:
        declared = re.search(rf"^\s*(input|output) (?:\[(\d+):0\] )?{re.escape(name)};",
                             body, re.M)
        assert declared, name
        ports[name] = (declared.group(1), int(declared.group(2) or 0) + 1)
    assert len(ports) == len(names)
    return ports


def tcl_ports(text):
    """``[(interface, name, role, direction, width)]`` of every add_interface_port."""
    return [(i, n, r, d.lower(), int(w))
            for i, n, r, d, w in re.findall(
                r"^add_interface_port (\w+) (\w+) (\w+) (Input|Output|Bidir) (\d+)$",
                text, re.M)]


def test_every_verilog_port_is_in_the_hw_tcl_once(folder, tcl):
    verilog = verilog_header_ports((folder / VERILOG_NAME).read_text())
    listed = tcl_ports(tcl)
    names = [name for _, name, _, _, _ in listed]
    assert sorted(names) == sorted(verilog)
    for interface, name, role, direction, width in listed:
        assert (direction, width) == verilog[name], name
    # The widths follow the parameters: two channels.
    assert verilog["uart_rx"] == ("input", 2)


def test_interfaces_are_declared_and_roles_unique(tcl):
    declared = dict(re.findall(r"^add_interface (\w+) (\w+) (?:end|start)$", tcl, re.M))
    assert declared == {"clock": "clock", "reset": "reset", "avs": "avalon",
                        "uart": "conduit", "sd": "conduit", "sdram": "conduit",
                        "led": "conduit", "button": "conduit"}
    listed = tcl_ports(tcl)
    for interface in declared:
        roles = [role for i, _, role, _, _ in listed if i == interface]
        assert roles and len(roles) == len(set(roles)), interface
    avs_roles = {role for i, _, role, _, _ in listed if i == "avs"}
    assert avs_roles == {"address", "read", "write", "writedata", "byteenable", "readdata",
                         "waitrequest", "readdatavalid"}
    clocked = re.findall(r"^set_interface_property (\w+) associatedClock clock$", tcl, re.M)
    assert set(clocked) == set(declared) - {"clock"}


def test_avalon_slave_properties_match_its_timing(tcl):
    props = dict(re.findall(r"^set_interface_property avs (\w+) (\S+)$", tcl, re.M))
    for name, value in AVS_TIMING.items():
        assert props[name] == str(value), name
    assert props["associatedReset"] == "reset"
    assert re.search(r"^set_interface_property reset synchronousEdges BOTH$", tcl, re.M)
    # The clock sink asks for the clock the gateware was generated for.
    assert re.search(r"^set_interface_property clock clockRate 40000000$", tcl, re.M)


def test_module_and_file_set(tcl):
    assert tcl.count(f"package require -exact qsys {QSYS_VERSION}\n") == 1
    assert re.search(rf"^set_module_property NAME {TOPLEVEL_NAME}$", tcl, re.M)
    assert re.search(r'^add_fileset QUARTUS_SYNTH QUARTUS_SYNTH "" ""$', tcl, re.M)
    assert re.search(rf"^set_fileset_property QUARTUS_SYNTH TOP_LEVEL {TOPLEVEL_NAME}$",
                     tcl, re.M)
    assert (f"add_fileset_file {VERILOG_NAME} VERILOG PATH {VERILOG_NAME} TOP_LEVEL_FILE"
            in tcl)


def test_c_header_offsets_are_bytes_of_the_register_map(folder):
    header = (folder / HEADER_NAME).read_text()
    regs = RegisterMap(AvalonLogger(**KWARGS).csr_memory_map)
    defined = {name: int(value, 16) for name, value in
               re.findall(r"^#define MAGLOG_AVS_(\w+)_ADDR (0x[0-9a-f]+)u$", header, re.M)}
    assert defined == {reg.name.upper(): 4 * reg.address for reg in regs}
    # Two channels: the front end's window has no third channel.
    assert "FRONTEND_CH1_DIVISOR" in defined and "FRONTEND_CH2_DIVISOR" not in defined
    for reg in regs:
        for field in reg.fields.values():
            name = f"MAGLOG_AVS_{reg.name}_{field.name.replace('.', '_')}".upper()
            assert f"#define {name}_SHIFT {field.offset}u\n" in header
            assert f"#define {name}_MASK {field.mask:#x}u\n" in header
    assert "BYTE OFFSETS" in header
    assert header.count("#ifndef MAGLOG_AVS_REGS_H") == 1 and header.rstrip().endswith("*/")


def test_readme_names_the_files_and_the_id(folder):
    text = (folder / README_NAME).read_text()
    for name in (HW_TCL_NAME, VERILOG_NAME, HEADER_NAME):
        assert name in text
    assert f"{LOGGER_ID:#010x}" in text.lower()
    assert "40000000 Hz" in text


def test_verilog_is_lint_clean_but_for_the_project_waivers(folder, external):
    """Verilator's -Wall on the component's Verilog, with only the waivers every generated
    top has (sim/backends/cocotb.py's VERILATOR_WAIVERS, as tests/hw/test_lint.py)."""
    import subprocess
    from maglog.sim.backends.cocotb import verilator_waiver_args
    verilator = external.simulator("verilator")
    proc = subprocess.run([verilator, "--lint-only", "-Wall", *verilator_waiver_args(),
                           "--top-module", TOPLEVEL_NAME, str(folder / VERILOG_NAME)],
                          capture_output=True, text=True, timeout=300)
    warnings = re.findall(r"^%Warning-.*$", proc.stderr, re.M)
    assert warnings == [] and proc.returncode == 0, proc.stderr[-2000:]


def test_the_component_header_and_the_regmap_header_share_no_macro(folder):
    # One holds byte offsets, the other word addresses: no name may mean both.
    from maglog.sw.regmap import to_c_header
    component = (folder / HEADER_NAME).read_text()
    regmap = to_c_header(RegisterMap(AvalonLogger(**KWARGS).csr_memory_map), prefix="maglog")
    macros = lambda text: set(re.findall(r"^#(?:define|ifndef) (\w+)", text, re.M))
    assert macros(component) and macros(regmap)
    assert not macros(component) & macros(regmap)
