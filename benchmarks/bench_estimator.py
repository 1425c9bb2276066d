"""Per-update time of the estimators: median and p99, against a baseline measured in the same run.

Baseline: the reference Kalman filter (numpy predict + correct) on the same translational data,
so a slow machine or a busy neighbour shows up in both columns and the ratio stays meaningful.
Run: .venv/bin/python benchmarks/bench_estimator.py
Targets (issue 4, this 2-core machine): translational p99 < 0.5 ms, attitude p99 < 1 ms.
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
from bench.estimator.config import AttitudeSmootherConfig, TranslationSmootherConfig  # noqa: E402
from bench.estimator.factors import range_bearing  # noqa: E402
from bench.estimator.motion_model import CwhMotionModel  # noqa: E402
from bench.estimator.translation import TranslationSmoother  # noqa: E402
from bench.plant.attitude import AttitudeSensorSpec, AttitudeSimulation  # noqa: E402
from bench.gnc.cwh import RendezvousParams  # noqa: E402

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
    rb_std = TranslationSmootherConfig()
    rb_std = np.array([rb_std.range_noise_std_m, rb_std.bearing_noise_std_rad, rb_std.bearing_noise_std_rad])
    range_bearings = np.array([range_bearing(x[:3]) for x in xs]) + rng.normal(0.0, 1.0, (STEPS, 3)) * rb_std
    return fixes, range_bearings, np.array(thrusts)


def time_kalman(fixes, thrusts) -> Timings:
    config = TranslationSmootherConfig()
    m = CwhMotionModel(PARAMS.mass_kg, PARAMS.time_step_s, config.process_noise_psd_m2ps3).discrete(PARAMS.mean_motion)
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


def time_attitude(seconds: float = 300.0) -> tuple[Timings, Timings]:
    spec = AttitudeSensorSpec()
    sim = AttitudeSimulation(np.diag([0.03, 0.04, 0.02]), Rotation.random(random_state=2).as_quat(scalar_first=True),
                             [0.01, -0.02, 0.015], spec, seed=2)
    samples = [sim.step() for _ in range(int(seconds * spec.gyro_rate_hz))]
    keyframes, gyro = Timings(), Timings()
    for _ in range(REPEATS):
        smoother, keyframe = AttitudeSmoother(AttitudeSmootherConfig()), 0
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
    rows = [
        ("Kalman filter (numpy, baseline)", time_kalman(fixes, thrusts)),
        ("translation smoother, lag 20", time_translation(TranslationSmootherConfig(), fixes, range_bearings, thrusts)),
        ("translation + mean motion, lag 20", time_translation(
            TranslationSmootherConfig(estimate_mean_motion=True), fixes, range_bearings, thrusts, believed_radius_error=0.01)),
        ("translation, range/bearing, lag 20", time_translation(
            TranslationSmootherConfig(sensor="range_bearing"), fixes, range_bearings, thrusts)),
    ]
    keyframes, gyro = time_attitude()
    rows += [("attitude smoother keyframe, lag 20 s", keyframes), ("attitude gyro sample (preintegrate)", gyro)]

    base = rows[0][1].wall_ms()
    base_median, base_p99 = np.median(base), np.percentile(base, 99)
    print(f"estimator per-update time, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    print(f"{'':38s} {'n':>6s} {'wall median':>11s} {'wall p99':>9s} {'cpu median':>10s} {'cpu p99':>8s}"
          f" {'median/KF':>9s} {'p99/KF':>7s}  (ms)")
    for name, t in rows:
        wall, cpu = t.wall_ms(), t.cpu_ms()
        med, p99 = np.median(wall), np.percentile(wall, 99)
        print(f"{name:38s} {wall.size:6d} {med:11.3f} {p99:9.3f} {np.median(cpu):10.3f} {np.percentile(cpu, 99):8.3f}"
              f" {med / base_median:9.1f} {p99 / base_p99:7.1f}")


if __name__ == "__main__":
    main()
