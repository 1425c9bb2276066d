"""Outlier Monte Carlo of the translational smoother (issue 27): isolated outliers plus a one-sided
burst of consecutive 20-sigma fixes, judged against the clean run and an oracle that drops the bad
fixes. Shared by tests/test_estimator_outliers.py (a few runs) and benchmarks/bench_outliers.py (30).

Each run: truth from initial condition A with a velocity drawn from the smoother's prior, random
thrust, and (process-noise regime) a white acceleration of the believed spectral density; a fix
every step, 600 s apart. Bad fixes: 20 sigma in the whitened measurement space (relative position:
200 m at 10 m noise; range/bearing: any mix of range and angles), a random direction for each
isolated one, one direction for the whole burst (one-sided: the case that walks a gate open).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
from scipy.stats import chi2

from bench.config.estimator import TranslationSmootherConfig
from bench.estimator.factors import range_bearing
from bench.estimator.motion_model import CwhMotionModel
from bench.estimator.translation import TranslationSmoother
from bench.gnc.cwh import RendezvousParams
from bench.scenario import load_scenario

PARAMS = RendezvousParams.from_reference()
STEPS = 40
OUTLIER_SIGMA = 20.0
ISOLATED_STEPS = (6, 12, 32)
BURST_STEPS = tuple(range(18, 23))            # five consecutive bad fixes
BAD_STEPS = frozenset(ISOLATED_STEPS + BURST_STEPS)
RECOVERY_FIXES = 5                            # NEES back inside its bounds this many fixes after the burst
RMS_FROM_STEP = 3                             # before, the 10 m/s initial velocity prior dominates
RMS_FACTOR = 1.5
DEFAULT_SCENARIO = Path(__file__).resolve().parents[1] / "bench" / "scenarios" / "rendezvous_smoother.toml"


def default_smoother_config() -> TranslationSmootherConfig:
    """The estimator configuration of the built-in smoother scenario, as the bench flies it."""
    scenario = load_scenario(DEFAULT_SCENARIO)
    assert scenario.estimator.mode == "smoother"
    return scenario.estimator.translation


def regime_config(config: TranslationSmootherConfig, sensor: str, process_noise_psd_m2ps3: float,
                  **overrides) -> TranslationSmootherConfig:
    return msgspec.structs.replace(config, sensor=sensor, process_noise_psd_m2ps3=process_noise_psd_m2ps3, **overrides)


def ungated(config: TranslationSmootherConfig) -> TranslationSmootherConfig:
    """Least squares, no protection: the clean and oracle references."""
    return msgspec.structs.replace(config, gate_probability=None, robust_loss="none")


@dataclass
class Run:
    error: np.ndarray        # (STEPS, 6) estimate - truth
    nees: np.ndarray         # (STEPS,)
    rejected: np.ndarray     # (STEPS,) bool
    reacquisitions: int


@dataclass
class Data:
    truth: np.ndarray        # (STEPS, 6)
    thrust: np.ndarray       # (STEPS, 3): thrust held from step k-1 to k (zero at 0)
    clean: list              # per step: the clean fix (relpos (3,) or range/bearing (3,))
    bad: list                # the same with the bad fixes


def draw(seed: int, config: TranslationSmootherConfig) -> Data:
    smoother = TranslationSmoother(config, PARAMS)     # for its believed noise levels only
    model = CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, config.process_noise_psd_m2ps3 or 0.0).discrete(
        PARAMS.mean_motion)
    rng = np.random.default_rng(seed)
    x = PARAMS.initial_state_m_mps("A").copy()
    x[3:] = rng.normal(0.0, config.initial_velocity_std_mps, 3)
    if config.sensor == "relpos":
        sigmas = np.full(3, smoother.position_noise_std_m)
        measure = lambda state: state[:3]    # noqa: E731
    else:
        sigmas = np.array([smoother.range_noise_std_m, smoother.bearing_noise_std_rad, smoother.bearing_noise_std_rad])
        measure = lambda state: range_bearing(state[:3])    # noqa: E731
    burst_direction = _unit(rng)
    truth, thrusts, clean, bad = [], [], [], []
    thrust = np.zeros(3)
    for k in range(STEPS):
        truth.append(x.copy())
        thrusts.append(thrust.copy())
        z = measure(x) + rng.normal(0.0, 1.0, 3) * sigmas
        clean.append(z)
        direction = burst_direction if k in BURST_STEPS else _unit(rng)
        bad.append(z + OUTLIER_SIGMA * direction * sigmas if k in BAD_STEPS else z)
        thrust = rng.uniform(-0.5, 0.5, 3)
        w = rng.multivariate_normal(np.zeros(6), model.process_cov) if config.process_noise_psd_m2ps3 else 0.0
        x = model.transition @ x + model.input_matrix @ thrust + w
    return Data(np.array(truth), np.array(thrusts), clean, bad)


def fly(config: TranslationSmootherConfig, data: Data, fixes: str) -> Run:
    """fixes: "bad" (with outliers), "clean", or "oracle" (bad fixes dropped)."""
    smoother = TranslationSmoother(config, PARAMS)
    errors, nees, rejected = [], [], []
    for k in range(STEPS):
        z = data.clean[k] if fixes == "clean" else None if (fixes == "oracle" and k in BAD_STEPS) else data.bad[k]
        if config.sensor == "relpos":
            r = smoother.update(k, 600.0 * k, z, data.thrust[k])
        else:
            r = smoother.update(k, 600.0 * k, None, data.thrust[k], range_bearing=z)
        e = r.state_m_mps - data.truth[k]
        errors.append(e)
        nees.append(float(e @ np.linalg.solve(r.covariance, e)))
        rejected.append(r.measurement_rejected)
    return Run(np.array(errors), np.array(nees), np.array(rejected), smoother.reacquisitions)


@dataclass
class Verdict:
    rms_m: float               # position RMS of the protected smoother (steps >= RMS_FROM_STEP)
    clean_rms_m: float
    oracle_rms_m: float
    outliers_used: int         # bad fixes the smoother used
    good_rejected_after_burst: int
    good_rejected: int
    reacquisitions: int
    nees_after: float          # mean over runs of the time-averaged NEES from RECOVERY_FIXES after the burst
    nees_bounds: tuple[float, float]
    worst_step_nees: float     # the largest 30-run mean NEES of one step from RECOVERY_FIXES after the burst
    step_nees_upper: float     # its 95 % upper bound

    @property
    def rms_ratio(self) -> float:
        return self.rms_m / max(self.clean_rms_m, self.oracle_rms_m)

    @property
    def passed(self) -> bool:
        low, high = self.nees_bounds
        return (self.rms_ratio <= RMS_FACTOR and self.good_rejected_after_burst == 0
                and low <= self.nees_after <= high)


def monte_carlo(config: TranslationSmootherConfig, runs: int, seed0: int = 27_000) -> Verdict:
    protected, clean, oracle = [], [], []
    for i in range(runs):
        data = draw(seed0 + i, config)
        protected.append(fly(config, data, "bad"))
        clean.append(fly(ungated(config), data, "clean"))
        oracle.append(fly(ungated(config), data, "oracle"))
    after = BURST_STEPS[-1] + 1
    from_step = after + RECOVERY_FIXES
    bad = np.array([k in BAD_STEPS for k in range(STEPS)])
    rejected = np.array([r.rejected for r in protected])
    nees = np.array([r.nees for r in protected])
    time_averaged = nees[:, from_step:].mean(axis=1)
    bounds = tuple(chi2.ppf([0.025, 0.975], runs * 6) / runs)
    return Verdict(
        rms_m=_position_rms(protected), clean_rms_m=_position_rms(clean), oracle_rms_m=_position_rms(oracle),
        outliers_used=int((~rejected[:, bad]).sum()),
        good_rejected_after_burst=int(rejected[:, after:][:, ~bad[after:]].sum()),
        good_rejected=int(rejected[:, ~bad].sum()),
        reacquisitions=sum(r.reacquisitions for r in protected),
        nees_after=float(time_averaged.mean()), nees_bounds=bounds,
        worst_step_nees=float(nees[:, from_step:].mean(axis=0).max()),
        step_nees_upper=float(chi2.ppf(0.975, runs * 6) / runs),
    )


def _position_rms(runs: list[Run]) -> float:
    errors = np.concatenate([r.error[RMS_FROM_STEP:, :3] for r in runs])
    return float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)
