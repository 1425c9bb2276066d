"""Calibration and detection figures of the FDIR actuator monitor (bench.gnc.actuator_monitor),
in process (the lock-step loop's twin: tests/test_fdir.py checks the processes give the same
detections). docs/fdir.md quotes what this prints.

    .venv/bin/python benchmarks/fdir_calibration.py clean [--seeds 10] [--steps N] [--scenarios a,b]
        every fault-free built-in attitude scenario (run in process, whatever its mode), seeds
        1..N in place of its own: FDIR alarms (false alarms: there is no fault), and per coil the
        share of evaluations judged (excited enough), the largest statistic d^2 and the largest
        |gain - 1| and |offset| the monitor estimated while judging;
    .venv/bin/python benchmarks/fdir_calibration.py reaction
        attitude_quick with a coil fault from 100 s, with and without the accommodation;
    .venv/bin/python benchmarks/fdir_calibration.py faults [--seeds 5] [--onset-s 120] [--classes ...]
        a coil fault through the plant's coil hook ([attitude.coils] gain: -1 reversed, 0 open,
        0.5 weak) on each axis of the missions below: detected or not, on the right axis and in
        the right class, the alarm and the classification latency after the onset, and the
        signal-to-noise ratio of a reversed coil at the gyro's noise (per step, and over the
        window: 2 / sigma_gain).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import msgspec
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.gnc.actuator_monitor import AXES, ActuatorMonitor  # noqa: E402
from bench.scenario import fault_free_attitude_builtins, load_scenario, parse_scenario  # noqa: E402

FAULTS = {"reversed": -1.0, "open": 0.0, "gain": 0.5}
FDIR_OVERRIDES: dict = {}      # --fdir key=value: [attitude_control.fdir] settings tried
# The missions of bench/studies/campaigns/attitude_faults.toml where coils are commanded hard
# enough to be judged, and the other built-in attitude scenarios with their own laws.
FAULT_MISSIONS = ("attitude_quick", "attitude_detumble", "attitude_detumble_sgp4", "attitude_slew_milqr_truth")


def scenario(name: str, seed: int, steps: int | None, coils: dict | None = None, duration_s: float | None = None):
    truth = name.endswith("_truth")
    data = msgspec.to_builtins(load_scenario(name.removesuffix("_truth")))
    if duration_s is not None:
        steps = int(round(duration_s * data["attitude"]["sensors"]["gyro_rate_hz"]))
    data["run"]["seed"] = seed
    # In process, as lock-step; a scenario that cannot be lock-step (the board's magnetometer
    # windows on the wall clock: attitude_pointing_rt) keeps its mode, the loop is the same.
    if not (data.get("can") or {}).get("board", {}).get("mag_window_period_s"):
        data["run"]["mode"] = "lock-step"
    if steps:
        data["run"]["steps"] = steps
    if truth:      # the campaign's planned slew flies on the truth estimate
        data["estimator"]["mode"] = "truth"
    if coils:
        data["attitude"]["coils"] = coils
    if FDIR_OVERRIDES:
        data["attitude_control"]["fdir"] = {**data["attitude_control"].get("fdir", {}), **FDIR_OVERRIDES}
    return parse_scenario(data, name)


def run(s, keep_statistics: bool = False) -> tuple[ActuatorMonitor, dict]:
    """The in-process loop with the cycle's monitor kept (and its per-evaluation statistics)."""
    import bench.sim as sim
    from bench.controller import attitude_cycle

    holder = {}
    original = attitude_cycle.AttitudeCycle.__init__

    def init(self, scenario_):
        original(self, scenario_)
        if self.fdir is not None:
            self.fdir.keep_statistics = keep_statistics
        holder["cycle"] = self

    attitude_cycle.AttitudeCycle.__init__ = init
    try:
        trajectory = sim.simulate_attitude_in_process(s)
    finally:
        attitude_cycle.AttitudeCycle.__init__ = original
    return holder["cycle"].fdir, trajectory


