"""Outlier Monte Carlo of the translational smoother (issue 27): 30 seeded runs per regime of 40
fixes with three isolated 20-sigma outliers and a one-sided burst of five 20-sigma fixes (steps
18-22), relative position and range/bearing, with and without process noise.

Criteria (the default built-in configuration must meet them): position RMS (steps >= 3) within
1.5x of the larger of the clean run's and an oracle's that drops the bad fixes (both least
squares), no good fix rejected after the burst, and NEES back inside its 95 % bounds 5 fixes after
the burst (the mean over runs of each run's time-averaged NEES from step 28 on, as in
tests/test_estimator_consistency.py; "worst step" is the largest 30-run mean NEES of a single
step from there, against the per-step 95 % upper bound, for information).

Run: PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_outliers.py [--runs 30]
"""
from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import msgspec  # noqa: E402
import numpy as np  # noqa: E402

from tests.outlier_monte_carlo import (RMS_FROM_STEP, default_smoother_config, draw, fly, monte_carlo,  # noqa: E402
                                       regime_config, ungated)

PROCESS_NOISE_PSD = 1.0e-6     # m^2/s^3: 8.5 m of position random walk per 600 s step
VARIANTS = {
    "default (gate, burst guard, re-acquisition)": {},
    "gate only (as before issue 27)": dict(gate_burst_likelihood_ratio=1e15, reacquire_after_rejections=10_000),
    "no protection (least squares)": dict(gate_probability=None),
    "Huber k=3, no gate": dict(gate_probability=None, robust_loss="huber"),
    "Cauchy k=3, no gate": dict(gate_probability=None, robust_loss="cauchy"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=30)
    parser.add_argument("--robust-clean", action="store_true",
                        help="only the clean-data cost of the robust losses (position RMS over least squares)")
    args = parser.parse_args()
    base = default_smoother_config()
    if args.robust_clean:
        robust_clean_cost(base, args.runs)
        return
    print(f"{args.runs} runs per row; default = the estimator section of bench/scenarios/rendezvous_smoother.toml")
    print("| sensor | process noise | smoother | RMS m | clean | oracle | RMS / max | bad fixes used | "
          "good rejected after burst | re-acquisitions | NEES after (bounds) | worst step (bound) | pass |")
    print("| " + " | ".join(["---"] * 13) + " |")
    for sensor in ("relpos", "range_bearing"):
        for psd in (0.0, PROCESS_NOISE_PSD):
            for name, overrides in VARIANTS.items():
                config = regime_config(base, sensor, psd, **overrides)
                v = monte_carlo(config, args.runs)
                low, high = v.nees_bounds
                print(f"| {sensor} | {psd:g} | {name} | {v.rms_m:.1f} | {v.clean_rms_m:.1f} | {v.oracle_rms_m:.1f} | "
                      f"{v.rms_ratio:.2f} | {v.outliers_used} | {v.good_rejected_after_burst} | {v.reacquisitions} | "
                      f"{v.nees_after:.2f} ({low:.2f}-{high:.2f}) | {v.worst_step_nees:.1f} ({v.step_nees_upper:.2f}) | "
                      f"{'yes' if v.passed else 'NO'} |", flush=True)



def robust_clean_cost(base, runs: int) -> None:
    """Position RMS of Huber and Cauchy (no gate) over least squares, on the clean fixes."""
    for sensor in ("relpos", "range_bearing"):
        for psd in (0.0, PROCESS_NOISE_PSD):
            config = ungated(regime_config(base, sensor, psd))
            rms = {}
            for loss in ("none", "huber", "cauchy"):
                flown = msgspec.structs.replace(config, robust_loss=loss)
                errors = np.concatenate([fly(flown, draw(27_000 + i, config), "clean").error[RMS_FROM_STEP:, :3]
                                         for i in range(runs)])
                rms[loss] = float(np.sqrt(np.mean(np.sum(errors**2, axis=1))))
            print(f"{sensor} process noise {psd:g}: least squares {rms['none']:.2f} m, Huber x{rms['huber'] / rms['none']:.3f}, "
                  f"Cauchy x{rms['cauchy'] / rms['none']:.3f}", flush=True)


if __name__ == "__main__":
    main()
