"""Campaign throughput: in-process vs multi-process cases, 1 vs 2 workers, local pool vs Ray.

Baseline measured in the same run: the in-process mode on one worker (cases run in this process,
no pool). Every configuration runs the same small campaign (LQR on CWH with the smoother, 288
steps per case) into a fresh results file; runs/s counts the whole campaign wall time, worker
start-up included (spawned pool workers and Ray workers import the bench: seconds each). Ray's
own start-up (`ray.init` of a local 2-CPU cluster) is timed separately.

    .venv/bin/python benchmarks/bench_campaign.py [--cases 12] [--process-cases 4]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from bench.studies.campaign import RAY_OBJECT_STORE_BYTES, parse_spec, read_rows, run_campaign


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=12, help="in-process cases per configuration")
    parser.add_argument("--process-cases", type=int, default=4, help="multi-process cases per configuration")
    parser.add_argument("--no-ray", action="store_true")
    args = parser.parse_args()
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
