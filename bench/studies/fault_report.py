"""The fault campaign's failure-modes matrix: fault kind (rows) x attitude law (columns), each cell
coloured by the worst mission effect over the seeds, with how often each effect occurred, the
share of cases detected, by which monitor (board, driver, FDIR) and with what first, and the
median detection latency (simulated seconds). A cell with an undetected case is a failure whatever
its effect (purple, never green): a fault nobody saw is one the flight side cannot react to.
A board power loss's cell also says how long the coils were off inside its window and whether the
board was operational again after it (the driver's NMT start, ms after the reboot).

Read from the Parquet results `bench campaign attitude_faults` writes; `bench campaign-report`
re-renders it (markdown table and PNG).
"""
from __future__ import annotations

import importlib

import math
from pathlib import Path

import numpy as np

from bench.studies.fault_campaign import EFFECTS

COLOURS = {"none": "#4caf50", "recovered": "#ffeb3b", "degraded": "#ff9800", "lost": "#e53935",
           "undetected": "#8e24aa", "failed": "#9e9e9e"}
MARKS = {"none": "🟩", "recovered": "🟨", "degraded": "🟧", "lost": "🟥", "undetected": "🟪", "failed": "⬜"}


HTML_PAGE = "bench.report.markdown_page"     # Markdown -> HTML beside it, in the run reports' style

def is_fault_campaign(rows: list[dict]) -> bool:
    return bool(rows) and "fault_kind" in rows[0]


def cells(rows: list[dict]) -> tuple[list[str], list[str], dict]:
    """(faults in case order, laws in case order, {(fault, law): summary})."""
    rows = sorted(rows, key=lambda r: r["case_index"])
    faults = list(dict.fromkeys(r["fault"] for r in rows))
    laws = list(dict.fromkeys(r["law"] for r in rows))
    out = {}
    for fault in faults:
        for law in laws:
            group = [r for r in rows if r["fault"] == fault and r["law"] == law]
            if not group:
                continue
            ok = [r for r in group if r["status"] == "ok"]
            counts = {e: sum(r["effect"] == e for r in ok) for e in EFFECTS}
            worst = next((e for e in reversed(EFFECTS) if counts[e]), "failed")
            latencies = np.array([r["detection_latency_s"] for r in ok if r["detected"]], float)
            recover = np.array([r["time_to_recover_s"] for r in ok if r["effect"] == "recovered"], float)
            detected_by = [r.get("detected_by") or "driver" for r in ok if r["detected"]]
            power = [r for r in ok if r["fault_kind"] == "board_power_loss"]
            out[(fault, law)] = {
                "runs": len(group), "failed": len(group) - len(ok), "counts": counts, "worst": worst,
                "detected": sum(bool(r["detected"]) for r in ok),
                "latency_median_s": float(np.median(latencies)) if latencies.size else float("nan"),
                "latency_max_s": float(latencies.max()) if latencies.size else float("nan"),
                "first_detection": max((r["first_detection"] for r in ok if r["detected"]),
                                       key=lambda k: sum(r["first_detection"] == k for r in ok), default=""),
                "max_deviation": max((r["max_deviation"] for r in ok), default=float("nan")),
                "recover_median_s": float(np.median(recover)) if recover.size else float("nan"),
                "outlasts": any(bool(r.get("fault_outlasts_mission", False)) for r in ok),
                "mission": group[0]["mission"],
                "detected_by": max(dict.fromkeys(detected_by), key=detected_by.count, default=""),
                "monitors": sorted({m for r in ok for m in (r.get("monitors") or "").split(",") if m}),
                # power loss: the least share of its window with the coils off, boards operational after
                "off_share_min": min((r["coils_off_in_fault_s"] / r["fault_duration_s"] for r in power
                                      if r.get("fault_duration_s")), default=float("nan")),
                "operational_after": sum(bool(r.get("board_operational_after")) for r in power),
                "recovery_ms_max": max((r["board_recovery_ms"] for r in power
                                        if r.get("board_recovery_ms") is not None and not math.isnan(r["board_recovery_ms"])),
                                       default=float("nan")),
                "power_runs": len(power),
            }
            out[(fault, law)]["colour"] = ("undetected" if ok and out[(fault, law)]["detected"] < len(ok)
                                           else out[(fault, law)]["worst"])
    return faults, laws, out


