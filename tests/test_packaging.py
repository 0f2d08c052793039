"""The distribution as pip builds it: a wheel of a copy of the source holds every package
folder of the tree, every module and every data file the code reads, and the console script.
The editable install of ``make`` would hide a package left out (it reads the source tree)."""

import configparser
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The folders that become ``maglog.<folder>`` (setup.py's ROOTS, restated here).
PACKAGE_ROOTS = ("hw", "sw", "sim", "calib", "cli")
#: Files besides the Python modules that the code opens at run time.
DATA_SUFFIXES = (".toml", ".cpp", ".lib", ".v")


def source_files():
    """``{path in the wheel: path in the tree}`` for every module and data file under the
    package roots, in folders that are packages (hold an ``__init__.py``)."""
    found = {}
    for root in PACKAGE_ROOTS:
        for path in (ROOT / root).rglob("*"):
            if not path.is_file() or "__pycache__" in path.parts:
                continue
            if not (path.parent / "__init__.py").is_file():
                continue
            if path.suffix == ".py" or path.suffix in DATA_SUFFIXES:
                found["maglog/" + path.relative_to(ROOT).as_posix()] = path
    return found


def build_wheel(source, dist, output=None):
    """pip's wheel of the folder ``source`` (no dependencies, this environment's setuptools)
    into ``dist``; returns its path. ``output``, a list, gets what pip printed."""
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
         "--wheel-dir", str(dist), str(source)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    if output is not None:
        output.append(result.stdout + result.stderr)
    wheels = list(dist.glob("maglog-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def copy_source(target, *, leave_out=()):
    """The files a source distribution holds (setup.py, pyproject.toml, README.md and the
    package roots), without caches, into ``target``; ``leave_out``: folders to drop."""
    for name in ("setup.py", "pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, target / name)
    for root in PACKAGE_ROOTS:
        shutil.copytree(ROOT / root, target / root,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for folder in leave_out:
        shutil.rmtree(target / folder)


def wheel_problems(wheel, expected):
    """What the wheel lacks of ``expected`` (wheel paths), and whether its console script
    is there."""
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        entry_points = next((n for n in names if n.endswith(".dist-info/entry_points.txt")),
                            None)
        scripts = configparser.ConfigParser()
        if entry_points:
            scripts.read_string(archive.read(entry_points).decode())
    missing = sorted(set(expected) - names)
    if not scripts.has_option("console_scripts", "maglog"):
        missing.append("console script maglog")
    return missing


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """(the wheel, what pip printed while building it)."""
    source = tmp_path_factory.mktemp("source")
    copy_source(source)
    output = []
    return build_wheel(source, tmp_path_factory.mktemp("dist"), output), output[0]


@pytest.fixture(scope="module")
def wheel(built):
    return built[0]


def test_the_build_prints_no_warning_banner(built):
    # setuptools frames what it deprecates or doubts in the configuration (a license as a
    # table, a License classifier beside the SPDX expression, ...) between "!!" lines, which
    # pip shows even with --quiet: the build of pyproject.toml and setup.py says nothing.
    # (The editable install of scripts/setup.sh prints setuptools' one notice of every
    # editable install of a layout that is not src/: see pyproject.toml.)
    output = built[1]
    assert "!!" not in output and "Warning" not in output, output


def test_the_wheel_holds_every_package_module_and_data_file(wheel):
    expected = source_files()
    assert "maglog/hw/platform/__init__.py" in expected          # the one once left out
    assert "maglog/sim/stimulus/default.toml" in expected
    assert wheel_problems(wheel, expected) == []
    with zipfile.ZipFile(wheel) as archive:
        shipped = {n.split("/")[1] for n in archive.namelist() if n.startswith("maglog/")}
    assert shipped == set(PACKAGE_ROOTS)                           # no tests/, no bench/


def test_a_package_the_build_leaves_out_is_seen(tmp_path):
    # The check itself: a source copy whose setup.py discovers nothing below the roots
    # (as a hand-written list that forgot a folder would) gives a wheel the check refuses.
    source = tmp_path / "source"
    source.mkdir()
    copy_source(source)
    setup = source / "setup.py"
    text = setup.read_text()
    assert "find_packages(root)" in text
    setup.write_text(text.replace("find_packages(root)", "[]"))
    wheel = build_wheel(source, tmp_path / "dist")
    missing = wheel_problems(wheel, source_files())
    assert "maglog/hw/platform/__init__.py" in missing
