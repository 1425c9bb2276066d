"""`bench tune-lqr` and `bench compare-controllers`: the seed 003 studies from the command line."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.data import load_reference
from bench.gnc.cwh import RendezvousParams

SEED_Q_STAR = tuple(load_reference()["weights"]["q_star"])


def add_commands(subparsers) -> None:
    p = subparsers.add_parser("tune-lqr", help="LQR tuning study of seed 003 (tasks 10, 11)")
    p.add_argument("--initial-condition", default="A", help="A, B or C (default A)")
    p.add_argument("--q-start", type=float, nargs=6, default=list(SEED_Q_STAR), metavar="Q",
                   help="centre of the first grid (default the seed's q*)")
    p.add_argument("--rounds", type=int, default=4, help="grid refinements (default 4)")
    p.add_argument("--span", type=float, default=1.0, help="first grid's half-width in decades (default 1)")
    p.set_defaults(func=_tune_lqr)

    p = subparsers.add_parser("compare-controllers",
                              help="LQR and the MPC family from A, B, C on linear and nonlinear dynamics")
    p.add_argument("--out", type=Path, default=Path("runs/compare-controllers"), help="directory for the plots")
    p.add_argument("--q", type=float, nargs=6, default=list(SEED_Q_STAR), metavar="Q",
                   help="Q = diag(q) for every controller (default the seed's q*)")
    p.add_argument("--q-lqr-tuned", type=float, nargs=6, default=None, metavar="Q",
                   help="also run an LQR with these weights (e.g. the result of bench tune-lqr)")
    p.add_argument("--horizon", type=int, default=30)
    p.add_argument("--steps", type=int, default=None, help="steps per run (default the reference's 288)")
    p.add_argument("--dynamics", nargs="+", default=["cwh", "nonlinear"], choices=["cwh", "nonlinear"])
    p.add_argument("--initial-conditions", nargs="+", default=["A", "B", "C"])
    p.set_defaults(func=_compare)


def _bad_input(message: str) -> int:
    from rich.console import Console

    Console(stderr=True).print(f"[red]error:[/red] {message}")
    return 2


def _tune_lqr(args) -> int:
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    from bench.studies.tuning import lqr_tuning, refine_q

    params = RendezvousParams.from_reference()
    try:
        x0 = params.scaled.to_scaled(params.initial_state_m_mps(args.initial_condition))
        if args.rounds < 1 or args.span <= 0:
            raise ValueError("--rounds must be >= 1 and --span > 0")
        per_round = 5 ** 4 + 9 ** 2
        with Progress(transient=True) as progress:
            task = progress.add_task("LQR tuning", total=args.rounds * per_round)
            q_best, _ = refine_q(x0, args.q_start, params, rounds=args.rounds, span_decades=args.span,
                                 progress=lambda n: progress.advance(task, n))
    except (KeyError, ValueError) as exc:
        return _bad_input(str(exc).strip("'\""))
    candidates = np.array([SEED_Q_STAR, args.q_start, q_best])
    rows, best = lqr_tuning(x0, candidates, params)
    table = Table(title=f"LQR tuning from initial condition {args.initial_condition} (R = I, 2 days)")
    for col in ["", "q = [q_x, q_y, q_z, q_vx, q_vy, q_vz]", "s_max m", "y_max m", "u_max N", "J_u", "d_f m",
                "v_f m/s", "feasible"]:
        table.add_column(col, justify="right")
    for name, row in zip(["seed q*", "start", "best found"], rows):
        m = row.metrics
        table.add_row(name, ", ".join(f"{v:.3g}" for v in row.q_diag), f"{m.max_abs_position_xz_m:.0f}",
                      f"{m.max_abs_position_y_m:.0f}", f"{m.max_abs_thrust_n:.3f}", f"{m.input_cost_n2:.3f}",
                      f"{m.final_distance_m:.1f}", f"{m.final_speed_mps:.4f}", "yes" if m.feasible else "no")
    Console(width=160).print(table)
    if best is None:
        Console().print("no feasible q found")
        return 1
    print("best q = [" + ", ".join(f"{v:.6g}" for v in rows[best].q_diag) + "]")
    return 0


def _compare(args) -> int:
    from bench.studies.comparison import run_comparison

    try:
        return run_comparison(args)
    except (KeyError, ValueError) as exc:
        return _bad_input(str(exc).strip("'\""))
