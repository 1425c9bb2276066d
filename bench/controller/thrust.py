"""The translational control law as the controller process sees it: SI in, SI out.

The seed's controllers work on the scaled state (Mm, km/s); the scaling stays inside here. Where
the estimator estimates the orbit (seed 001's uncertain orbit radius), the law is rebuilt on the
estimated mean motion, so the controller's A and B are the estimated ones.
"""
from __future__ import annotations

from functools import partial

import numpy as np

from bench.controller.factory import build_controller
from bench.gnc.cwh import params_with_mean_motion, RendezvousParams
from bench.scenario import Scenario

# Rebuild the controller when the estimated mean motion has moved this much (relative) since the
# model it was built on: the gains vary smoothly with n, so a small dead band costs nothing.
MODEL_REFRESH_REL = 1e-3


class ThrustLaw:
    """in_process=False: only the factory is kept (`self.factory`); the law is built elsewhere
    (a solver worker), so a model update never builds a terminal set in a control cycle."""

    def __init__(self, scenario: Scenario, in_process: bool = True):
        self.in_process = in_process
        self.config = scenario.controller
        self.model_updates = 0
        self._build(scenario.onboard_params())   # the flight side knows only the believed orbit

    def _build(self, params: RendezvousParams) -> None:
        self.params = params
        self.scaled = params.scaled
        previous = getattr(self, "controller", None)
        self.factory = partial(build_controller, self.config, params)
        self.controller = self.factory() if self.in_process else None
        if previous is not None and self.controller is not None and hasattr(self.controller, "continue_from"):
            # A law with a clock and a plan (LQT) keeps them across a model update. (In a solver
            # worker the law is rebuilt there from the factory and starts its plan afresh.)
            self.controller.continue_from(previous)

    def update_model(self, mean_motion_radps: float | None) -> bool:
        """Rebuild on an estimated mean motion that moved past the dead band; True if rebuilt."""
        if mean_motion_radps is None or abs(mean_motion_radps / self.params.mean_motion - 1.0) <= MODEL_REFRESH_REL:
            return False
        self._build(params_with_mean_motion(self.params, mean_motion_radps))
        self.model_updates += 1
        return True

    def to_scaled(self, state_m_mps: np.ndarray) -> np.ndarray:
        return self.scaled.to_scaled(np.asarray(state_m_mps, dtype=float))

    def command(self, state_m_mps: np.ndarray, mean_motion_radps: float | None = None) -> tuple[np.ndarray, dict]:
        self.update_model(mean_motion_radps)
        u_n, info = self.controller.eval(self.to_scaled(state_m_mps))
        return np.asarray(u_n, dtype=float).reshape(3), info
