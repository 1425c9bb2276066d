"""False alarms of every monitor on the fault campaign's clean missions, seed after seed.

    .venv/bin/python benchmarks/false_alarms.py [--seeds 10] [--workers 2] [--spec attitude_faults]

Each law of the campaign spec flies its mission (the mission's and the law's patches, the seed in
place of the scenario's) without any fault, in process with the lock-step bus for the whole
mission (bench.sim.simulate_attitude_in_process(with_bus=True): the flight-side driver, the bus
model and the board as the processes run them, on simulated time) and the FDIR in the loop (the
actuator monitor and, where the mission sets a pointing limit, the pointing envelope). There is no
fault, so every event of the driver, the board or the FDIR is a false alarm; the events that are
not alarms (bench.studies.fault_bus.BENIGN_EVENTS: heartbeat resumed, error reset, host overrun...)
are left out. It prints, per law, the runs, the alarms of each monitor and the worst pointing
error the envelope saw beside its limit. docs/fdir.md quotes what it prints.
"""
from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def clean_scenario(spec_name: str, law_name: str, seed: int) -> dict:
    from bench.studies.campaign import _merge, load_spec
    from bench.studies.fault_campaign import mission_base

    spec = load_spec(spec_name)
    law = spec.laws[law_name]
    data = _merge(mission_base(spec, law.mission), law.patch)     # as the campaign's cases, without the fault
    data = _merge(data, {"name": f"clean_{law_name}_s{seed}", "run": {"seed": seed}})
    data["can"] = {**data["can"], "faults": []}
    return data


def run_clean(spec_name: str, law_name: str, seed: int) -> dict:
    import logging

    import numpy as np

    from bench.scenario import parse_scenario
    from bench.sim import simulate_attitude_in_process
    from bench.studies.fault_bus import BENIGN_EVENTS, monitor_of

    logging.getLogger("bench.bus.can").setLevel(logging.ERROR)
    scenario = parse_scenario(clean_scenario(spec_name, law_name, seed), "clean mission")
    started = time.perf_counter()
    trajectory = simulate_attitude_in_process(scenario, with_bus=True)
    alarms = [(t, e.kind) for t, e in trajectory["can_driver_events"] if e.kind not in BENIGN_EVENTS]
    alarms += [(float(t), f"fdir_{c}") for t, c in zip(trajectory["fdir_event_time_s"], trajectory["fdir_event_class"])]
    by_monitor: dict[str, list] = {"board": [], "driver": [], "FDIR": []}
    for t, kind in sorted(alarms):
        by_monitor[monitor_of(kind)].append(f"{kind} at {t:.1f} s")
    limit = scenario.attitude_control.fdir.pointing_error_limit_deg
    peak = None
    if limit is not None:
        from bench.gnc import quaternion as qt

        target = np.asarray(scenario.attitude_control.target.q_wxyz, float)
        peak = float(np.rad2deg(max(qt.angle_between_rad(target, q) for q in trajectory["att_q_wxyz"])))
    return {"law": law_name, "seed": seed, "steps": len(trajectory["att_time_s"]), "alarms": by_monitor,
            "peak_pointing_error_deg": peak, "pointing_limit_deg": limit, "wall_s": time.perf_counter() - started}


def main() -> int:
    from bench.studies.campaign import load_spec

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--spec", default="attitude_faults")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--laws", default=None, help="comma-separated law names of the spec (default: all)")
    args = parser.parse_args()
    spec = load_spec(args.spec)
    laws = args.laws.split(",") if args.laws else list(spec.laws)
    jobs = [(args.spec, law, seed) for law in laws for seed in range(1, args.seeds + 1)]
    started = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(run_clean, *zip(*jobs)))
    print(f"{len(results)} clean runs ({len(laws)} laws x seeds 1..{args.seeds}) in {time.perf_counter() - started:.0f} s, "
          f"{args.workers} workers")
    print("| law (mission) | runs | steps each | board alarms | driver alarms | FDIR alarms | peak pointing error / envelope |")
    print("|---|---|---|---|---|---|---|")
    for law in laws:
        rows = [r for r in results if r["law"] == law]
        counts = {m: sum(len(r["alarms"][m]) for r in rows) for m in ("board", "driver", "FDIR")}
        peaks = [r["peak_pointing_error_deg"] for r in rows if r["peak_pointing_error_deg"] is not None]
        envelope = (f"{max(peaks):.2f} / {rows[0]['pointing_limit_deg']:g} deg" if peaks else "-")
        print(f"| {law} ({spec.laws[law].mission}) | {len(rows)} | {rows[0]['steps']} | {counts['board']} | "
              f"{counts['driver']} | {counts['FDIR']} | {envelope} |")
    for r in results:
        for monitor, events in r["alarms"].items():
            if events:
                print(f"  {r['law']} seed {r['seed']}: {monitor}: {', '.join(events[:5])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
