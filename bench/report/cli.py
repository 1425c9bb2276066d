"""`bench report RUN_DIR` and `bench compare RUN_DIR RUN_DIR...`."""
from __future__ import annotations

import sys

from bench.report.rundata import RunDirError

EXIT_BAD_INPUT = 2


def cmd_report(args) -> int:
    from bench.report.build import write_report

    try:
        md, page = write_report(args.run_dir)
    except RunDirError as exc:
        print(f"bench report: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    print(f"wrote {page} and {md}")
    return 0


def cmd_compare(args) -> int:
    from bench.report.compare import CompareError, write_comparison

    try:
        md, page = write_comparison(args.run_dirs, args.out, args.reference)
    except (RunDirError, CompareError) as exc:
        print(f"bench compare: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    # the comparison itself, as the terminal shows it: its first section (note and table)
    text = md.read_text()
    first = text.split("\n## ", 2)
    print(("## " + first[1]).split("![")[0].rstrip() if len(first) > 1 else text)
    print(f"wrote {page} and {md}")
    return 0


def add_commands(subparsers) -> None:
    report = subparsers.add_parser("report", help="write report.html, report.md and plots of a run directory")
    report.add_argument("run_dir", help="a run directory, e.g. runs/<run_id>")
    report.set_defaults(func=cmd_report)

    compare = subparsers.add_parser("compare", help="put runs side by side in one table and one set of plots")
    compare.add_argument("run_dirs", nargs="+", help="run directories to compare")
    compare.add_argument("--out", help="output directory (default: runs/compare-<time>)")
    compare.add_argument("--reference", help="the clean run the others' fault effects are measured against "
                                             "(attitude; added to the runs if not among them)")
    compare.set_defaults(func=cmd_compare)
