"""Shared builds of the model tests."""

from __future__ import annotations

import pytest

from maglog.sim.stimulus import load_scenario


@pytest.fixture(scope="session")
def default_built():
    """The built-in default scenario, built once per session (about 15 s)."""
    return load_scenario().build()
