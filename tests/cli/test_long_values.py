"""A value of thousands of characters given on the command line is repeated in its error
cut short (issue 23: a 10,000-character value echoed whole)."""

import pytest

from maglog.cli.main import main


def _last_line(capsys, argv):
    try:
        status = main(argv)
    except SystemExit as exit_:
        status = exit_.code
    err = capsys.readouterr().err.strip().splitlines()
    assert status in (1, 2) and err, err
    return err[-1]


@pytest.mark.parametrize("argv", [
    ["card", "format", "{tmp}/c.img", "--size", "64MiB", "--cluster-size", "512", "--label",
     "x" * 10_000],
    ["hdl", "regmap", "--format", "x" * 10_000],
    ["replay", "short", "--port", "mag=loop://", "--speed", "9" * 10_000],
    ["simulate", "short", "-o", "{tmp}/c.img", "--max-seconds", "x" * 10_000],
])
def test_long_values_are_cut_short(tmp_path, capsys, argv):
    line = _last_line(capsys, [a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert line.startswith("maglog") and len(line) < 300 and "…" in line, line
