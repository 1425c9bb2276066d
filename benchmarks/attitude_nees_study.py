"""Is the attitude estimate's covariance honest at every tick? A Monte Carlo of the smoother's
frontend (bench.estimator.attitude_frontend, the estimator process's own code) on a built-in
scenario's sensors, open loop (no dipole), one run per seed: the NEES of each tick's published
estimate against the plant's truth, averaged over the runs (ANEES, chi-square with 3 x runs dof
over runs), per stretch of the run, and the first ticks (a star-tracker fix and the gyro after it).

    PYTHONPATH=$PWD python benchmarks/attitude_nees_study.py attitude_pointing_rt 40

A real-time scenario's magnetometer in coil-blanking windows is taken on its schedule instead
(the windows need the board's wall clock), and the run is lock-step: the estimator does the same.
"""
import argparse
import copy
import tomllib
from importlib import resources

import numpy as np
from scipy import stats

from bench.estimator.attitude_frontend import AttitudeEstimator
from bench.plant.attitude_plant import AttitudePlant
from bench.report.attitude_estimation import rotation_vector
from bench.scenario import parse_scenario


def lock_step_twin(name: str):
    data = copy.deepcopy(tomllib.loads(resources.files("bench.scenarios").joinpath(f"{name}.toml").read_text()))
    data["run"] = {"mode": "lock-step", "seed": data["run"].get("seed", 1)}
    data["attitude"].setdefault("sensors", {})["magnetometer_sampling"] = "schedule"
    data.pop("can", None)
    data["estimator"] = {**data.get("estimator", {}), "mode": "smoother"}
    return parse_scenario(data, name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenario")
    parser.add_argument("runs", type=int)
    args = parser.parse_args()
    scenario = lock_step_twin(args.scenario)
    n_ticks = scenario.n_steps
    nees = np.full((args.runs, n_ticks), np.nan)
    for run in range(args.runs):
        plant = AttitudePlant(scenario.attitude, n_ticks, run + 1)
        estimator = AttitudeEstimator(scenario)
        for k in range(n_ticks):
            s = plant.sense()
            e = estimator.step(k, plant.time_s, s.gyro_radps, s.magnetometer_t,
                               None if s.magnetometer_t is None else s.field_inertial_t, s.star_tracker_wxyz)
            if e.valid and e.attitude_covariance_rad2 is not None:
                error = rotation_vector(np.array([plant.sim.q_wxyz]), np.array([e.q_wxyz]))[0]
                nees[run, k] = error @ np.linalg.solve(e.attitude_covariance_rad2, error)
            plant.apply(np.zeros(3))
    average = np.nanmean(nees, axis=0)
    low, high = stats.chi2.ppf([0.025, 0.975], 3 * args.runs) / args.runs
    t = np.arange(n_ticks) * scenario.step_s
    print(f"{args.scenario} (lock-step twin, open loop), {args.runs} runs of {n_ticks} ticks; ANEES 95 % band "
          f"[{low:.2f}, {high:.2f}]")
    print("| stretch (s) | ANEES mean | ticks inside the band |")
    print("| --- | --- | --- |")
    edges = np.unique(np.r_[np.linspace(0.0, t[-1] + scenario.step_s, 5), [2.0]])
    for a, b in zip(edges, edges[1:]):
        m = (t >= a) & (t < b)
        inside = np.mean((average[m] >= low) & (average[m] <= high))
        print(f"| {a:g}-{b:g} | {np.nanmean(average[m]):.2f} | {inside:.2f} |")
    print(f"| all | {np.nanmean(average):.2f} | {np.mean((average >= low) & (average <= high)):.2f} |")
    print("first ticks' ANEES:", " ".join(f"{x:.2f}" for x in average[:12]))


if __name__ == "__main__":
    main()
