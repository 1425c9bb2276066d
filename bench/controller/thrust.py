"""The translational control law as the controller process sees it: SI in, SI out.

The seed's controllers work on the scaled state (Mm, km/s); the scaling stays inside here.
"""
from __future__ import annotations

import numpy as np

from bench.controller.factory import build_controller
from bench.scenario import Scenario


class ThrustLaw:
    def __init__(self, scenario: Scenario):
        self.params = scenario.params()
        self.scaled = self.params.scaled
        self.controller = build_controller(scenario.controller, self.params)

    def command(self, state_m_mps: np.ndarray) -> tuple[np.ndarray, dict]:
        u_n, info = self.controller.eval(self.scaled.to_scaled(state_m_mps))
        return np.asarray(u_n, dtype=float).reshape(3), info
