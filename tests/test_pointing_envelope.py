"""The system-level FDIR check (bench.gnc.pointing_envelope) on made-up error histories."""
import numpy as np
import pytest

from bench.gnc.pointing_envelope import PointingEnvelope

LIMIT_RAD = np.deg2rad(5.0)


def _events(errors_deg, persistence_s=10.0, step_s=1.0):
    envelope = PointingEnvelope(LIMIT_RAD, persistence_s)
    for k, error in enumerate(errors_deg):
        envelope.step(k * step_s, None if error is None else np.deg2rad(error))
    return envelope.events


def test_an_error_above_the_limit_for_the_persistence_raises_one_event_at_its_end():
    events = _events([3.0] * 20 + [6.0] * 30)
    assert [(e.alarm_s, e.time_s) for e in events] == [(20.0, 30.0)]
    assert events[0].kind == "fdir_pointing" and events[0].error_deg == pytest.approx(6.0)
    assert "above the 5 deg envelope since 20.000 s" in events[0].describe()


def test_a_shorter_excursion_raises_nothing_and_a_second_one_raises_again():
    assert _events([3.0] * 5 + [6.0] * 9 + [3.0] * 5) == []
    events = _events([6.0] * 12 + [4.0] + [7.0] * 11)
    assert [e.alarm_s for e in events] == [0.0, 13.0]


def test_an_error_at_the_limit_or_missing_is_no_alarm():
    assert _events([5.0] * 30) == []
    assert _events([None] * 30 + [float("nan")] * 30) == []
