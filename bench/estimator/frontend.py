"""What the estimator runs each plant step, in either mode; shared by its process and bench.sim.

mode "truth": the estimate is the true state (seed 001's full state knowledge).
mode "smoother": gtsam fixed-lag smoothing of the noisy relative position, with the thrust the
flight side commanded over the previous step (and the mean motion, where it is estimated).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.estimator.translation import TranslationSmoother
from bench.scenario import Scenario


@dataclass(frozen=True)
class StateEstimate:
    state_m_mps: np.ndarray
    covariance: np.ndarray | None          # 6x6 SI, None with full state knowledge
    mean_motion_radps: float | None        # the estimated orbit, where it is estimated


class StateEstimator:
    def __init__(self, scenario: Scenario):
        self.mode = scenario.estimator.mode
        self.smoother = (TranslationSmoother(scenario.estimator.translation, scenario.onboard_params())
                         if self.mode == "smoother" else None)

    @property
    def needs_truth(self) -> bool:
        return self.smoother is None

    @property
    def failed_updates(self) -> int:
        return self.smoother.failed_updates if self.smoother else 0

    def step(self, seq: int, sim_time_s: float, *, truth_m_mps=None, position_m=None,
             position_noise_std_m: float | None = None, thrust_commanded_n=None) -> StateEstimate | None:
        """The estimate at step `seq`; None only before the smoother's first fix."""
        if self.smoother is None:
            return StateEstimate(np.array(truth_m_mps, dtype=float), None, None)
        thrust = np.zeros(3) if thrust_commanded_n is None else np.asarray(thrust_commanded_n, dtype=float)
        result = self.smoother.update(seq, sim_time_s, None if position_m is None else np.asarray(position_m),
                                      thrust, position_noise_std_m)
        if result is None:
            return None
        return StateEstimate(result.state_m_mps, result.covariance, result.mean_motion_radps)