def _cell_text(s: dict) -> str:
    counts = ", ".join(f"{e} {n}" for e, n in s["counts"].items() if n)
    if s["failed"]:
        counts += f", failed {s['failed']}"
    ok = s["runs"] - s["failed"]
    if s["detected"]:
        others = [m for m in s["monitors"] if m != s["detected_by"]]
        detection = (f"detected {s['detected']}/{ok} by **{s['detected_by']}** ({s['first_detection']}) in "
                     f"{s['latency_median_s'] * 1e3:.0f} ms (max {s['latency_max_s'] * 1e3:.0f})"
                     + (f", also {', '.join(others)}" if others else ""))
        if s["detected"] < ok:
            detection += f"; **undetected {ok - s['detected']}**"
    else:
        detection = f"**undetected** ({ok} runs)"
    recover = ("" if math.isnan(s["recover_median_s"]) else
               f"; back {s['recover_median_s']:.0f} s after the onset, the fault still acting" if s["outlasts"]
               else f"; recovers {s['recover_median_s']:.0f} s after")
    power = ""
    if s["power_runs"]:
        power = (f"; coils off {100 * s['off_share_min']:.0f} % of the window (least), operational again "
                 f"{s['operational_after']}/{s['power_runs']}"
                 + ("" if math.isnan(s["recovery_ms_max"]) else f" (NMT start {s['recovery_ms_max']:.1f} ms after the boot)"))
    return f"{MARKS[s['colour']]} **{s['worst']}** ({counts}); {detection}{recover}{power}"


def matrix_markdown(rows: list[dict]) -> str:
    faults, laws, summary = cells(rows)
    missions = {law: next(s["mission"] for (f, l), s in summary.items() if l == law) for law in laws}
    lines = ["| fault | " + " | ".join(f"{law} ({missions[law]})" for law in laws) + " |",
             "|---|" + "---|" * len(laws)]
    for fault in faults:
        lines.append(f"| {fault} | " + " | ".join(_cell_text(summary[(fault, law)]) if (fault, law) in summary else ""
                                                  for law in laws) + " |")
    legend = ("Worst mission effect over the seeds (counts per effect): none = within tolerance of the clean run "
              "throughout; recovered = back within tolerance for good (median time after the fault's end, or after its onset for a fault that outlasts the mission); "
              "degraded = not back by the end, mission goal still met; lost = goal missed where the clean run met it. "
              "Detection: cases in which a monitor raised a fault event after the onset: the monitor that was first "
              "most often (board: its E2E/SecOC checks and command timeout, reported by EMCY; driver: heartbeat, "
              "telemetry, applied against commanded, its controller's errors; FDIR: the actuator monitor, from the "
              "dynamics) with its first event, the other monitors that saw it too, median (max) latency in simulated "
              "milliseconds. 🟪 marks a cell with an undetected case: a failure whatever the effect.")
    return "\n".join(lines) + "\n\n" + legend + "\n"


def matrix_plot(rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    faults, laws, summary = cells(rows)
    order = list(EFFECTS) + ["undetected", "failed"]
    grid = np.full((len(faults), len(laws)), np.nan)
    for (fault, law), s in summary.items():
        grid[faults.index(fault), laws.index(law)] = order.index(s["colour"])
    fig, ax = plt.subplots(figsize=(2.4 * len(laws) + 2, 0.55 * len(faults) + 1.5))
    ax.imshow(grid, cmap=ListedColormap([COLOURS[e] for e in order]), vmin=-0.5, vmax=len(order) - 0.5, aspect="auto")
    for (fault, law), s in summary.items():
        latency = "undetected" if not s["detected"] else f"{s['detected_by']} {s['latency_median_s'] * 1e3:.0f} ms"
        ax.text(laws.index(law), faults.index(fault), f"{s['worst']}\n{latency}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(laws)), laws, fontsize=8)
    ax.set_yticks(range(len(faults)), faults, fontsize=8)
    ax.set_title("fault x attitude law: worst mission effect over the seeds (purple: undetected), "
                 "first monitor and detection latency (median)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_fault_report(results: Path, rows: list[dict], out_dir: Path) -> Path:
    plot = matrix_plot(rows, out_dir / "fault_matrix.png")
    table = matrix_markdown(rows)
    (out_dir / "fault_matrix.md").write_text(table)
    failures = [r for r in rows if r["status"] != "ok"]
    seeds = sorted({r["seed"] for r in rows})
    text = [f"# Fault campaign report: {results.name}", "",
            f"{len(rows)} cases, seeds {seeds[0]}-{seeds[-1]}; {len(failures)} failed (exception or timeout).", "",
            "## Failure-modes matrix", "", table, f"![fault matrix]({plot.name})"]
    if failures:
        text += ["", "## Failed cases", ""] + [f"- `{r['case_id']}` {r['status']}: {r['error']}" for r in failures[:50]]
    path = out_dir / "report.md"
    path.write_text("\n".join(text) + "\n")
    # Above the studies layer (bench.report): looked up by name, as the attitude metrics are.
    importlib.import_module(HTML_PAGE).write_html_beside(path)          # report.html with the matrix picture, for a browser
    return path
