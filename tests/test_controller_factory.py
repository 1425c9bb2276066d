"""build_controller: the controller process's only entry point into bench.controller."""
import numpy as np
import pytest

from bench.config.controller import ControllerConfig
from bench.controller.factory import build_controller
from bench.gnc.cwh import RendezvousParams
from bench.gnc.lqr import dlqr


@pytest.fixture(scope="module")
def params():
    return RendezvousParams.from_reference()


def test_lqr_from_config_uses_the_configured_weights(params):
    cfg = ControllerConfig(type="lqr", q_diag=[94.0, 0.1579, 500.0, 0.01, 0.1, 0.01], r_diag=[1.0, 2.0, 1.0])
    ctrl = build_controller(cfg, params)
    k, _ = dlqr(params.scaled.A, params.scaled.B, np.diag(cfg.q_diag), np.diag(cfg.r_diag))
    x = params.scaled.to_scaled(params.initial_state_m_mps("A"))
    u, info = ctrl.eval(x)
    np.testing.assert_allclose(u, k @ x, rtol=1e-12)
    assert info["ctrl_feas"] and info["status"] == "solved"
