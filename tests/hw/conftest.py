"""Fixtures shared by the gateware tests."""

import pytest

from maglog.sim import formal


@pytest.fixture(scope="module")
def sby_env(tmp_path_factory):
    """The yowasp SymbiYosys tools (see :mod:`maglog.sim.formal`); skips when missing."""
    try:
        return formal.find_tools(tmp_path_factory.mktemp("bin"))
    except formal.FormalToolsMissing as missing:
        pytest.skip(str(missing))
