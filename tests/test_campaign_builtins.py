"""Every built-in campaign spec (bench/studies/campaigns/*.toml) runs: every cell of its grid
expands and validates (for the first seed: seeds change only the per-seed draws, and the whole
540-case seed 001 grid takes 5-12 s to expand on this machine), and a slice of it (one seed, the first and the last case of the grid, a few steps) runs
end to end through `run_campaign`, the path `bench campaign` takes, into rows and a report. A
scenario change that breaks a spec fails here, not in a user's 40-minute campaign."""
import math
import re

import msgspec
import pytest

from bench.scenario import NAME_PATTERN
from bench.studies.campaign import AXES, CampaignSpec, builtin_specs, expand, load_spec, read_rows, run_campaign
from bench.studies.campaign_report import write_report

SLICE_STEPS = 12


def test_there_are_built_in_specs():
    assert "seed001" in builtin_specs()


def fault_specs() -> list[str]:
    return [n for n in builtin_specs() if not isinstance(load_spec(n), CampaignSpec)]


@pytest.mark.parametrize("name", [n for n in builtin_specs() if n not in fault_specs()])
def test_built_in_spec_expands_and_a_slice_runs_end_to_end(name, tmp_path):
    import re

    spec = load_spec(name)
    short = msgspec.structs.replace(spec, seeds=1, steps=min(spec.steps or SLICE_STEPS, SLICE_STEPS))
    cells = msgspec.structs.replace(spec, seeds=1)
    cases = expand(cells)                  # every cell of the grid, validated as the spec runs it
    assert len(cases) == math.prod(len(getattr(spec, axis)) for axis in AXES)
    ids = [c.case_id for c in cases]
    assert len(set(ids)) == len(ids)
    names = [c.scenario["name"] for c in cases]
    assert len(set(names)) == len(names) and all(re.fullmatch(NAME_PATTERN, n) for n in names)
    assert all(c.case_id in c.scenario["description"] for c in cases)    # the scenario says which case it is

    short_cases = expand(short)
    chosen = [short_cases[0], short_cases[-1]] if len(short_cases) > 1 else short_cases
    out = tmp_path / f"{name}.parquet"
    outcome = run_campaign(short, out, workers=1, show_progress=False, cases=chosen)
    rows = read_rows(out)
    assert outcome.ran == len(chosen) == len(rows)
    for row in rows:
        assert row["status"] == "ok", (row["case_id"], row["error"])
        assert row["steps"] == short.steps and math.isfinite(row["final_position_error_m"]), row["case_id"]
    report = write_report(out, tmp_path / "report").read_text()
    assert all(row["controller"] in report for row in rows)


@pytest.mark.parametrize("name", fault_specs())
def test_built_in_fault_spec_expands_and_a_slice_runs_end_to_end_with_its_matrix(name, tmp_path):
    """Every case of the fault spec expands at full length; a slice (one seed, each law once with a
    different fault, missions cut to 20 steps, faults moved to 5 s for 2 s) runs into rows and the
    report's fault x law matrix."""
    from bench.bus.can.faults import FAULTS
    from test_campaign_faults import tiny

    spec = load_spec(name)
    cases = expand(msgspec.structs.replace(spec, seeds=1))
    assert {c.cell["fault"] for c in cases} == set(spec.faults)
    assert {f.name for f in spec.faults.values()} == set(FAULTS)          # every fault kind the bench injects
    assert len(spec.laws) >= 3 and spec.seeds >= 10
    assert len(cases) == len(spec.laws) * len(spec.faults)
    ids = [c.case_id for c in cases]
    assert len(set(ids)) == len(ids) and all(re.fullmatch(NAME_PATTERN, c.scenario["name"]) for c in cases)

    short = tiny(spec)
    short_cases = expand(short)
    laws = list(dict.fromkeys(c.cell["law"] for c in short_cases))
    faults = list(short.faults)
    # Law i with fault i (mod): every law and as many fault kinds as laws, one case each.
    chosen = [next(c for c in short_cases if c.cell["law"] == law and c.cell["fault"] == faults[i * 3 % len(faults)])
              for i, law in enumerate(laws)]
    out = tmp_path / f"{name}.parquet"
    outcome = run_campaign(short, out, workers=1, show_progress=False, cases=chosen)
    rows = read_rows(out)
    assert outcome.ran == len(chosen) == len(rows)
    for row in rows:
        assert row["status"] == "ok", (row["case_id"], row["error"])
        assert row["steps"] == 20 and row["effect"] in ("none", "recovered", "degraded", "lost"), row["case_id"]
        assert row["false_alarms"] == 0, row["case_id"]
    report_dir = tmp_path / "report"
    report = write_report(out, report_dir).read_text()
    matrix = (report_dir / "fault_matrix.md").read_text()
    assert (report_dir / "fault_matrix.png").is_file() and matrix in report
    page = (report_dir / "report.html").read_text()     # the same report for a browser, its matrix picture in it
    assert "<table>" in page and "<img src=\"fault_matrix.png\"" in page
    header = matrix.splitlines()[0]
    assert all(law in header for law in laws)
    assert all(f"| {row['fault']} |" in matrix for row in rows)
