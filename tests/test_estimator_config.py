"""The [estimator] section: the smoother options load, bad values are named."""
from __future__ import annotations

import pytest

from bench.scenario import ScenarioError, parse_scenario


def test_smoother_options_load():
    s = parse_scenario({"name": "t", "estimator": {
        "mode": "smoother",
        "translation": {"lag_steps": 30, "estimate_mean_motion": True},
        "attitude": {"lag_s": 30.0},
    }, "onboard": {"believed_radius_error": 0.01}})
    assert s.estimator.mode == "smoother"
    assert s.estimator.translation.lag_steps == 30 and s.estimator.translation.estimate_mean_motion
    assert s.estimator.attitude.lag_s == 30.0
    assert s.onboard_params().target_radius_m == pytest.approx(1.01 * s.params().target_radius_m)


@pytest.mark.parametrize("section, field", [
    ({"mode": "kalman"}, "estimator.mode"),
    ({"translation": {"lag_steps": 0}}, "estimator.translation.lag_steps"),
    ({"translation": {"process_noise_psd_m2ps3": -1.0}}, "estimator.translation.process_noise_psd_m2ps3"),
    ({"translation": {"sensor": "lidar"}}, "estimator.translation.sensor"),
    ({"attitude": {"magnetometer_noise_std_t": 0.0}}, "estimator.attitude.magnetometer_noise_std_t"),
    ({"translation": {"lag": 3}}, "lag"),
])
def test_bad_estimator_values_are_named(section, field):
    with pytest.raises(ScenarioError, match=field.replace(".", r"\.")):
        parse_scenario({"name": "t", "estimator": section})


def test_bad_onboard_belief_is_named():
    with pytest.raises(ScenarioError, match=r"onboard\.believed_radius_error"):
        parse_scenario({"name": "t", "onboard": {"believed_radius_error": 0.7}})
