"""Per-update time of the estimators: CPU and wall time percentiles, against a baseline measured
in the same run.

CPU time (this thread's) is the estimator's own cost; wall time adds whatever the scheduler gave
to other processes, so on a shared machine the two are reported separately. Baseline: the
reference Kalman filter (numpy predict + correct) on the same translational data, so a slow
machine or a busy neighbour shows up in both and the ratios stay meaningful.
Run: PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_estimator.py
Target (issue 16): p99 CPU time <= 0.5 ms per update for every mode; see docs/estimation.md.
"""
from __future__ import annotations

import os

# One BLAS thread, as each bench process should run: on this 2-core machine shared with other
# processes, OpenBLAS's worker threads turn a 9x9 scipy expm or 3x3 triangular solve from
# microseconds into ~10 ms (measured). Must be set before numpy/scipy load their BLAS.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from bench.estimator import kalman  # noqa: E402
from bench.estimator.attitude import AttitudeSmoother  # noqa: E402
from bench.config.estimator import AttitudeSmootherConfig, TranslationSmootherConfig  # noqa: E402
from bench.estimator.factors import range_bearing  # noqa: E402
from bench.estimator.motion_model import CwhMotionModel  # noqa: E402
from bench.estimator.translation import TranslationSmoother  # noqa: E402
from bench.plant.attitude import AttitudeSensorSpec, AttitudeSimulation  # noqa: E402
from bench.gnc.cwh import RendezvousParams  # noqa: E402
from bench.config.plant import RangeBearingSensorConfig  # noqa: E402

PARAMS = RendezvousParams.from_reference()


class Timings:
    """Wall time (what the loop waits for) and this thread's CPU time (the estimator's own cost,
    without the time the scheduler gave to other processes) of each timed call, in ms."""

    def __init__(self):
        self.wall_ns: list[int] = []
        self.cpu_ns: list[int] = []

    def __call__(self, fn, *args, record: bool = True, **kwargs):
        w0, c0 = time.perf_counter_ns(), time.thread_time_ns()
        out = fn(*args, **kwargs)
        if record:
            self.cpu_ns.append(time.thread_time_ns() - c0)
            self.wall_ns.append(time.perf_counter_ns() - w0)
        return out

    def percentiles(self, which: str) -> tuple[float, float, float]:
        values = self.wall_ms() if which == "wall" else self.cpu_ms()
        return tuple(float(v) for v in np.percentile(values, [50, 90, 99]))

    def wall_ms(self) -> np.ndarray:
        return np.array(self.wall_ns) * 1e-6

    def cpu_ms(self) -> np.ndarray:
        return np.array(self.cpu_ns) * 1e-6
STEPS = 288          # the reference rendezvous: 2 days of 600 s steps
REPEATS = 5
WARMUP = 5           # first updates of each run (smoother creation, caches) are not counted
NOISE_M = 10.0


def translation_data(seed: int = 1):
    """An open-loop CWH trajectory from A with random thrust, its noisy fixes and range/bearings."""
    rng = np.random.default_rng(seed)
    a, b = PARAMS.discrete_si()
    x, xs, thrusts = PARAMS.initial_state_m_mps("A"), [], []
    for _ in range(STEPS):
        xs.append(x)
        u = rng.uniform(-0.2, 0.2, 3)
        thrusts.append(u)
        x = a @ x + b @ u
    xs = np.array(xs)
    fixes = xs[:, :3] + rng.normal(0.0, NOISE_M, (STEPS, 3))
    rb = RangeBearingSensorConfig()
    rb_std = np.array([rb.range_noise_std_m, rb.bearing_noise_std_rad, rb.bearing_noise_std_rad])
    range_bearings = np.array([range_bearing(x[:3]) for x in xs]) + rng.normal(0.0, 1.0, (STEPS, 3)) * rb_std
    return fixes, range_bearings, np.array(thrusts)


def time_kalman(fixes, thrusts) -> Timings:
    config = TranslationSmootherConfig()
    m = CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, config.process_noise_psd_m2ps3 or 0.0).discrete(PARAMS.mean_motion)
    r = np.eye(3) * NOISE_M**2

    def step(belief, k):
        belief = kalman.predict(belief, m.transition, m.input_matrix, thrusts[k - 1], m.process_cov)
        return kalman.correct(belief, fixes[k], kalman.POSITION_MATRIX, r)

    timings = Timings()
    for _ in range(REPEATS):
        belief = kalman.initial_belief_from_position(fixes[0], NOISE_M, config.initial_velocity_std_mps)
        for k in range(1, STEPS):
            belief = timings(step, belief, k)
    return timings


