"""MPC (17) time and accuracy against independent solvers, and the deadline mechanism's cost.

One process, one run. The QP sequence is MPC (17)'s closed loop from initial condition A and from B
(seed 003, Q*, R*, N = 30, 288 steps each). For every state, every solver is called in turn
(interleaved state by state, the order rotated each state, so machine load hits all alike), each
warm-started from its own previous call where it can be, each timed around its whole call (vectors
from the state, solve, first input). Accuracy: max |u_0 - u_0(quadprog)| over the sequence.

Solvers: the bench's MPC (explicit law, last active set, then proxsuite, each certified by the KKT
conditions); "proxsuite only", the bench's MPC before issue 17 (warm-started proxsuite, eps 1e-9,
duality-gap check); OSQP at eps 1e-9 with polishing (polish status counted); DAQP at primal
tolerance 1e-9 (the external anchor); quadprog (the reference, dense Goldfarb-Idnani).

Then the deadline mechanism: MPC (17) cycles through DeadlineMonitor in-process and through the
solver worker (interleaved, budget large enough that nothing misses) - the difference is the
worker's overhead; the round trip of a trivial law through shared memory + semaphores against a
multiprocessing Pipe; and a law made to take 50 ms against a 10 ms budget, 200 cycles at 30 ms,
the flight thread at SCHED_FIFO (10; real-time mode runs it at 10 or its process's 20) and without.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/bench_mpc.py [--repeats 3] [--solvers-only]

Targets (issue 17), on B's sequence: median MPC (17) <= 2x DAQP's and >= 5x faster than OSQP-1e-9
polished, every first input within 1e-7 N of quadprog; deadline mechanism's overhead <= 50 us
median (solver worker with the explicit fast path; the worker-only row is the baseline); with the
50 ms solve, command out within budget + 1 ms at p99.
"""
from __future__ import annotations

import argparse
import gc
import multiprocessing as mp
import time
from functools import partial

import daqp
import numpy as np
import osqp
import quadprog
from scipy import sparse

from bench.config.controller import DeadlineConfig
from bench.controller.deadline import DeadlineMonitor
from bench.gnc.cwh import RendezvousParams
from bench.gnc.mpc import MPC
from bench.gnc.qp import DenseBoxQP
from bench.runtime.priority import realtime_priority
from bench.runtime.solver_worker import WorkerLaw
from bench.studies.simulate import simulate

Q_STAR = np.diag([94.0, 0.1579, 300.0, 0.01, 0.10, 0.10])
R_STAR = np.eye(3)
NU = 3


class _SameQP:
    """The bench MPC's condensed QP for state x: (H, g, C, l, u, l_box, u_box)."""

    def __init__(self, ctrl: MPC):
        self.d = ctrl.qp_data

    def vectors(self, x):
        d = self.d
        return d.G @ x + d.g0, d.l0 + d.Dl @ x, d.u0 + d.Du @ x


class ProxsuiteOnly(_SameQP):
    """The bench's MPC before issue 17: warm-started proxsuite, no certificate."""

    def __init__(self, ctrl):
        super().__init__(ctrl)
        d = self.d
        self.qp = DenseBoxQP(d.H, d.A, d.C, d.l_box, d.u_box)

    def __call__(self, x):
        g, l, u = self.vectors(x)
        return self.qp._proxsuite(g, np.zeros(0), l, u, cold=False).y[:NU]


class OsqpPolished(_SameQP):
    def __init__(self, ctrl, eps=1e-9):
        super().__init__(ctrl)
        d = self.d
        n = d.H.shape[0]
        self.solver = osqp.OSQP()
        self.solver.setup(sparse.csc_matrix(np.triu(d.H)), np.zeros(n), sparse.csc_matrix(np.vstack([d.C, np.eye(n)])),
                          np.concatenate([d.l0, d.l_box]), np.concatenate([d.u0, d.u_box]), verbose=False,
                          eps_abs=eps, eps_rel=eps, polishing=True, warm_starting=True, max_iter=100000)
        self.polish_status: dict[int, int] = {}
        self.not_solved = 0

    def __call__(self, x):
        g, l, u = self.vectors(x)
        d = self.d
        self.solver.update(q=g, l=np.concatenate([l, d.l_box]), u=np.concatenate([u, d.u_box]))
        res = self.solver.solve()
        self.not_solved += res.info.status != "solved"
        self.polish_status[res.info.status_polish] = self.polish_status.get(res.info.status_polish, 0) + 1
        return res.x[:NU]


