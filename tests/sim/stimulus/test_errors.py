"""Error-model presets: paper A's Table 1 read as B̂ = P B_e + O, the project's default, an
ideal sensor."""

from __future__ import annotations

import numpy as np
import pytest

from maglog.sim.stimulus.scenario import DEFAULT_ERRORS
from maglog.sim.stimulus import loads_scenario, preset
from maglog.sim.stimulus.errors import PAPER_A_O, PAPER_A_P, c_no, forward, from_forward

from .conftest import SHORT


def test_paper_a_is_table_1():
    model = preset("paper_a")
    a, b = forward(model)
    assert np.abs(a - np.array(PAPER_A_P)).max() < 1e-12
    assert np.abs(b - np.array(PAPER_A_O)).max() < 1e-9
    # Table 1 itself (PAPERS.md, section A).
    assert PAPER_A_P[0] == (1.0117, 0.0079, 0.0184) and PAPER_A_P[2][1] == -0.0166
    assert PAPER_A_O == (1576.1, -604.3794, -41.7471)
    # The physical factors: C_NO of the paper's form, scale factors A's diagonal, C_SI
    # symmetric.
    non_orth = np.array(model.non_orthogonality)
    assert np.allclose(np.linalg.norm(non_orth, axis=1), 1) and non_orth[0, 1:].tolist() == [0, 0]
    assert np.allclose(np.triu(non_orth, 1), 0)
    soft = np.array(model.soft_iron)
    assert np.allclose(soft, soft.T) and model.scale == (1.0117, 1.001, 0.9972)


def test_paper_a_truth_in_the_stimulus():
    truth = loads_scenario(SHORT).build().truth["errors"]
    assert truth["preset"] == "paper_a"
    assert np.abs(np.array(truth["A"]) - PAPER_A_P).max() < 1e-12
    assert np.abs(np.array(truth["b"]) - PAPER_A_O).max() < 1e-9
    k, c = np.array(truth["K"]), np.array(truth["c"])
    # K A is a rotation (the part no scalar calibration sees), c = K b.
    q = k @ np.array(PAPER_A_P)
    assert np.allclose(q @ q.T, np.eye(3), atol=1e-12) and np.linalg.det(q) > 0
    assert np.allclose(c, k @ np.array(PAPER_A_O), atol=1e-9)
    # The recoverable P (K⁻¹) differs from the printed P by that rotation, under 0.03.
    assert 0.005 < np.abs(np.linalg.inv(k) - PAPER_A_P).max() < 0.03


def test_default_and_none_presets():
    default = preset("default")
    assert default.matrix().tolist() == DEFAULT_ERRORS.matrix().tolist()
    assert forward(default)[1].tolist() == forward(DEFAULT_ERRORS)[1].tolist()
    ideal = preset("none", noise=2.0)
    assert np.array_equal(ideal.matrix(), np.eye(3)) and forward(ideal)[1].tolist() == [0, 0, 0]
    assert ideal.noise == 2.0
    with pytest.raises(ValueError, match="Error preset must be one of default, paper_a, none, "
                                         "not 'paper_c'"):
        preset("paper_c")


def test_from_forward_rebuilds_any_matrix_near_identity():
    rng = np.random.default_rng(5)
    for _ in range(5):
        a = np.eye(3) + rng.normal(scale=0.02, size=(3, 3))
        model = from_forward(a, (1.0, 2.0, 3.0))
        assert np.abs(model.matrix() - a).max() < 1e-12
    assert np.allclose(c_no(0, 0, 0), np.eye(3))
    with pytest.raises(ValueError, match="diagonal must be positive"):
        from_forward(-np.eye(3), (0, 0, 0))
