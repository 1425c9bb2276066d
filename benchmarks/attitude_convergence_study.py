"""Which sliding-mode gains make the magnetorquer-only loop converge (issue 11), measured on the
bench's own in-process loop (`bench.sim.simulate_attitude_in_process`: IGRF, gravity gradient,
residual dipole, the board's rounding and saturation, the scenario's law through the least-norm
dipole map). Prints, per case: the pointing error at 13 instants, its final value, its maximum over
the last orbit, and the minimum of the continuous rotation angle (a slew from 200 deg went the short
way while it stays above 180).

    PYTHONPATH=$PWD python benchmarks/attitude_convergence_study.py attitude_slew 3 sm,0.001,0.005 pd,1e-6,5e-4
    ... attitude_pointing 2 --truth --rate-hz 1 sm,0.002,0.25

A case is `sm,lambda,k` (sliding mode) or `pd,kp,kd`; the second argument is the duration in orbits.
"""
import argparse
import copy
import time
import tomllib
from importlib import resources

import numpy as np

from bench.report.attitude_metrics import continuous_rotation_angle_deg, pointing_error_deg
from bench.scenario import parse_scenario
from bench.sim import simulate_attitude_in_process

ORBIT_S = 5670.0     # 500 km circular


def case_scenario(name: str, orbits: float, spec: str, truth: bool, rate_hz: float | None, dither: bool = False,
                  compensation_am2: float | None = None, no_gravity_gradient: bool = False):
    data = tomllib.loads(resources.files("bench.scenarios").joinpath(f"{name}.toml").read_text())
    data = copy.deepcopy(data)
    data["attitude"]["duration_s"] = round(orbits * ORBIT_S)
    if rate_hz is not None:
        sensors = data["attitude"].setdefault("sensors", {})
        sensors["gyro_rate_hz"] = rate_hz
        sensors["magnetometer_period_s"] = max(1.0, 1.0 / rate_hz)
        sensors["star_tracker_period_s"] = max(1.0, 1.0 / rate_hz)
    if truth:
        data["estimator"] = {"mode": "truth"}
    kind, a, b = spec.split(",")
    control = data["attitude_control"]
    control["quantisation_error_feedback"] = dither
    if compensation_am2 is not None:
        control["residual_dipole_compensation_am2"] = [compensation_am2, 0.0, 0.0]
    if no_gravity_gradient:
        data["attitude"]["disturbances"]["gravity_gradient"] = False
    for key in ("sliding_gain_radps", "convergence_gain_radps", "kp_nm", "kd_nms"):
        control.pop(key, None)
    if kind == "sm":
        control.update(law="sliding_mode", sliding_gain_radps=float(a), convergence_gain_radps=float(b))
    else:
        control.update(law="pd", kp_nm=float(a), kd_nms=float(b))
    return parse_scenario(data, f"{name}-{spec}")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("scenario")
    parser.add_argument("orbits", type=float)
    parser.add_argument("cases", nargs="+")
    parser.add_argument("--truth", action="store_true")
    parser.add_argument("--rate-hz", type=float, default=None)
    parser.add_argument("--dither", action="store_true", help="quantisation_error_feedback = true")
    parser.add_argument("--compensation-am2", type=float, default=None,
                        help="residual_dipole_compensation_am2 x component (the plant's residual is 1e-3 along x)")
    parser.add_argument("--no-gravity-gradient", action="store_true")
    args = parser.parse_args()
    for spec in args.cases:
        scenario = case_scenario(args.scenario, args.orbits, spec, args.truth, args.rate_hz, args.dither, args.compensation_am2,
                                 args.no_gravity_gradient)
        started = time.process_time()
        trajectory = simulate_attitude_in_process(scenario)
        error = pointing_error_deg(trajectory, scenario)
        angle = continuous_rotation_angle_deg(trajectory, scenario)
        t = trajectory["att_time_s"]
        last_orbit = t >= t[-1] - ORBIT_S
        idx = np.linspace(0, len(error) - 1, 13).astype(int)
        saturated = float(np.mean(np.any(np.abs(trajectory["att_dipole_commanded_am2"]) >= 0.2 - 1e-9, axis=1)))
        extras = (" dither" if args.dither else "") + (f" compensation {args.compensation_am2}" if args.compensation_am2 is not None else "") \
            + (" no-gg" if args.no_gravity_gradient else "")
        print(f"{spec}{extras} ({args.scenario}, {args.orbits} orbits, {len(t)} steps, cpu {time.process_time() - started:.0f} s): "
              f"final {error[-1]:.2f} deg, last-orbit max {error[last_orbit].max():.2f} deg, "
              f"min rotation angle {angle.min():.1f} deg, saturated {saturated:.2f}; "
              f"at t = {[int(t[i]) for i in idx]} s: {[round(float(error[i]), 1) for i in idx]}", flush=True)


if __name__ == "__main__":
    main()
