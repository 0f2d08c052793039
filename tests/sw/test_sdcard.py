"""sw/sdcard.py: the SD driver needs hw/arch only, and meets cards as they are."""

import subprocess
import sys


def test_the_driver_imports_without_amaranth():
    # A fresh interpreter: the firmware's SD driver must not pull in Amaranth (nor any
    # gateware module) on its way in.
    code = ("import sys, maglog.sw.sdcard\n"
            "assert 'amaranth' not in sys.modules, 'amaranth imported'\n"
            "gateware = sorted(name for name in sys.modules if name.startswith('maglog.hw.')"
            " and not name.startswith('maglog.hw.arch'))\n"
            "assert not gateware, gateware\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
