"""The MILQR plan against the attitude flown: the planner's plans (`plan/attitude`, each with its N+1
states and N dipoles, sample k at start_time_s + k dt_s) beside the plant's truth (trajectory.npz):
the angle to the plan's target attitude, the body rate per axis and the dipole per axis, planned
(each plan a thin dashed line, from where it starts) and flown or commanded (solid)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bench.bus import keys  # noqa: E402
from bench.report import plots  # noqa: E402

PLOT_FILE = "attitude_plan.png"


def angle_to_deg(q_wxyz: np.ndarray, target_wxyz) -> np.ndarray:
    """The rotation angle (deg) from each attitude to the target."""
    q = np.asarray(q_wxyz, float)
    t = np.asarray(target_wxyz, float)
    dot = np.abs(q @ t) / (np.linalg.norm(q, axis=1) * np.linalg.norm(t))
    return np.rad2deg(2.0 * np.arccos(np.clip(dot, 0.0, 1.0)))


def plans_of(run) -> list[dict]:
    plans = [m.body for m in run.on(keys.PLAN_ATTITUDE)]
    return sorted(plans, key=lambda p: (p["start_time_s"], p["plan_id"]))


def plan_figure(run, path: Path) -> Path | None:
    """The figure, or None where the run has no plan or no attitude trajectory."""
    trajectory = run.trajectory
    plans = plans_of(run)
    if not plans or "att_q_wxyz" not in trajectory:
        return None
    t = np.asarray(trajectory["att_time_s"], float)
    end_s = float(t[-1])
    fig, axes = plt.subplots(7, 1, figsize=(11, 15), sharex=True)
    target = plans[-1]["target_wxyz"]
    axes[0].plot(t, angle_to_deg(trajectory["att_q_wxyz"], target), color="k", lw=1.2, label="flown (truth)")
    omega = np.rad2deg(np.asarray(trajectory["att_omega_radps"], float))
    commanded = np.asarray(trajectory["att_dipole_commanded_am2"], float)
    for i in range(3):
        axes[1 + i].plot(t, omega[:, i], color="k", lw=1.2, label="flown (truth)")
        axes[4 + i].step(t, commanded[:, i], where="post", color="k", lw=1.2, label="commanded (controller)")
    for n, plan in enumerate(plans):
        states = np.asarray(plan["states"], float)
        dipoles = np.asarray(plan["dipoles_am2"], float)
        times = plan["start_time_s"] + plan["dt_s"] * np.arange(len(states))
        keep = times <= end_s + plan["dt_s"]
        if not keep.any():
            continue
        # One colour and one legend entry a plan: a replan is a new plan, drawn from its own start.
        label = (f"MILQR plan {n + 1} of {len(plans)}, from {plan['start_time_s']:.0f} s" if len(plans) > 1
                 else "plan (MILQR)")
        colour = f"C{n % 10}"
        axes[0].plot(times[keep], angle_to_deg(states[keep, :4], plan["target_wxyz"]), "--", color=colour, lw=1,
                     label=label)
        for i in range(3):
            axes[1 + i].plot(times[keep], np.rad2deg(states[keep, 4 + i]), "--", color=colour, lw=1, label=label)
            k = keep[: len(dipoles)]
            if k.any():
                axes[4 + i].step(times[: len(dipoles)][k], dipoles[k, i], where="post", ls="--", color=colour, lw=1,
                                 label=label)
    axes[0].set_ylabel("angle to target [deg]")
    for i, axis in enumerate("xyz"):
        axes[1 + i].set_ylabel(f"ω{axis} [deg/s]")
        axes[4 + i].set_ylabel(f"dipole {axis} [A m²]")
    axes[-1].set_xlabel("simulated time [s]")
    axes[0].set_title("MILQR plan against the attitude flown")
    for a in axes:
        a.grid(True, alpha=0.3)
        a.legend(fontsize="small", loc="upper right")
    return plots.save(fig, path, dpi=80)