def time_translation(config: TranslationSmootherConfig, fixes, range_bearings, thrusts,
                     believed_radius_error: float = 0.0) -> Timings:
    timings = Timings()
    for _ in range(REPEATS):
        smoother = TranslationSmoother(config, PARAMS.with_radius_error(believed_radius_error))
        for k in range(STEPS):
            u = thrusts[k - 1] if k else np.zeros(3)
            if config.sensor == "relpos":
                timings(smoother.update, k, 600.0 * k, fixes[k], u, NOISE_M, record=k >= WARMUP)
            else:
                timings(smoother.update, k, 600.0 * k, None, u, range_bearing=range_bearings[k], record=k >= WARMUP)
        assert smoother.failed_updates == 0
    return timings


def time_attitude(seconds: float = 300.0, config: AttitudeSmootherConfig | None = None,
                  spec: AttitudeSensorSpec | None = None) -> tuple[Timings, Timings]:
    config = config or AttitudeSmootherConfig()
    spec = spec or AttitudeSensorSpec()
    sim = AttitudeSimulation(np.diag([0.03, 0.04, 0.02]), Rotation.random(random_state=2).as_quat(scalar_first=True),
                             [0.01, -0.02, 0.015], spec, seed=2)
    samples = [sim.step() for _ in range(int(seconds * spec.gyro_rate_hz))]
    keyframes, gyro = Timings(), Timings()
    for _ in range(REPEATS):
        smoother, keyframe = AttitudeSmoother(config), 0
        for s in samples:
            gyro(smoother.add_gyro, s.gyro_radps, sim.dt_s)
            if s.magnetometer_t is None and s.star_tracker_wxyz is None:
                continue
            keyframe += 1
            keyframes(smoother.update, keyframe, s.time_s, s.magnetometer_t, s.field_inertial_t, s.star_tracker_wxyz,
                      record=keyframe > WARMUP)
        assert smoother.failed_updates == 0
    return keyframes, gyro


def main() -> None:
    fixes, range_bearings, thrusts = translation_data()
    joint = dict(estimate_mean_motion=True)
    # Joint modes: the flight side believes the orbit radius 1 % off.
    translation_modes = [
        ("translation smoother, lag 20", TranslationSmootherConfig()),
        ("  + chi-square gate", TranslationSmootherConfig(gate_probability=0.9999)),
        ("  + Huber loss", TranslationSmootherConfig(robust_loss="huber")),
        ("translation + mean motion, lag 20", TranslationSmootherConfig(**joint)),
        ("translation, range/bearing, lag 20", TranslationSmootherConfig(sensor="range_bearing")),
        ("  relinearised every update (old)", TranslationSmootherConfig(
            sensor="range_bearing", range_bearing_linearisation="every_update")),
        ("range/bearing + mean motion, lag 20", TranslationSmootherConfig(sensor="range_bearing", **joint)),
    ]
    rows = [("Kalman filter (numpy, baseline)", time_kalman(fixes, thrusts))]
    rows += [(name, time_translation(config, fixes, range_bearings, thrusts, 0.01 if config.estimate_mean_motion else 0.0))
             for name, config in translation_modes]
    keyframes, gyro = time_attitude()
    calibrated, _ = time_attitude(config=AttitudeSmootherConfig(estimate_magnetometer_calibration=True))
    rows += [("attitude smoother keyframe, lag 20 s", keyframes),
             ("  + magnetometer calibration", calibrated),
             ("attitude gyro sample (preintegrate)", gyro)]

    base_cpu, base_wall = rows[0][1].percentiles("cpu"), rows[0][1].percentiles("wall")
    print(f"estimator per-update time (ms), {os.cpu_count()} cores, load average "
          f"{' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    print(f"{'':38s} {'n':>6s} | {'CPU p50':>8s} {'p90':>7s} {'p99':>7s} {'p50/KF':>7s} {'p99/KF':>7s} |"
          f" {'wall p50':>8s} {'p90':>7s} {'p99':>7s} {'p50/KF':>7s} {'p99/KF':>7s}")
    for name, t in rows:
        cpu, wall = t.percentiles("cpu"), t.percentiles("wall")
        print(f"{name:38s} {len(t.cpu_ns):6d} | {cpu[0]:8.3f} {cpu[1]:7.3f} {cpu[2]:7.3f} {cpu[0] / base_cpu[0]:7.1f}"
              f" {cpu[2] / base_cpu[2]:7.1f} | {wall[0]:8.3f} {wall[1]:7.3f} {wall[2]:7.3f} {wall[0] / base_wall[0]:7.1f}"
              f" {wall[2] / base_wall[2]:7.1f}")


if __name__ == "__main__":
    main()
