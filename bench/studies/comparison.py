"""The seed-001 style comparison behind `bench compare-controllers`: LQR and the MPC family of
seed 003 from initial conditions A, B, C on linear (CWH) and nonlinear relative dynamics.

Each run applies the controller's input unsaturated, as the seed's simulate does, so a controller
that asks for more than u_max shows it as a violation instead of being clipped.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.config.controller import ControllerConfig
from bench.controller.factory import build_controller, weights_from_config
from bench.studies.metrics import POSITION_TOL_M, THRUST_TOL_N, fuel_delta_v_mps, traj_constraints, traj_cost
from bench.gnc.cwh import RendezvousParams
from bench.plant.dynamics import propagate

VARIANTS = ["mpc", "mpc_te", "mpc_ts", "mpc_ts_sc", "mpc_tube"]
LABELS = {"lqr": "LQR", "mpc": "MPC", "mpc_te": "MPC_TE", "mpc_ts": "MPC_TS", "mpc_ts_sc": "MPC_TS_SC",
          "mpc_tube": "MPC_TUBE (z) + MPC"}


@dataclass
class RunResult:
    initial_condition: str
    dynamics: str
    controller: str
    X_si: np.ndarray            # 6 x (N+1), m and m/s
    U_n: np.ndarray             # 3 x N
    infeasible_cycles: int
    solve_times_s: np.ndarray


def run_closed_loop(ctrl, x0_si, params: RendezvousParams, dynamics: str, n_steps: int):
    scaling = np.asarray(params.scaling)
    X = np.empty((6, n_steps + 1))
    U = np.empty((3, n_steps))
    X[:, 0] = x0_si
    infeasible, times = 0, np.empty(n_steps)
    for k in range(n_steps):
        u, info = ctrl.eval(scaling * X[:, k])
        U[:, k] = u
        infeasible += not info["ctrl_feas"]
        times[k] = info["solve_time"]
        X[:, k + 1] = propagate(X[:, k], u, params.time_step_s, params, dynamics)
    return X, U, infeasible, times


def run_comparison(args) -> int:
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    base = RendezvousParams.from_reference()
    params = base if args.steps is None else RendezvousParams.from_reference(n_steps=args.steps)
    if args.horizon < 1:
        raise ValueError(f"--horizon must be >= 1, got {args.horizon}")
    for ic in args.initial_conditions:
        params.initial_state_m_mps(ic)                       # names a bad initial condition early
    entries = [("lqr", "LQR q*", args.q)]
    if args.q_lqr_tuned is not None:
        entries.append(("lqr", "LQR tuned", args.q_lqr_tuned))
    entries += [(kind, LABELS[kind], args.q) for kind in VARIANTS]
    controllers = {}
    results: list[RunResult] = []
    with Progress(transient=True) as progress:
        task = progress.add_task("building controllers", total=len(entries))
        for kind, label, q in entries:
            cfg = ControllerConfig(type=kind, q_diag=list(q), horizon=args.horizon)
            controllers[label] = cfg
            progress.advance(task)
        task = progress.add_task("closed loops", total=len(entries) * len(args.initial_conditions) * len(args.dynamics))
        for ic in args.initial_conditions:
            for dyn in args.dynamics:
                for label, cfg in controllers.items():
                    ctrl = build_controller(cfg, params)    # fresh: no warm start carried across runs
                    X, U, infeasible, times = run_closed_loop(ctrl, params.initial_state_m_mps(ic), params, dyn,
                                                              params.n_steps)
                    results.append(RunResult(ic, dyn, label, X, U, infeasible, times))
                    progress.advance(task)

    table = Table(title=f"Seed 003 controllers, Q = diag({', '.join(f'{v:g}' for v in args.q)}), R = I, "
                        f"N = {args.horizon}, {params.n_steps} steps of {params.time_step_s:g} s")
    for col in ["IC", "dynamics", "controller", "feasible", "infeasible QPs", "J_u N^2", "J x'Qx+u'Ru", "fuel dv m/s", "d_f m",
                "v_f m/s", "state viol.", "input viol.", "solve med us", "solve p99 us"]:
        table.add_column(col, justify="right")
    rows = []
    for r in results:
        x_scaled = np.asarray(params.scaling)[:, None] * r.X_si
        m = traj_constraints(x_scaled, r.U_n, params)
        # Closed-loop quadratic cost (seed task 15) in the controller's own weights, scaled state.
        cost = traj_cost(x_scaled, r.U_n, *weights_from_config(controllers[r.controller]))
        pos = r.X_si[:3]
        state_viol = int(np.sum((np.maximum(np.abs(pos[0]), np.abs(pos[2])) > params.max_abs_position_xz_m + POSITION_TOL_M)
                                | (np.abs(pos[1]) > params.max_abs_position_y_m + POSITION_TOL_M)))
        input_viol = int(np.sum(np.max(np.abs(r.U_n), axis=0) > params.max_abs_thrust_n + THRUST_TOL_N))
        row = [r.initial_condition, r.dynamics, r.controller, "yes" if m.feasible else "no", str(r.infeasible_cycles),
               f"{m.input_cost_n2:.2f}", f"{cost:.4g}", f"{fuel_delta_v_mps(r.U_n, params.time_step_s, params.mass_kg):.1f}",
               f"{m.final_distance_m:.1f}", f"{m.final_speed_mps:.3f}", str(state_viol), str(input_viol),
               f"{np.median(r.solve_times_s) * 1e6:.0f}", f"{np.percentile(r.solve_times_s, 99) * 1e6:.0f}"]
        rows.append(row)
        table.add_row(*row)
    Console(width=200).print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    _write_markdown(args.out / "table.md", table.columns, rows)
    _plot(results, params, args.out)
    print(f"plots and table.md in {args.out}")
    return 0


def _write_markdown(path: Path, columns, rows) -> None:
    header = [str(c.header) for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    path.write_text("\n".join(lines) + "\n")


def _plot(results: list[RunResult], params: RendezvousParams, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_h = np.arange(params.n_steps + 1) * params.time_step_s / 3600.0
    for ic in sorted({r.initial_condition for r in results}):
        for dyn in sorted({r.dynamics for r in results}):
            runs = [r for r in results if r.initial_condition == ic and r.dynamics == dyn]
            fig, axes = plt.subplots(3, 1, figsize=(9, 10), sharex=True)
            for r in runs:
                axes[0].semilogy(t_h, np.linalg.norm(r.X_si[:3], axis=0), label=r.controller)
                axes[1].plot(t_h, np.maximum(np.abs(r.X_si[0]), np.abs(r.X_si[2])) / 1e3, label=r.controller)
                axes[2].step(t_h[:-1], np.max(np.abs(r.U_n), axis=0), where="post", label=r.controller)
            axes[0].axhline(params.max_final_position_m, color="k", ls="--", lw=0.8)
            axes[0].set_ylabel("distance to target (m)")
            axes[1].axhline(params.max_abs_position_xz_m / 1e3, color="k", ls="--", lw=0.8)
            axes[1].set_ylabel("max(|x|, |z|) (km)")
            axes[2].axhline(params.max_abs_thrust_n, color="k", ls="--", lw=0.8)
            axes[2].set_ylabel("max |u_i| (N)")
            axes[2].set_xlabel("time (h)")
            axes[0].legend(fontsize=8)
            axes[0].set_title(f"initial condition {ic}, {dyn} dynamics")
            fig.tight_layout()
            fig.savefig(out / f"compare_{ic}_{dyn}.png", dpi=110)
            plt.close(fig)
