"""``maglog hdl build`` and ``hdl component``: the output folder checked before the
elaboration (which takes seconds), and ``--sdram-phase`` read as a number even when it starts
with a minus ("-inf", "-1e-3")."""

import pytest

from maglog.cli.main import main


@pytest.fixture
def no_elaboration(monkeypatch):
    """The builders replaced: a test that reaches them records its arguments."""
    from maglog.hw.platform import component, quartus
    calls = []

    def build_project(board, directory, **kwargs):
        calls.append(("build", directory, kwargs))
        return []

    def write_component(directory, kwargs=None):
        calls.append(("component", directory, kwargs))
        return []
    monkeypatch.setattr(quartus, "build_project", build_project)
    monkeypatch.setattr(component, "write_component", write_component)
    return calls


def _main(argv):
    """main()'s exit status, the parser's exit 2 included."""
    try:
        return main(argv)
    except SystemExit as exit_:
        return exit_.code


def _one_line(capsys, status, code=1):
    err = capsys.readouterr().err.strip().splitlines()
    assert status == code and len(err) == 1, err
    return err[0]


@pytest.mark.parametrize("argv", [
    ["hdl", "build", "--board", "de0nano", "-o", "/proc/maglog-x"],
    ["hdl", "component", "-o", "/proc/maglog-x"],
    ["hdl", "build", "--board", "de0nano", "-o", "{file}"],
    ["hdl", "component", "-o", "{file}"],
    ["hdl", "component", "-o", "{file}/sub"],
    ["hdl", "build", "--board", "de0nano", "-o", "{full}"],
])
def test_output_refused_before_elaboration(tmp_path, capsys, no_elaboration, argv):
    (tmp_path / "FILE").write_text("mine")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    argv = [a.replace("{file}", str(tmp_path / "FILE")).replace("{full}", str(tmp_path / "full"))
            for a in argv]
    line = _one_line(capsys, _main(argv))
    assert line.startswith("maglog: error: ")
    assert no_elaboration == []
    assert (tmp_path / "FILE").read_text() == "mine"
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


def test_output_folder_made_then_elaborated(tmp_path, capsys, no_elaboration):
    out = tmp_path / "a" / "b"
    assert main(["hdl", "build", "--board", "de0nano", "-o", str(out)]) == 0
    assert out.is_dir() and no_elaboration[0][0] == "build"
    assert main(["hdl", "component", "-o", str(tmp_path / "c")]) == 0
    assert no_elaboration[1][0] == "component"
    assert not list(out.iterdir())      # the write test leaves nothing behind


@pytest.mark.parametrize("value", ["-inf", "inf", "-nan", "nan", "x", "-infinity"])
def test_sdram_phase_not_finite_is_a_usage_error(tmp_path, capsys, no_elaboration, value):
    line = _one_line(capsys, _main(["hdl", "build", "--board", "de0nano", "-o",
                                   str(tmp_path / "p"), "--sdram-phase", value]), 2)
    assert "--sdram-phase" in line and "finite number" in line, line
    assert no_elaboration == [] and not (tmp_path / "p").exists()


@pytest.mark.parametrize("value, ns", [("-1e-3", -1e-3), ("-2.5", -2.5), ("-.5", -0.5),
                                       ("1E1", 10.0), ("-3", -3.0)])
def test_sdram_phase_with_a_minus_is_a_value(tmp_path, no_elaboration, value, ns):
    assert main(["hdl", "build", "--board", "de0nano", "-o", str(tmp_path / "p"),
                 "--sdram-phase", value]) == 0
    assert no_elaboration[0][2]["sdram_phase_ns"] == ns


def test_a_failed_build_leaves_no_folder_it_made(tmp_path, capsys):
    # The real builder: a phase beyond a clock period is refused by the PLL settings.
    out = tmp_path / "p"
    line = _one_line(capsys, _main(["hdl", "build", "--board", "de0nano", "-o", str(out),
                                   "--sdram-phase", "-1e3"]))
    assert "exceeds a period" in line and not out.exists()


def test_board_name_echo_is_cut_short(tmp_path, capsys, no_elaboration):
    line = _one_line(capsys, _main(["hdl", "build", "--board", "b" * 10_000, "-o",
                                   str(tmp_path / "p")]))
    assert len(line) < 200 and "unknown board" in line


@pytest.mark.parametrize("command", [["hdl", "verilog"], ["hdl", "verilog", "--frontend"],
                                     ["hdl", "regmap"]])
@pytest.mark.parametrize("target", ["/proc/maglog-x.v", "{dir}", "{file}/sub.v"])
def test_verilog_and_regmap_check_the_output_first(tmp_path, capsys, monkeypatch, command,
                                                   target):
    from maglog.hw import frontend, top

    def elaborates(*args, **kwargs):
        raise AssertionError("elaborated before the output was checked")
    monkeypatch.setattr(frontend, "generate_verilog", elaborates)
    monkeypatch.setattr(top, "generate_verilog", elaborates)
    monkeypatch.setattr(top, "Logger", elaborates)
    (tmp_path / "FILE").write_text("mine")
    target = target.replace("{dir}", str(tmp_path)).replace("{file}", str(tmp_path / "FILE"))
    line = _one_line(capsys, _main(command + ["-o", target]))
    assert line.startswith("maglog: error: ") and ".maglog-write-test" not in line, line
    assert (tmp_path / "FILE").read_text() == "mine"
