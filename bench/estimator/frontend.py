"""What the estimator runs each plant step, in either mode; shared by its process and bench.sim.

mode "truth": the estimate is the true state (seed 001's full state knowledge).
mode "smoother": gtsam fixed-lag smoothing of the noisy relative position, with the thrust the
flight side commanded over the previous step (and the mean motion, where it is estimated). The
smoother runs on the flight side's beliefs (`OnboardBeliefs`), never on the plant's truth: the
noise level a measurement message carries is not used.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.estimator.beliefs import OnboardBeliefs
from bench.estimator.translation import TranslationSmoother
from bench.scenario import Scenario


@dataclass(frozen=True)
class StateEstimate:
    state_m_mps: np.ndarray
    covariance: np.ndarray | None          # 6x6 SI, None with full state knowledge
    mean_motion_radps: float | None        # the estimated orbit, where it is estimated
    nis: float | None = None               # normalised innovation squared of this step's measurement
    nis_dof: int = 0
    measurement_rejected: bool = False     # the innovation gate rejected this step's measurement


class StateEstimator:
    def __init__(self, scenario: Scenario):
        self.mode = scenario.estimator.mode
        self.smoother = None
        if self.mode == "smoother":
            beliefs = OnboardBeliefs.from_scenario(scenario)
            self.smoother = TranslationSmoother(beliefs.translation_config(scenario.estimator.translation),
                                                scenario.onboard_params())

    @property
    def needs_truth(self) -> bool:
        return self.smoother is None

    @property
    def failed_updates(self) -> int:
        return self.smoother.failed_updates if self.smoother else 0

    def is_late(self, seq: int) -> bool:
        """A sample of this step would be late: a later (or the same) step is already estimated."""
        newest = None if self.smoother is None else self.smoother.newest_seq
        return newest is not None and seq <= newest

    @property
    def sensor(self) -> str | None:
        """The measurement the smoother uses ("relpos" or "range_bearing"); None in truth mode."""
        return None if self.smoother is None else self.smoother.config.sensor

    def step(self, seq: int, sim_time_s: float, *, truth_m_mps=None, position_m=None, range_bearing=None,
             thrust_commanded_n=None) -> StateEstimate | None:
        """The estimate at step `seq`; None only before the smoother's first fix.

        A relative-position fix sensed at an earlier step than the newest one (it arrived late)
        is applied at its sensing step when that is still inside the smoother's window.
        """
        if self.smoother is None:
            return StateEstimate(np.array(truth_m_mps, dtype=float), None, None)
        position = None if position_m is None else np.asarray(position_m)
        rb = None if range_bearing is None else np.asarray(range_bearing)
        if self.is_late(seq):
            result = None
            if position is not None or rb is not None:
                result = self.smoother.add_late_measurement(seq, position, range_bearing=rb)
        else:
            thrust = np.zeros(3) if thrust_commanded_n is None else np.asarray(thrust_commanded_n, dtype=float)
            result = self.smoother.update(seq, sim_time_s, position, thrust, range_bearing=rb)
        if result is None:
            return None
        return StateEstimate(result.state_m_mps, result.covariance, result.mean_motion_radps,
                             result.nis, result.nis_dof, result.measurement_rejected)
