"""Run only some cells of a campaign spec (e.g. seed 001's nonlinear noisy-sensor cells) into a
results file, with that spec's report: the figures docs/campaigns.md gives for re-run cells.

    PYTHONPATH=$PWD python benchmarks/campaign_cells.py seed001 --cell dynamics=nonlinear \
        --cell knowledge=noisy_sensor,noisy_sensor_and_orbit --seeds 30 --workers 2 --out x.parquet

A case is run when, for every --cell AXIS=V1,V2 given, its value on AXIS is one of the values.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import msgspec

from bench.studies.campaign import expand, load_spec, run_campaign
from bench.studies.campaign_report import write_report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("spec")
    parser.add_argument("--cell", action="append", default=[], help="AXIS=VALUE[,VALUE...] (repeatable)")
    parser.add_argument("--seeds", type=int)
    parser.add_argument("--steps", type=int, help="override the run length (plant steps)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    spec = load_spec(args.spec)
    changes = {k: v for k, v in (("seeds", args.seeds), ("steps", args.steps)) if v is not None}
    spec = msgspec.structs.replace(spec, **changes)
    wanted = {}
    for item in args.cell:
        axis, _, values = item.partition("=")
        if not values:
            parser.error(f"--cell {item!r}: expected AXIS=VALUE[,VALUE...]")
        wanted[axis] = set(values.split(","))
    cases = expand(spec)
    unknown = set(wanted) - set(cases[0].cell)
    if unknown:
        parser.error(f"unknown axes {sorted(unknown)}; the spec's are {sorted(cases[0].cell)}")
    chosen = [c for c in cases if all(c.cell[axis] in values for axis, values in wanted.items())]
    if not chosen:
        parser.error("no case matches the --cell filters")
    outcome = run_campaign(spec, Path(args.out), workers=args.workers, show_progress=False, cases=chosen)
    print(f"{outcome.total} cases: {outcome.ran} run ({outcome.failed} failed) in {outcome.wall_s:.1f} s")
    print(f"report: {write_report(Path(args.out))}")


if __name__ == "__main__":
    main()
