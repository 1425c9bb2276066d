"""The estimator's CWH model: closed form = the plant's discretisation, exact mean-motion derivative."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm_frechet

from bench.estimator.motion_model import CwhMotionModel, cwh_discrete_closed_form
from bench.gnc.cwh import params_with_mean_motion, RendezvousParams, cwh_continuous, discretise_zoh

PARAMS = RendezvousParams.from_reference()


@pytest.mark.parametrize("n_steps", [1, 3])
def test_closed_form_equals_the_plant_discretisation(n_steps):
    a_d, b_d = discretise_zoh(*PARAMS.continuous(), n_steps * PARAMS.time_step_s)
    a_cf, b_cf = cwh_discrete_closed_form(PARAMS.mean_motion, PARAMS.mass_kg, n_steps * PARAMS.time_step_s)
    np.testing.assert_allclose(a_cf, a_d, rtol=1e-11, atol=1e-12 * np.abs(a_d).max())
    np.testing.assert_allclose(b_cf, b_d, rtol=1e-11, atol=1e-12 * np.abs(b_d).max())


def test_mean_motion_derivative_matches_the_frechet_derivative_of_expm():
    # Independent check: d/dn expm([[A(n), B], [0, 0]] T) along dA/dn, by scipy's Frechet derivative.
    n, t, m = PARAMS.mean_motion, PARAMS.time_step_s, PARAMS.mass_kg
    a_c, b_c = cwh_continuous(n, m)
    block = np.zeros((9, 9))
    block[:6, :6], block[:6, 6:] = a_c, b_c
    direction = np.zeros((9, 9))
    direction[3, 0], direction[3, 4], direction[4, 3], direction[5, 2] = 6 * n, 2.0, -2.0, -2 * n
    _, d_phi = expm_frechet(block * t, direction * t)
    d_a, d_b = CwhMotionModel(m, t, 1e-9).derivative(n, 1)
    np.testing.assert_allclose(d_a, d_phi[:6, :6], rtol=1e-9, atol=1e-9 * np.abs(d_phi[:6, :6]).max())
    np.testing.assert_allclose(d_b, d_phi[:6, 6:], rtol=1e-9, atol=1e-9 * np.abs(d_phi[:6, 6:]).max())


def test_process_noise_is_full_rank_and_grows_with_the_gap():
    model = CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, 1e-9)
    one, three = model.discrete(PARAMS.mean_motion, 1).process_cov, model.discrete(PARAMS.mean_motion, 3).process_cov
    assert np.linalg.eigvalsh(one).min() > 0
    assert np.trace(three) > 3 * np.trace(one)


def test_params_with_mean_motion_round_trips_and_rejects_nonsense():
    moved = params_with_mean_motion(PARAMS, 1.01 * PARAMS.mean_motion)
    assert moved.mean_motion == pytest.approx(1.01 * PARAMS.mean_motion, rel=1e-12)
    with pytest.raises(ValueError, match="mean_motion_radps must be positive"):
        params_with_mean_motion(PARAMS, -1.0)
    with pytest.raises(ValueError, match="process_noise_psd_m2ps3"):
        CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, -1e-9)
