"""Campaign throughput: in-process vs multi-process cases, 1 vs 2 workers, local pool vs Ray.

Baseline measured in the same run: the in-process mode on one worker (cases run in this process,
no pool). Every configuration runs the same small campaign (LQR on CWH with the smoother, 288
steps per case) into a fresh results file; runs/s counts the whole campaign wall time, worker
start-up included (spawned pool workers and Ray workers import the bench: seconds each). Ray's
own start-up (`ray.init` of a local 2-CPU cluster) is timed separately.

The fault campaign (`--faults`, built-in `attitude_faults`: each law on its mission with a bus
fault co-simulated through the real board and driver) is measured on the local pool and on Ray in
the same run, on one seed of every fault kind for the detumble and pointing laws (missions cut to
--fault-steps steps, faults moved to 60 s): cases/s per engine, and whether the rows are identical.

    .venv/bin/python benchmarks/bench_campaign.py [--cases 12] [--process-cases 4] [--faults-only]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bench.studies.campaign import parse_spec, run_campaign
from bench.studies.campaign_engines import RAY_OBJECT_STORE_BYTES
from bench.studies.campaign_results import read_rows


def spec(seeds: int, mode: str):
    return parse_spec({
        "name": f"bench-{mode}", "base_scenario": "rendezvous_lqr", "seeds": seeds, "mode": mode,
        "controllers": {"LQR": {"controller": {"type": "lqr"}}},
        "dynamics": {"linear": {"plant": {"dynamics": "cwh"}}},
        "knowledge": {"noisy": {"estimator": {"mode": "smoother"}}},
        "initial_conditions": {"A": {"plant": {"initial_condition": "A"}, "sample_position_std_m": 500.0}},
    })


def measure(label: str, campaign, out_dir: Path, **kwargs) -> dict:
    out = out_dir / f"{label.replace(' ', '_').replace(',', '')}.parquet"
    outcome = run_campaign(campaign, out, show_progress=False, **kwargs)
    rows = read_rows(out)
    for r in rows:
        if r["status"] != "ok":
            print(f"  {label}: {r['case_id']} {r['status']}: {r['error'][:300]}")
    return {"label": label, "runs": outcome.ran, "failed": outcome.failed, "wall_s": outcome.wall_s,
            "runs_per_s": outcome.runs_per_s,
            "rows": sorted((r["case_id"], r["final_position_error_m"]) for r in rows)}


def fault_spec(steps: int):
    import msgspec

    from bench.studies.campaign import load_spec

    spec = load_spec("attitude_faults")
    faults = {name: msgspec.structs.replace(f, start_s=60.0) for name, f in spec.faults.items()}
    laws = {name: law for name, law in spec.laws.items() if law.mission != "planned_slew"}
    return msgspec.structs.replace(spec, seeds=1, steps=steps, onset_jitter_s=0.0, faults=faults, laws=laws)


def measure_faults(out_dir: Path, steps: int) -> None:
    """Cases/s of the fault campaign on the local pool and on Ray, same cases, same run."""
    import ray

    from bench.studies.fault_campaign import METRIC_COLUMNS

    campaign = fault_spec(steps)
    rates, rows = {}, {}
    for engine in ("local", "ray"):
        started = time.perf_counter()
        if engine == "ray":
            ray.init(address="local", num_cpus=2, object_store_memory=RAY_OBJECT_STORE_BYTES,
                     include_dashboard=False, log_to_driver=False)
            print(f"ray.init of a local 2-CPU cluster: {time.perf_counter() - started:.1f} s (not in the rate)")
        try:
            out = out_dir / f"faults_{engine}.parquet"
            outcome = run_campaign(campaign, out, engine=engine, workers=2, show_progress=False)
        finally:
            if engine == "ray":
                ray.shutdown()
        rates[engine] = outcome
        rows[engine] = sorted((r["case_id"], r["status"], *(repr(r[c]) for c in METRIC_COLUMNS)) for r in read_rows(out))
    print(f"fault campaign ({steps} steps per mission, 2 workers): ", end="")
    print("; ".join(f"{e}: {o.ran} cases, {o.failed} failed, {o.wall_s:.1f} s, {o.runs_per_s:.2f} cases/s"
                    for e, o in rates.items()))
    print(f"fault campaign rows identical on the local pool and Ray (every metric column): {rows['local'] == rows['ray']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=12, help="in-process cases per configuration")
    parser.add_argument("--process-cases", type=int, default=4, help="multi-process cases per configuration")
    parser.add_argument("--no-ray", action="store_true")
    parser.add_argument("--faults-only", action="store_true", help="only the fault campaign, both engines")
    parser.add_argument("--fault-steps", type=int, default=200, help="steps per mission in the fault campaign")
    args = parser.parse_args()
    if args.faults_only:
        with tempfile.TemporaryDirectory() as tmp:
            measure_faults(Path(tmp), args.fault_steps)
        return
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        in_process, processes = spec(args.cases, "in-process"), spec(args.process_cases, "processes")
        results.append(measure("in-process, local, 1 worker", in_process, tmp, workers=1))
        results.append(measure("in-process, local, 2 workers", in_process, tmp, workers=2))
        ray_start_s = None
        if not args.no_ray:
            import ray

            started = time.perf_counter()
            ray.init(address="local", num_cpus=2, object_store_memory=RAY_OBJECT_STORE_BYTES,
                     include_dashboard=False, log_to_driver=False)
            ray_start_s = time.perf_counter() - started
            try:
                results.append(measure("in-process, ray local, 2 CPUs", in_process, tmp, engine="ray", workers=2))
            finally:
                ray.shutdown()
        results.append(measure("multi-process, local, 1 worker", processes, tmp, workers=1))
        results.append(measure("multi-process, local, 2 workers", processes, tmp, workers=2))
        if not args.no_ray:
            measure_faults(tmp, args.fault_steps)
    baseline = results[0]["runs_per_s"]
    print(f"{'configuration':34s} {'runs':>5s} {'failed':>6s} {'wall s':>8s} {'runs/s':>8s} {'x baseline':>10s}")
    for r in results:
        print(f"{r['label']:34s} {r['runs']:5d} {r['failed']:6d} {r['wall_s']:8.1f} {r['runs_per_s']:8.2f} "
              f"{r['runs_per_s'] / baseline:10.2f}")
    scaling = results[1]["runs_per_s"] / results[0]["runs_per_s"]
    print(f"scaling 1 -> 2 workers (in-process, local): {scaling:.2f}x")
    mp = [r for r in results if r["label"].startswith("multi-process")]
    print(f"scaling 1 -> 2 workers (multi-process, local): {mp[1]['runs_per_s'] / mp[0]['runs_per_s']:.2f}x")
    if ray_start_s is not None:
        print(f"ray.init of a local 2-CPU cluster: {ray_start_s:.1f} s (not in the campaign wall time)")
        same = results[1]["rows"] == results[2]["rows"]
        print(f"local pool and Ray results identical (case ids, final distances): {same}")


if __name__ == "__main__":
    main()