def clean(args) -> None:
    names = args.scenarios.split(",") if args.scenarios else fault_free_attitude_builtins()
    print(f"fault-free built-in attitude scenarios: {', '.join(names)}; seeds 1..{args.seeds}; "
          f"{'full length' if not args.steps else f'{args.steps} steps'}")
    total_alarms, total_evaluations = 0, 0
    for name in names:
        alarms, judged, evaluations, peak, worst_gain, worst_offset, wall = 0, [0, 0, 0], 0, 0.0, 0.0, 0.0, 0.0
        for seed in range(1, args.seeds + 1):
            t0 = time.perf_counter()
            monitor, _ = run(scenario(name, seed, args.steps))
            wall += time.perf_counter() - t0
            alarms += len(monitor.events)
            for e in monitor.events:
                print(f"  FALSE ALARM {name} seed {seed}: {e.describe()}")
            evaluations += monitor.evaluations
            for j in range(3):
                judged[j] += monitor.judged[j]
            peak = max(peak, max(monitor.peak_statistic))
            worst_gain = max(worst_gain, monitor.worst_gain_deviation)
            worst_offset = max(worst_offset, monitor.worst_offset_am2)
        total_alarms += alarms
        total_evaluations += 3 * evaluations
        share = ", ".join(f"{a} {100 * judged[j] / max(1, evaluations):.0f}%" for j, a in enumerate(AXES))
        print(f"{name:26s} alarms {alarms}  evaluations {evaluations:6d}  judged {share}  peak d2 {peak:.2f}  "
              f"max |g-1| {worst_gain:.3f}  max |s| {worst_offset:.2e} A m^2  ({wall:.0f} s)")
    print(f"total: {total_alarms} FDIR alarms in {total_evaluations} coil evaluations")


def faults(args) -> None:
    classes = args.classes.split(",")
    missions = args.scenarios.split(",") if args.scenarios else FAULT_MISSIONS
    latencies: dict[str, list[float]] = {c: [] for c in classes}
    alarm_latencies: dict[str, list[float]] = {c: [] for c in classes}
    for name in missions:
        # SNR of a reversed coil at the gyro's noise, from the clean run (seed 1).
        duration_s = args.onset_s + args.jitter_s + args.after_s
        monitor, trajectory = run(scenario(name, 1, None, duration_s=duration_s), keep_statistics=True)
        snr_step, snr_window = reversed_coil_snr(monitor, trajectory)
        print(f"{name}: reversed-coil SNR at the gyro's noise, per step (median over commanded steps) "
              + ", ".join(f"{a} {snr_step[j]:.2f}" for j, a in enumerate(AXES))
              + f"; over the {monitor.settings.window_s:.0f} s window (2 / sigma_g, median over the evaluations) "
              + ", ".join(f"{a} {snr_window[j]:.1f}" for j, a in enumerate(AXES)))
        # What that allows: the alarm needs (|g - 1| - gain_tolerance) / sigma_g above sqrt(threshold);
        # a reversed coil is 2 from 1, and sigma_g falls as T^-3/2 with the window T (a rate ramp
        # fitted against white noise): T* = window (sqrt(threshold) sigma_g(window) / (2 - tol))^(2/3).
        st = monitor.settings
        print("  expected alarm latency of a reversed coil (least squares on this excitation): "
              + ", ".join(f"{a} {st.window_s * (np.sqrt(st.threshold) * (2 / snr_window[j]) / (2 - st.gain_tolerance)) ** (2 / 3):.0f} s"
                          for j, a in enumerate(AXES)))
        mission_latencies: dict[str, list[tuple[float, float]]] = {c: [] for c in classes}
        for fault_class in classes:
            for axis in range(3):
                outcomes = []
                for seed in range(1, args.seeds + 1):
                    gain = [1.0, 1.0, 1.0]
                    gain[axis] = FAULTS[fault_class]
                    # The onset moved per seed (the truth-estimate missions have no other randomness),
                    # on a whole step, as the campaign's onset_jitter_s does.
                    onset_s = args.onset_s + round(args.jitter_s * float(np.random.default_rng(seed).uniform(-1, 1)))
                    monitor, _ = run(scenario(name, seed, None, {"gain": gain, "from_s": onset_s}, duration_s))
                    events = [e for e in monitor.events if e.time_s >= onset_s]
                    early = [e for e in monitor.events if e.time_s < onset_s]
                    right = [e for e in events if e.axis == axis and e.fault_class == fault_class]
                    wrong = [e for e in events if not (e.axis == axis and e.fault_class == fault_class)]
                    if right:
                        latencies[fault_class].append(right[0].time_s - onset_s)
                        alarm_latencies[fault_class].append(right[0].alarm_s - onset_s)
                        mission_latencies[fault_class].append((right[0].alarm_s - onset_s, right[0].time_s - onset_s))
                    outcomes.append("ok %.0f/%.0f s" % (right[0].alarm_s - onset_s, right[0].time_s - onset_s)
                                    if right else "MISSED")
                    for e in wrong + early:
                        outcomes.append(f"WRONG {e.kind} {e.axis_name} at {e.time_s:.0f} s")
                print(f"  {fault_class:8s} coil {AXES[axis]}: " + "; ".join(outcomes))
        for fault_class, found in mission_latencies.items():
            if found:
                print(f"  {name} {fault_class}: {len(found)} of {3 * args.seeds} classified, median alarm "
                      f"{statistics.median(a for a, _ in found):.0f} s, class {statistics.median(c for _, c in found):.0f} s "
                      f"(max {max(c for _, c in found):.0f} s)")
    for fault_class in classes:
        lat, alarm = latencies[fault_class], alarm_latencies[fault_class]
        if lat:
            print(f"{fault_class}: classified in {len(lat)} cases, median latency after the onset: alarm "
                  f"{statistics.median(alarm):.0f} s, class {statistics.median(lat):.0f} s (max {max(lat):.0f} s)")


