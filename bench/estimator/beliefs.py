"""What the flight side believes about the world, separately from what the plant simulates.

The plant's truth (orbit radius, sensor noise, no process noise on the linear CWH) is the default
belief: a well-tuned flight side. A scenario may set a different belief, and then the estimator
runs mistuned while the plant's truth is unchanged: that is how a mistuned flight side is tested.

Until the scenario's `[onboard]` section exists (issue 9), the beliefs are read from the
`[estimator.translation]` fields that state them (`position_noise_std_m`,
`range_noise_std_m`, `bearing_noise_std_rad`, `process_noise_psd_m2ps3`, `believed_radius_error`);
unset ones take the plant's value.
"""
from __future__ import annotations

from dataclasses import dataclass

import msgspec

from bench.estimator.config import TranslationSmootherConfig


@dataclass(frozen=True)
class OnboardBeliefs:
    target_radius_m: float            # believed orbit radius of the target (sets the mean motion)
    relpos_noise_std_m: float         # believed relative-position sensor noise, 1 sigma per axis
    process_noise_psd_m2ps3: float    # believed white acceleration on the chaser (0: none, as the CWH plant)
    range_noise_std_m: float          # believed range/bearing sensor noise
    bearing_noise_std_rad: float

    @classmethod
    def from_scenario(cls, scenario) -> "OnboardBeliefs":
        plant, translation = scenario.plant, scenario.estimator.translation
        return cls(
            target_radius_m=plant.target_radius_m * (1.0 + translation.believed_radius_error),
            relpos_noise_std_m=_belief(translation.position_noise_std_m, plant.relpos_sensor.noise_std_m),
            process_noise_psd_m2ps3=translation.process_noise_psd_m2ps3,
            range_noise_std_m=_belief(translation.range_noise_std_m, plant.range_bearing_sensor.range_noise_std_m),
            bearing_noise_std_rad=_belief(translation.bearing_noise_std_rad,
                                          plant.range_bearing_sensor.bearing_noise_std_rad),
        )

    def translation_config(self, config: TranslationSmootherConfig, true_radius_m: float) -> TranslationSmootherConfig:
        """The smoother's configuration with these beliefs in it (the smoother reads nothing else)."""
        return msgspec.structs.replace(
            config,
            position_noise_std_m=self.relpos_noise_std_m,
            range_noise_std_m=self.range_noise_std_m,
            bearing_noise_std_rad=self.bearing_noise_std_rad,
            process_noise_psd_m2ps3=self.process_noise_psd_m2ps3,
            believed_radius_error=self.target_radius_m / true_radius_m - 1.0,
        )


def _belief(stated: float | None, truth: float) -> float:
    """The belief a scenario states, or else the plant's truth."""
    return truth if stated is None else stated