class Daqp(_SameQP):
    def __init__(self, ctrl, primal_tol=1e-9):
        super().__init__(ctrl)
        self.primal_tol = primal_tol
        self.failed = 0

    def __call__(self, x):
        g, l, u = self.vectors(x)
        d = self.d
        # simple bounds first, then the rows of C
        x_opt, _, exitflag, _ = daqp.solve(d.H, g, d.C, np.concatenate([d.u_box, u]), np.concatenate([d.l_box, l]),
                                           primal_tol=self.primal_tol)
        self.failed += exitflag < 1
        return np.asarray(x_opt)[:NU]


class Quadprog(_SameQP):
    def __call__(self, x):
        g, l, u = self.vectors(x)
        d = self.d
        n = d.H.shape[0]
        fu, fl = np.isfinite(u), np.isfinite(l)
        C = np.vstack([-d.C[fu], d.C[fl], -np.eye(n), np.eye(n)])
        b = np.concatenate([-u[fu], l[fl], -d.u_box, d.l_box])
        return quadprog.solve_qp(d.H, -g, C.T, b, 0)[0][:NU]


def closed_loop_states(model, params, ic, horizon):
    ctrl = MPC(Q_STAR, R_STAR, horizon, model)
    X, _, infos = simulate(model.to_scaled(params.initial_state_m_mps(ic)), ctrl, model, params.n_steps)
    return list(X[:, :-1].T), sum(i.get("path") != "explicit" for i in infos)


def pct(t, q):
    return float(np.percentile(t, q) * 1e6)


def interleaved(solvers: dict, states, repeats: int):
    """times[name] (s), first inputs[name] (first repeat), each solver warm on its own sequence."""
    names = list(solvers)
    times = {n: [] for n in names}
    firsts = {n: [] for n in names}
    for rep in range(repeats):
        for i, x in enumerate(states):
            k = (i + rep) % len(names)
            for name in names[k:] + names[:k]:
                t0 = time.perf_counter()
                u = solvers[name](x)
                times[name].append(time.perf_counter() - t0)
                if rep == 0:
                    firsts[name].append(np.asarray(u, float).copy())
    return {n: np.array(t) for n, t in times.items()}, {n: np.array(f) for n, f in firsts.items()}


# --- worker round trips ------------------------------------------------------------------------
class EchoLaw:
    def eval(self, x):
        return np.asarray(x)[:3], {"ctrl_feas": True, "solve_time": 0.0, "iterations": 0, "status": "ok"}


class SleepLaw:
    def __init__(self, delay_s):
        self.delay_s = delay_s

    def eval(self, x):
        time.sleep(self.delay_s)
        return np.asarray(x)[:3], {"ctrl_feas": True, "solve_time": self.delay_s, "iterations": 0, "status": "ok",
                                   "u_plan": np.zeros((5, 3))}


def _pipe_worker(conn):
    law = EchoLaw()
    while True:
        x = conn.recv()
        if x is None:
            return
        conn.send(law.eval(x))


def pipe_round_trips(n):
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    p = ctx.Process(target=_pipe_worker, args=(child,), daemon=True)
    p.start()
    x = np.ones(6)
    out = np.empty(n)
    for i in range(n + 50):
        t0 = time.perf_counter()
        parent.send(x)
        parent.recv()
        if i >= 50:
            out[i - 50] = time.perf_counter() - t0
    parent.send(None)
    p.join(2)
    return out


def shm_round_trips(n):
    w = WorkerLaw(partial(EchoLaw), nx=6, nu=3, plan_rows=1)
    w.wait_ready()
    x = np.ones(6)
    out = np.empty(n)
    for i in range(n + 50):
        t0 = time.perf_counter()
        w.evaluate(x, None)
        if i >= 50:
            out[i - 50] = time.perf_counter() - t0
    w.close()
    return out