def reaction(args) -> None:
    """The accommodation's worth: attitude_quick with each coil reversed, open or at half gain from
    100 s, with and without [attitude_control.fdir] accommodate."""
    import bench.sim as sim
    from bench.report.attitude_metrics import attitude_metrics

    def one(gain, accommodate_):
        data = msgspec.to_builtins(load_scenario("attitude_quick"))
        if gain is not None:
            data["attitude"]["coils"] = {"gain": gain, "from_s": 100.0}
        data["attitude_control"]["fdir"] = {"accommodate": accommodate_}
        s = parse_scenario(data, "reaction")
        trajectory = sim.simulate_attitude_in_process(s)
        detumbled = attitude_metrics(trajectory, s).get("time_to_detumble_s")
        rate = float(np.rad2deg(np.linalg.norm(trajectory["att_omega_radps"][-1])))
        found = ", ".join(f"{c} {a} at {t:.0f} s" for t, a, c in zip(trajectory["fdir_event_time_s"],
                                                                     trajectory["fdir_event_axis"],
                                                                     trajectory["fdir_event_class"]))
        goal = f"met from {detumbled:.0f} s" if detumbled is not None and np.isfinite(detumbled) else "missed"
        return f"{rate:.3f} deg/s, {goal}", found or "nothing"

    print("clean:", one(None, False)[0])
    for gain in ([-1, 1, 1], [1, -1, 1], [1, 1, -1], [0, 1, 1], [1, 0, 1], [1, 1, 0], [0.5, 1, 1]):
        without, found = one(gain, False)
        with_, _ = one(gain, True)
        print(f"coil gains {gain} from 100 s: detected {found}; without the reaction {without}; with it {with_}")


def reversed_coil_snr(monitor: ActuatorMonitor, trajectory: dict) -> tuple[list[float], list[float]]:
    """Per coil: the torque a reversed coil takes away, |2 m_j (e_j x B)| dt, against the gyro
    noise in momentum (J sigma sqrt 2: a rate difference), median over the steps the coil was
    commanded; and 2 / sigma_gain over the judged window fits."""
    dt = monitor.model.step_s
    sigma = monitor.model.gyro_noise_std_radps
    dipole = trajectory["att_dipole_applied_am2"]
    field_t = trajectory["att_field_body_t"]
    inertia = monitor.inertia
    per_step = []
    for j in range(3):
        e = np.zeros(3)
        e[j] = 1.0
        torque = 2 * np.abs(dipole[:, j])[:, None] * np.cross(e, field_t)
        momentum = np.linalg.norm(torque @ np.linalg.inv(inertia).T, axis=1) * dt   # rate change, rad/s
        commanded = np.abs(dipole[:, j]) > 0
        per_step.append(float(np.median(momentum[commanded] / (np.sqrt(2) * sigma))) if commanded.any() else 0.0)
    window = [float(np.median(monitor.gain_std_window[j])) if monitor.gain_std_window[j] else float("inf")
              for j in range(3)]
    return per_step, [2.0 / w for w in window]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=("clean", "faults", "reaction"))
    parser.add_argument("--seeds", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None, help="clean: steps per run (default: each scenario's length)")
    parser.add_argument("--scenarios", default="")
    parser.add_argument("--onset-s", type=float, default=120.0)
    parser.add_argument("--after-s", type=float, default=240.0, help="faults: simulated time after the onset")
    parser.add_argument("--jitter-s", type=float, default=20.0, help="faults: onset moved by up to this per seed")
    parser.add_argument("--classes", default="reversed,open,gain")
    parser.add_argument("--fdir", action="append", default=[], help="an [attitude_control.fdir] setting, key=value")
    args = parser.parse_args()
    for item in args.fdir:
        key, _, value = item.partition("=")
        FDIR_OVERRIDES[key] = float(value) if key != "persistence" else int(value)
    if args.what == "reaction":
        reaction(args)
    elif args.what == "clean":
        args.seeds = args.seeds or 10
        clean(args)
    else:
        args.seeds = args.seeds or 5
        faults(args)


if __name__ == "__main__":
    main()
