"""In-process closed loop for the estimator tests: CWH truth, noisy fixes, smoother, LQR.

Not the bench's process pipeline (that is bench/sim.py and the nodes): the smallest loop that
shows what the smoother does to the rendezvous of seed 003 (LQR from initial condition A).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.translation import TranslationSmoother
from bench.gnc.cwh import params_with_mean_motion, RendezvousParams
from bench.gnc.lqr import LQR

# The tuned weights of the default scenario (bench/scenarios/rendezvous_lqr.toml).
Q_DIAG = [94.0, 0.1579, 500.0, 0.01, 0.1, 0.01]
# Re-solve the LQR when the estimated mean motion has moved this much (relative) since the last
# gain: the DARE costs ~1 ms and the gain changes smoothly with n, so a small dead band suffices.
GAIN_REFRESH_REL = 1e-3


@dataclass
class LoopResult:
    truth_m_mps: np.ndarray        # (N+1, 6), x_0 .. x_N
    estimate_m_mps: np.ndarray     # (N, 6), estimate at steps 0 .. N-1
    covariance: np.ndarray         # (N, 6, 6)
    thrust_n: np.ndarray           # (N, 3)
    mean_motion_radps: np.ndarray  # (N,), the controller's model at each step
    gain_updates: int
    failed_updates: int

    def terminal_errors(self) -> tuple[float, float]:
        final = self.truth_m_mps[-1]
        return float(np.linalg.norm(final[:3])), float(np.linalg.norm(final[3:]))


def lqr_for(params: RendezvousParams) -> LQR:
    scaled = params.scaled
    return LQR(np.diag(Q_DIAG), np.eye(3), scaled.A, scaled.B)


def run_closed_loop(true_params: RendezvousParams, config: TranslationSmootherConfig,
                    noise_std_m: float, seed: int, steps: int | None = None,
                    believed_radius_error: float = 0.0) -> LoopResult:
    """believed_radius_error: the flight side's orbit radius is the truth's times (1 + this)."""
    steps = true_params.n_steps if steps is None else steps
    rng = np.random.default_rng(seed)
    a_true, b_true = true_params.discrete_si()
    smoother = TranslationSmoother(config, true_params.with_radius_error(believed_radius_error))
    model_params = smoother.believed_params      # the controller starts from the believed orbit
    controller, gain_n = lqr_for(model_params), model_params.mean_motion
    gain_updates = 0

    x = true_params.initial_state_m_mps("A")
    truth, est, cov, thrust, n_hist = [x], [], [], [], []
    u = np.zeros(3)
    for k in range(steps):
        fix = x[:3] + rng.normal(0.0, noise_std_m, 3)
        r = smoother.update(k, k * true_params.time_step_s, fix, u, noise_std_m)
        if r.mean_motion_radps is not None and abs(r.mean_motion_radps / gain_n - 1.0) > GAIN_REFRESH_REL:
            model_params = params_with_mean_motion(true_params, r.mean_motion_radps)
            controller, gain_n = lqr_for(model_params), r.mean_motion_radps
            gain_updates += 1
        u_cmd, _ = controller.eval(model_params.scaled.to_scaled(r.state_m_mps))
        u = np.clip(u_cmd, -true_params.max_abs_thrust_n, true_params.max_abs_thrust_n)
        x = a_true @ x + b_true @ u
        truth.append(x); est.append(r.state_m_mps); cov.append(r.covariance); thrust.append(u); n_hist.append(gain_n)
    return LoopResult(np.array(truth), np.array(est), np.array(cov), np.array(thrust), np.array(n_hist),
                      gain_updates, smoother.failed_updates)