def slow_solver_cycles(priority, n=200, budget_s=0.010, solve_s=0.050, period_s=0.030):
    w = WorkerLaw(partial(SleepLaw, solve_s), nx=6, nu=3, plan_rows=8)
    w.wait_ready()
    monitor = DeadlineMonitor(DeadlineConfig(budget_s=budget_s, fallback="shifted_plan"),
                              lqr_law=lambda x: np.zeros(3))
    out = []
    nxt = time.monotonic()
    with realtime_priority(priority) as granted:
        for _ in range(n):
            nxt += period_s
            s = time.monotonic_ns()
            monitor.run_cycle(np.ones(6), w, s)
            out.append((time.monotonic_ns() - s) / 1e9)
            time.sleep(max(0.0, nxt - time.monotonic()))
    stats = w.stats.summary()
    w.close()
    return np.array(out), stats, granted


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--solvers-only", action="store_true",
                        help="only the solver comparison (time and accuracy), not the deadline mechanism")
    args = parser.parse_args()

    params = RendezvousParams.from_reference()
    model = params.scaled
    print(f"MPC (17), N = {args.horizon}, Q*, R*: closed-loop QP sequences from A and B, {args.repeats} repeats, "
          "solvers interleaved state by state\n")
    results = {}
    for ic in "AB":
        states, constrained = closed_loop_states(model, params, ic, args.horizon)
        ctrl = MPC(Q_STAR, R_STAR, args.horizon, model)
        osqp_s, daqp_s = OsqpPolished(ctrl), Daqp(ctrl)
        solvers = {
            "MPC (17) bench": lambda x, c=ctrl: c.eval(x)[0],
            "proxsuite only (before)": ProxsuiteOnly(ctrl),
            "OSQP 1e-9 polished": osqp_s,
            "DAQP 1e-9": daqp_s,
            "quadprog (reference)": Quadprog(ctrl),
        }
        for x in states[:10]:                          # imports, first factorisations
            for s in solvers.values():
                s(x)
        ctrl.solver.paths.clear()
        gc.disable()
        times, firsts = interleaved(solvers, states, args.repeats)
        gc.enable()
        ref = firsts["quadprog (reference)"]
        print(f"### From {ic}: {len(states)} QPs, {constrained} with an active constraint; bench MPC paths "
              f"{dict(ctrl.solver.paths)} (rest explicit)\n")
        print("| solver | median us | p90 us | p99 us | max us | max abs(u0 - u0 quadprog) N |")
        print("|---|---|---|---|---|---|")
        for name, t in times.items():
            err = float(np.max(np.abs(firsts[name] - ref)))
            print(f"| {name} | {pct(t, 50):.1f} | {pct(t, 90):.1f} | {pct(t, 99):.1f} | {t.max() * 1e6:.1f} | {err:.1e} |")
        print(f"\nOSQP: not solved {osqp_s.not_solved}, polish status counts {osqp_s.polish_status} (1 polished, "
              f"0 not needed: no active constraint, -1 failed); DAQP failed {daqp_s.failed}")
        results[ic] = (times, firsts)
        med = {n: np.median(t) for n, t in times.items()}
        print(f"median ratios: MPC / DAQP = {med['MPC (17) bench'] / med['DAQP 1e-9']:.2f}, "
              f"OSQP / MPC = {med['OSQP 1e-9 polished'] / med['MPC (17) bench']:.1f}, "
              f"proxsuite-only / MPC = {med['proxsuite only (before)'] / med['MPC (17) bench']:.1f}\n")

    times, firsts = results["B"]
    med = {n: np.median(t) for n, t in times.items()}
    err = float(np.max(np.abs(firsts["MPC (17) bench"] - firsts["quadprog (reference)"])))
    ok_speed = med["MPC (17) bench"] <= 2 * med["DAQP 1e-9"] and med["OSQP 1e-9 polished"] >= 5 * med["MPC (17) bench"]
    print(f"targets on B (<= 2x DAQP, >= 5x OSQP, 1e-7 N): {'met' if ok_speed and err <= 1e-7 else 'NOT met'}\n")
    if args.solvers_only:
        return 0

    # --- deadline mechanism ------------------------------------------------------------------
    states, _ = closed_loop_states(model, params, "B", args.horizon)
    in_process = MPC(Q_STAR, R_STAR, args.horizon, model)
    cfg = DeadlineConfig(budget_s=1.0, fallback="shifted_plan")
    print("### Deadline mechanism, MPC (17) on B's sequence (interleaved with the in-process cycle, no misses)\n")
    print("Worker only: every cycle a round trip to the solver worker (the baseline). Fast path: the flight "
          "process answers on the MPC's explicit law where its KKT certificate holds, the rest go to the worker.\n")
    print("| cycle | p50 us | p90 us | p99 us | max us | overhead at p50 us |")
    print("|---|---|---|---|---|---|")
    notes = []
    for label, flight_prio, worker_prio in [("default scheduler", 0, 0),
                                             ("flight SCHED_FIFO 10", 10, 0),
                                             ("flight FIFO 10, worker FIFO 5", 10, 5)]:
        workers = {fast: WorkerLaw(partial(MPC, Q_STAR, R_STAR, args.horizon, model), nx=6, nu=3,
                                   plan_rows=args.horizon, worker_priority=worker_prio, explicit_fast_path=fast)
                   for fast in (False, True)}
        for w in workers.values():
            w.wait_ready()
        mon_in, mon_w, mon_f = DeadlineMonitor(cfg), DeadlineMonitor(cfg), DeadlineMonitor(cfg)
        t_in, t_w, t_f, to_worker, max_diff, max_diff_explicit = [], [], [], [], 0.0, 0.0
        with realtime_priority(flight_prio):
            for rep in range(args.repeats):
                for x in states:
                    s = time.monotonic_ns()
                    out = mon_in.run_cycle(x, in_process.eval, s)
                    t_in.append((time.monotonic_ns() - s) / 1e9)
                    to_worker.append(out.info.get("path") != "explicit")
                    s = time.monotonic_ns()
                    mon_w.run_cycle(x, workers[False], s)
                    t_w.append((time.monotonic_ns() - s) / 1e9)
                    s = time.monotonic_ns()
                    out_f = mon_f.run_cycle(x, workers[True], s)
                    t_f.append((time.monotonic_ns() - s) / 1e9)
                    diff = float(np.max(np.abs(out_f.thrust_n - out.thrust_n)))
                    if out.info.get("path") == "explicit":
                        max_diff_explicit = max(max_diff_explicit, diff)      # must be 0: same code
                    else:
                        max_diff = max(max_diff, diff)       # the worker's own warm-start history
        explicit = workers[True].stats.explicit_cycles
        for w in workers.values():
            w.close()
        t_in, t_w, t_f, to_worker = np.array(t_in), np.array(t_w), np.array(t_f), np.array(to_worker)
        for name, t in [(f"in-process, {label}", t_in), (f"solver worker only, {label}", t_w),
                        (f"solver worker + explicit fast path, {label}", t_f)]:
            print(f"| {name} | {pct(t, 50):.1f} | {pct(t, 90):.1f} | {pct(t, 99):.1f} | {t.max() * 1e6:.1f} | "
                  f"{pct(t, 50) - pct(t_in, 50):.1f} |")
        on_w = to_worker
        notes.append(f"{label}: fast path answered {explicit} of {t_f.size} cycles in the flight process "
                     f"(max |u - u in-process| {max_diff_explicit:.1e} N on them); the {int(on_w.sum())} others "
                     f"went to the worker (max |u - u in-process| {max_diff:.1e} N), their p50: in-process "
                     f"{pct(t_in[on_w], 50):.1f} us, worker only {pct(t_w[on_w], 50):.1f} us, fast path "
                     f"{pct(t_f[on_w], 50):.1f} us")
        assert mon_w.counter.misses == 0 and mon_in.counter.misses == 0 and mon_f.counter.misses == 0
    print("\n" + "\n".join(f"- {n}" for n in notes))
    print("\n(overhead target <= 50 us at the median)\n")

    n = 2000
    shm, pipe = shm_round_trips(n), pipe_round_trips(n)
    print("| round trip of a trivial law, 2000 calls | p50 us | p99 us |")
    print("|---|---|---|")
    print(f"| shared memory + semaphores (WorkerLaw) | {pct(shm, 50):.1f} | {pct(shm, 99):.1f} |")
    print(f"| multiprocessing Pipe (pickled arrays) | {pct(pipe, 50):.1f} | {pct(pipe, 99):.1f} |\n")

    print("### A law taking 50 ms against a 10 ms budget, 200 cycles 30 ms apart\n")
    print("| flight thread | command out p50 ms | p99 ms | max ms | timeouts | late results discarded | busy cycles |")
    print("|---|---|---|---|---|---|---|")
    for prio, label in [(10, "SCHED_FIFO 10"), (0, "default scheduler")]:
        t, st, granted = slow_solver_cycles(prio)
        t = t[t > 0.001]            # cycles that waited (the others found the worker busy: no wait)
        lab = label if granted or prio == 0 else label + " (refused)"
        print(f"| {lab} | {np.percentile(t, 50) * 1e3:.2f} | {np.percentile(t, 99) * 1e3:.2f} | {t.max() * 1e3:.2f} | "
              f"{st['timeouts']} | {st['late_results']} | {st['busy_cycles']} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
