"""What the flight side believes about the world, separately from what the plant simulates.

The scenario's [onboard] section states it (bench.scenario.OnboardConfig); what it leaves unset
is the plant's truth (orbit radius, sensor noise, no process noise on the linear CWH): a
well-tuned flight side. A belief that differs is a scenario: the estimator then runs mistuned
while the plant's truth is unchanged. [estimator.translation] may override a belief for the
estimator alone (`position_noise_std_m`, `range_noise_std_m`, `bearing_noise_std_rad`,
`process_noise_psd_m2ps3`), e.g. to detune the estimator but not the controller.
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec

from bench.config.estimator import TranslationSmootherConfig


@dataclass(frozen=True)
class OnboardBeliefs:
    target_radius_m: float            # believed orbit radius of the target (sets the mean motion)
    relpos_noise_std_m: float         # believed relative-position sensor noise, 1 sigma per axis
    process_noise_psd_m2ps3: float    # believed white acceleration on the chaser (0: none, as the CWH plant)
    range_noise_std_m: float          # believed range/bearing sensor noise
    bearing_noise_std_rad: float

    @classmethod
    def from_scenario(cls, scenario) -> "OnboardBeliefs":
        plant, onboard, translation = scenario.plant, scenario.onboard, scenario.estimator.translation
        rb = plant.range_bearing_sensor
        return cls(
            target_radius_m=scenario.onboard_params().target_radius_m,
            relpos_noise_std_m=_belief(translation.position_noise_std_m, onboard.relpos_noise_std_m,
                                       plant.relpos_sensor.noise_std_m),
            process_noise_psd_m2ps3=_belief(translation.process_noise_psd_m2ps3, onboard.process_noise_psd_m2ps3, 0.0),
            range_noise_std_m=_belief(translation.range_noise_std_m, onboard.range_noise_std_m, rb.range_noise_std_m),
            bearing_noise_std_rad=_belief(translation.bearing_noise_std_rad, onboard.bearing_noise_std_rad,
                                          rb.bearing_noise_std_rad),
        )

    def translation_config(self, config: TranslationSmootherConfig) -> TranslationSmootherConfig:
        """The smoother's configuration with these noise beliefs in it (the orbit radius goes in
        through `Scenario.onboard_params()`)."""
        return msgspec.structs.replace(
            config,
            position_noise_std_m=self.relpos_noise_std_m,
            process_noise_psd_m2ps3=self.process_noise_psd_m2ps3,
            range_noise_std_m=self.range_noise_std_m,
            bearing_noise_std_rad=self.bearing_noise_std_rad,
        )


def _belief(estimator_only: float | None, onboard: float | None, truth: float) -> float:
    """The estimator's own override, else the flight side's stated belief, else the plant's truth."""
    if estimator_only is not None:
        return estimator_only
    return truth if onboard is None else onboard
