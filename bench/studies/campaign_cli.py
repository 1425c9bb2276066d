"""`bench campaign SPEC` and `bench campaign-report RESULTS`."""
from __future__ import annotations

import sys
from pathlib import Path

from bench.scenario import ScenarioError

EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130      # 128 + SIGINT, as a shell reports a command Ctrl-C stopped


def cmd_campaign(args) -> int:
    from bench.studies.campaign import CampaignError, load_spec, run_campaign
    from bench.studies.campaign_results import parts_dir, read_rows
    from bench.studies.campaign_report import write_report

    out = None
    try:
        spec = load_spec(args.spec)
        if args.seeds is not None:
            import msgspec

            spec = msgspec.structs.replace(spec, seeds=args.seeds)
        out = Path(args.out or f"campaigns/{spec.name}.parquet")
        outcome = run_campaign(spec, out, engine=args.engine, workers=args.workers, address=args.address,
                               show_progress=not args.no_progress, flush_every=args.flush_every,
                               retry_failed=args.retry_failed)
    except (CampaignError, ScenarioError, ValueError) as exc:
        print(f"bench: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        # The pool is stopped and every finished row is in the parts: the same command resumes.
        kept = len(read_rows(out)) if out is not None else 0
        where = parts_dir(out) if out is not None else "nowhere (nothing had run)"
        print(f"bench: campaign interrupted: {kept} rows kept in {where}; run the same command to resume",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    print(f"{outcome.total} cases: {outcome.skipped} already done, {outcome.ran} run ({outcome.failed} failed) "
          f"in {outcome.wall_s:.1f} s, {outcome.runs_per_s:.2f} runs/s; results: {out}")
    if not args.no_report:
        print(f"report: {write_report(out)}")
    return 0


def cmd_campaign_report(args) -> int:
    from bench.studies.campaign_report import write_report

    results = Path(args.results)
    if not results.is_file():
        print(f"bench: error: results file {results} does not exist", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"report: {write_report(results, args.out)}")
    return 0


def add_commands(subparsers) -> None:
    p = subparsers.add_parser("campaign", help="run a Monte Carlo campaign (grid x seeds) into a Parquet file")
    p.add_argument("spec", help="campaign spec TOML, or a built-in name (seed001)")
    p.add_argument("--out", help="results file (default: campaigns/<name>.parquet); re-running resumes it")
    p.add_argument("--engine", choices=["local", "ray"], default="local", help="local process pool (default) or Ray")
    p.add_argument("--address", help="Ray cluster address (with --engine ray; default: start a local Ray)")
    p.add_argument("--workers", type=int, help="parallel runs (default: CPU count)")
    p.add_argument("--seeds", type=int, help="override the spec's number of seeds")
    p.add_argument("--flush-every", type=int, default=16, help="rows per part file written while running")
    p.add_argument("--retry-failed", action="store_true", help="re-run cases recorded as failed")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--no-report", action="store_true", help="skip the report (bench campaign-report later)")
    p.set_defaults(func=cmd_campaign)
    r = subparsers.add_parser("campaign-report", help="re-render a campaign's report from its results file")
    r.add_argument("results", help="the campaign's Parquet results file")
    r.add_argument("--out", help="report directory (default: <results>_report)")
    r.set_defaults(func=cmd_campaign_report)
