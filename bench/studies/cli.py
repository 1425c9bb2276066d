"""`bench tune-lqr` and `bench compare-controllers`: the seed 003 studies from the command line."""
from __future__ import annotations

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
    # 4 rounds of +-1 decade stopped at J_u 8.72 (d_f 92 m); 6 rounds of +-2 decades reach the
    # seed's J_u <= 8: 6.95 N^2 with d_f 96.2 m, v_f 0.55 m/s (issue 17).
    p.add_argument("--rounds", type=int, default=6, help="grid refinements (default 6)")
    p.add_argument("--span", type=float, default=2.0, help="first grid's half-width in decades (default 2)")
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

    p = subparsers.add_parser("mpc-studies", help="seed 003 tasks 21 (horizon), 24 (S and v), 32 (tube vs MPC_TS)")
    p.add_argument("studies", nargs="*", metavar="STUDY", help="horizon, soft, tube (default: all three)")
    p.add_argument("--sequences", type=int, default=20, help="sampled disturbance sequences for the tube study")
    p.add_argument("--out", type=Path, default=None, help="also write the tables as markdown into this file")
    p.set_defaults(func=_mpc_studies)


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


def _mpc_studies(args) -> int:
    from rich.console import Console
    from rich.progress import Progress
    from rich.table import Table

    from bench.studies import mpc_studies

    if args.sequences < 1:
        return _bad_input(f"--sequences must be >= 1, got {args.sequences}")
    args.studies = args.studies or ["horizon", "soft", "tube"]
    unknown = [s for s in args.studies if s not in ("horizon", "soft", "tube")]
    if unknown:
        return _bad_input(f"unknown study {unknown[0]!r}: choose from horizon, soft, tube")
    titles = {
        "horizon": ("Task 21: MPC (17), MPC_TE (18), MPC_TS (19) from A, Q*, R*, N = 40 .. 20", mpc_studies.horizon_study, 33),
        "soft": ("Task 24: MPC_TS_SC (20) from C, N = 30, S = s I and v", mpc_studies.soft_constraint_study, 9),
        "tube": (f"Task 32: tube MPC against MPC_TS on the z-subsystem from x_z0^A, N = 50, {args.sequences} sampled "
                 "sequences and the constant worst case", None, args.sequences + 1),
    }
    console = Console(width=220)
    markdown = []
    for name in args.studies:
        title, fn, total = titles[name]
        with Progress(transient=True) as progress:
            task = progress.add_task(name, total=total)
            advance = lambda n: progress.advance(task, n)
            if name == "tube":
                rows = mpc_studies.tube_study(n_sequences=args.sequences, progress=advance)
            else:
                rows = fn(progress=advance)
        table = Table(title=title)
        cols = list(rows[0])
        for c in cols:
            table.add_column(c, justify="right")
        fmt = lambda v: (("yes" if v else "no") if isinstance(v, (bool, np.bool_)) else
                         f"{v:.4g}" if isinstance(v, float) else str(v))
        for r in rows:
            table.add_row(*[fmt(r[c]) for c in cols])
        console.print(table)
        markdown += [f"### {title}", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        markdown += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in rows] + [""]
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(markdown) + "\n")
    return 0
