"""FDIR actuator monitor for the magnetorquers: is each coil giving the torque the law asked of it?

Pure algorithm, no middleware (bench/controller/attitude_cycle.py runs it after the law, in the
controller process and in the in-process loop alike). Per step it takes only what the flight side
has: the estimate (attitude, body rate with the gyro bias removed, the bias, the body field) and
the dipole it commanded, with what the flight side believes (inertia, the board's quantisation
and limit, the calibrated residual dipole, the orbit for the gravity gradient).

Model (body axes). Coil j applies g_j m_j + s_j of the commanded m_j: healthy (g, s) = (1, 0),
open coil (0, 0), reversed (-1, 0), weak or mis-calibrated (g, 0), stuck at a value (0, s). The
body's angular momentum h = J omega obeys dh/dt = sum_j (g_j m_j + s_j) e_j x B + tau_gg +
m_res x B - omega x J omega, the torque held over each step as the board holds its dipole. Over a
window of N steps, the rate samples the estimate gives are

    omega_k = J^-1 [h_0 + dt sum_{i<k} tau_i - (dt/2) tau_{k-1}] + n_k,   n_k ~ N(0, sigma^2 I)

(the last term when the gyro sample is the mean rate over the step before it, as the plant's
integrating gyro gives; without it for a rate sampled at the instant: the `truth` estimator; the
gyroscopic term is taken at the step's middle). The samples are linear in h_0 (a nuisance, which
also absorbs a constant gyro-bias error) and in the coil parameters, so each hypothesis is one
weighted least-squares fit over the window, with its covariance (the sensor noise scaled by the
fit's own variance factor when that is larger: unmodelled torques widen the covariance rather than
raise alarms). The sums are what make it sensitive: the momentum a coil's torque adds grows with
the window, the rate noise does not.

Per coil, the single-fault hypothesis (`ActuatorMonitor.isolation_fits`): that coil differs from the
belief by (dg, ds) from an onset on, the others as believed, with h_0 and the error of the believed
residual dipole as nuisances over the whole window; every onset in the window is tried, the
maximum-likelihood one kept. Every `evaluate_every_s`:
- excitation: a coil is judged only where its gain's standard deviation is at most `max_gain_std`.
  A coil that is hardly commanded, or whose torque is small because m_j e_j lies near B, gives a
  wide gain: "not observable", no alarm either way;
- detection: the Mahalanobis distance d^2 of (g, s) to the nominal box |g - 1| <= gain_tolerance,
  |s| <= offset_tolerance_am2 (chi-square with 2 degrees of freedom at the box's edge), the largest
  over a few onsets and the best one, above `threshold`;
- isolation: while a coil is alarmed, the coil whose hypothesis leaves the least residual, by
  `isolation_margin` over the next, is the faulty one, whichever coil raised the alarm;
- class (`classify`): "open" or "reversed" when gain 0 or -1 is consistent, else "gain" (wrong
  gain), read with the offset held at 0 unless the data demand one; with an offset, "stuck" (a
  constant dipole whatever is commanded) when gain 0 is consistent. `persistence` evaluations in a
  row must agree on coil and class.
A detected coil is latched: its identified model (g, s) is believed from its onset on and the window
restarts, so the monitor goes on judging the other two, and the accommodation (`accommodate`) can act.

Thresholds, the false-alarm count on the built-in scenarios, the signal-to-noise ratio of a
reversed coil and the detection latencies: docs/fdir.md.

Its terms (settings, beliefs, events) are bench/gnc/coil_faults.py; reading a coil's fit
(detection distance, class) bench/gnc/coil_judgement.py.
"""
from __future__ import annotations

from collections import deque

import numpy as np

from bench.gnc.coil_faults import (
    AXES, CLASS_MODELS, CoilBelief, CoilEstimate, FdirEvent, MonitorSettings, OnboardActuatorModel,
)
from bench.gnc.coil_judgement import IsolationFit, box_distance2, classify
from bench.gnc.quaternion import cross3, rotation_matrix


def _unit_cross_field(field_t: np.ndarray) -> np.ndarray:
    """(..., 3 coils, 3): e_j x B for each coil j."""
    bx, by, bz = field_t[..., 0], field_t[..., 1], field_t[..., 2]
    zero = np.zeros_like(bx)
    return np.stack([np.stack([zero, -bz, by], -1), np.stack([bz, zero, -bx], -1),
                     np.stack([-by, bx, zero], -1)], -2)


class ActuatorMonitor:
    """Call `step` once per control cycle with a valid estimate and the dipole commanded on it;
    `reset` when the estimate is missing or invalid (the window restarts)."""

    def __init__(self, model: OnboardActuatorModel, settings: MonitorSettings | None = None):
        self.model = model
        self.settings = settings = settings or MonitorSettings()
        dt = model.step_s
        self.inertia = np.asarray(model.inertia_kgm2, float)
        self.inertia_inverse = np.linalg.inv(self.inertia)
        self.window_steps = max(3, int(round(settings.window_s / dt)))
        self.min_steps = max(3, int(round(settings.min_window_s / dt)))
        self.evaluate_every = max(1, int(round(settings.evaluate_every_s / dt)))
        # window_steps samples need one record more: the torque before the first sample
        self._records: deque[np.ndarray] = deque(maxlen=self.window_steps + 1)
        self.beliefs = [CoilBelief() for _ in AXES]
        self.events: list[FdirEvent] = []
        self._streak = 0                                   # evaluations in a row isolating _streak_key
        self._streak_key: tuple[int, str] | None = None    # (coil, class)
        self._alarm_since: float | None = None             # first evaluation of the current alarm
        self._alarmed: set[int] = set()                    # coils whose last judged d^2 was above the threshold
        self._window_cache = None
        self._steps = 0
        self.evaluations = 0
        self.judged = [0, 0, 0]
        self.not_observable = [0, 0, 0]
        self.peak_statistic = [0.0, 0.0, 0.0]
        self.peak_statistic_time_s: list[float | None] = [None, None, None]
        # The calibration's figures: over the judged evaluations the largest |g - 1| and |s|
        # estimated; with keep_statistics (a study, not a run: they grow with the run), at every
        # evaluation each coil's gain sigma over the whole window (its excitation) and d^2.
        self.worst_gain_deviation = 0.0
        self.worst_offset_am2 = 0.0
        self.keep_statistics = False
        self.gain_std_window: list[list[float]] = [[], [], []]
        self.statistics: list[tuple[float, int, float]] = []   # (time, axis, d^2) of judged evaluations
        self.resets = 0
        self.last: list[CoilEstimate | None] = [None, None, None]

    # --- input ----------------------------------------------------------------------------------
    def applied_am2(self, commanded_am2: np.ndarray) -> np.ndarray:
        """The dipole the board sets for a command: its DAC step, then its limit (its datasheet)."""
        m = np.asarray(commanded_am2, float)
        if self.model.board_model is not None:
            return np.asarray(self.model.board_model(m), float)
        if self.model.dipole_resolution_am2:
            m = np.round(m / self.model.dipole_resolution_am2) * self.model.dipole_resolution_am2
        return np.clip(m, -self.model.dipole_limit_am2, self.model.dipole_limit_am2)

    def reset(self) -> None:
        if self._records:
            self.resets += 1
        self._records.clear()
        self._clear()

    def step(self, time_s: float, q_wxyz, omega_radps, gyro_bias_radps, field_body_t,
             commanded_am2) -> list[FdirEvent]:
        """Record one cycle; evaluate when due; the faults detected at this cycle (usually none)."""
        q, omega, bias, field_t, m = (np.asarray(v, float) for v in
                                      (q_wxyz, omega_radps, gyro_bias_radps, field_body_t, commanded_am2))
        if not all(np.all(np.isfinite(v)) for v in (q, omega, bias, field_t, m)) or not np.any(field_t):
            self.reset()
            return []
        dt = self.model.step_s
        if self._records and abs(time_s - self._records[-1][0] - dt) > 1e-6 * max(1.0, dt):
            self.reset()      # a gap: the sums would miss a step's torque
        # Known torques over the coming step: gravity gradient, residual dipole; the gyroscopic
        # term apart (_window_arrays takes it at the step's middle, from the next sample too).
        known = cross3(np.asarray(self.model.residual_dipole_am2, float), field_t)
        gyroscopic = -cross3(omega, self.inertia @ omega)
        if self.model.position_m is not None:
            r_body = rotation_matrix(q).T @ self.model.position_m(time_s)
            r = float(np.linalg.norm(r_body))
            r_hat = r_body / r
            known = known + 3.0 * self.model.mu_m3ps2 / r**3 * cross3(r_hat, self.inertia @ r_hat)
        # The raw gyro (omega + bias): the bias estimate jumps at each keyframe; a constant bias is h_0's.
        # One flat row per step: time, raw rate, applied dipole, field, known torque, gyroscopic.
        self._records.append(np.concatenate([[float(time_s)], omega + bias, self.applied_am2(m), field_t, known,
                                             gyroscopic]))
        self._steps += 1
        samples = len(self._records) - 1
        if samples < self.min_steps or self._steps % self.evaluate_every:
            return []
        return self._evaluate()

    # --- the fit --------------------------------------------------------------------------------
    def _window(self):
        """The window's arrays: samples 1..N (raw rate), records 0..N (applied dipole, field, known
        torque), the coil beliefs per record (a latched coil is healthy before its onset), e_j x B.
        Kept until the window or the beliefs change (an evaluation fits it several times)."""
        key = (self._steps, len(self._records), tuple((b.gain, b.offset_am2, b.onset_s) for b in self.beliefs))
        if self._window_cache is not None and self._window_cache[0] == key:
            return self._window_cache[1]
        self._window_cache = (key, self._window_arrays())
        return self._window_cache[1]

    def _window_arrays(self):
        rows = np.array(self._records)
        time_s = rows[:, 0]
        y = rows[1:, 1:4]
        applied = rows[:, 4:7]
        field_t = rows[:, 7:10]
        known = rows[:, 10:13]
        # -omega x J omega over step i (held for the coil torques, which the board holds, it is
        # not): at the step's middle, second-order in the step. At 8 deg/s (attitude_detumble_sgp4)
        # it is about ten times the coil torques (omega^2 (J_max - J_min) against m |B|).
        gyroscopic = rows[:, 13:16]
        following = np.concatenate([gyroscopic[1:], gyroscopic[-1:]])
        if self.model.rate_sample == "mean":     # sample i+1 is the mean rate over step i
            known = known + following
        else:                                    # instant rates at the step's ends
            known = known + 0.5 * (gyroscopic + following)
        gain_b, offset_b = np.ones((len(rows), 3)), np.zeros((len(rows), 3))
        for j, b in enumerate(self.beliefs):
            if b.fault is not None:
                after = time_s >= b.onset_s
                gain_b[after, j], offset_b[after, j] = b.gain, b.offset_am2
        ecb = _unit_cross_field(field_t)                            # (N+1, coil, 3)
        torque = np.einsum("kj,kjc->kc", applied * gain_b + offset_b, ecb) + known
        phi = np.empty((len(rows), 3, 6))                        # regressors of (dg_j, ds_j)
        phi[:, :, 0::2] = np.transpose(applied[:, :, None] * ecb, (0, 2, 1))
        phi[:, :, 1::2] = np.transpose(ecb, (0, 2, 1))
        return time_s, y, torque, phi, gain_b[-1], offset_b[-1]

    def _cumulative(self, x: np.ndarray, n: int) -> np.ndarray:
        """Sample k (1..N): dt sum_{i=1}^{k-1} x_i [- dt/2 x_{k-1} for a mean-rate sample]."""
        dt = self.model.step_s
        c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x[1:n], axis=0)]) * dt
        return c - 0.5 * dt * x[:n] if self.model.rate_sample == "mean" else c

    def isolation_fits(self, coil: int, onsets: list[int], keep: list[int] = ()) -> "IsolationFit":
        """The single-fault hypothesis for `coil` (`isolation_fits_all`)."""
        return self.isolation_fits_all([coil], onsets, keep)[0]

    def isolation_fits_all(self, coils: list[int], onsets: list[int], keep: list[int] = ()) -> list["IsolationFit"]:
        """The single-fault hypothesis of each of `coils`: that coil differs from the belief by
        (dg, ds) from the best of `onsets` on (the maximum-likelihood onset of an abrupt change),
        the others as believed, with two nuisances over the whole window: h_0 and the error of the
        believed residual dipole (a constant dipole in every coil's axis: the calibration is known
        to a few 1e-4 A m^2 at best, and attitude_detumble_sgp4 flies with none, 1e-3 A m^2 off).

        Normal equations from suffix sums over the window, all onsets and coils at once: the
        fault's regressors from onset o are the cumulative sums less their value at o, c_k - S_o
        for k > o (0 before), so each onset costs a few 8 x 8 products (a coil's fit over every
        onset of a 60-sample window: ~0.2 ms). `keep`: onsets (of `onsets`) whose estimate and
        covariance `by_onset` gives, besides the best one."""
        s = self.settings
        dt = self.model.step_s
        time_s, y, torque, phi, gain_now, offset_now = self._window()
        n = len(time_s) - 1
        g_mat = self.inertia_inverse / self.model.gyro_noise_std_radps
        b = (y - self._cumulative(torque, n) @ self.inertia_inverse.T) / self.model.gyro_noise_std_radps
        d_all = np.einsum("ab,kbp->kap", g_mat, self._cumulative(phi, n))      # (N, 3, 6): G c_k, every (dg, ds)
        base = np.concatenate([np.broadcast_to(g_mat, (n, 3, 3)), d_all[:, :, 1::2]], axis=2)  # h_0, residual error
        prefix = np.concatenate([np.zeros((2, 3, 6)), np.cumsum(phi[1:n], axis=0)]) * dt      # S_o, o = 0..N
        onsets = np.asarray(onsets, int)
        e_all = np.einsum("ab,obp->oap", g_mat, prefix[onsets])                 # (O, 3, 6): G S_o
        e_all[onsets == 0] = 0.0                                                # no mask from the start

        def suffix(x):
            return np.concatenate([np.cumsum(x[::-1], axis=0)[::-1], np.zeros((1,) + x.shape[1:])])[onsets]

        sd_all, sdd_all = suffix(d_all), suffix(np.einsum("kap,kaq->kpq", d_all, d_all))
        sdb_all, sb = suffix(np.einsum("kap,ka->kp", d_all, b)), suffix(b)
        sbd_all, sbase = suffix(np.einsum("kap,kaq->kpq", base, d_all)), suffix(base)
        m = (n - onsets)[:, None, None].astype(float)
        count = len(onsets)
        h = np.zeros((len(coils), count, 8, 8))
        rhs = np.zeros((len(coils), count, 8))
        h[:, :, :6, :6] = np.einsum("kap,kaq->pq", base, base)
        rhs[:, :, :6] = np.einsum("kap,ka->p", base, b)
        for i, coil in enumerate(coils):
            cols = slice(2 * coil, 2 * coil + 2)
            e, sd = e_all[:, :, cols], sd_all[:, :, cols]
            cross = sbd_all[:, :, cols] - np.einsum("oap,oaq->opq", sbase, e)
            h[i, :, :6, 6:], h[i, :, 6:, :6] = cross, np.transpose(cross, (0, 2, 1))
            et_sd = np.einsum("oap,oaq->opq", e, sd)
            h[i, :, 6:, 6:] = (sdd_all[:, cols, cols] - et_sd - np.transpose(et_sd, (0, 2, 1))
                               + m * np.einsum("oap,oaq->opq", e, e))
            rhs[i, :, 6:] = sdb_all[:, cols] - np.einsum("oap,oa->op", e, sb)
        prior = np.diag([0.0] * 3 + [1.0 / s.prior_residual_std_am2**2] * 3
                        + [1.0 / s.prior_gain_std**2, 1.0 / s.prior_offset_std_am2**2])
        bb = float(np.sum(b * b))
        position = {int(o): i for i, o in enumerate(onsets)}

        def solve(size, wanted):
            """Every coil and onset with the first `size` parameters (8, or 7: the offset held)."""
            hh, rr, pp = h[..., :size, :size], rhs[..., :size], prior[:size, :size]
            x = np.linalg.solve(hh + pp, rr[..., None])[..., 0]
            rss = bb - 2 * np.einsum("cop,cop->co", x, rr) + np.einsum("cop,copq,coq->co", x, hh, x)
            best = np.argmin(rss, axis=1)
            out = []
            for i in range(len(coils)):
                factor = max(1.0, float(rss[i, best[i]]) / max(1, 3 * n - size))
                rows = sorted({int(best[i])} | {position[o] for o in wanted if o in position})
                out.append((int(best[i]), factor, dict(zip(rows, factor * np.linalg.inv(hh[i, rows] + pp)))))
            return x, rss, out

        x, rss, full = solve(8, keep)
        x7, rss7, held = solve(7, ())
        fits = []
        for i, coil in enumerate(coils):
            (best, factor, covariances), (best7, _, cov7) = full[i], held[i]
            thetas = x[i, :, 6:] + np.array([gain_now[coil], offset_now[coil]])
            by_onset = {int(onsets[r]): (thetas[r], c[6:, 6:]) for r, c in covariances.items()}
            fits.append(IsolationFit(
                coil, thetas[best], covariances[best][6:, 6:], factor, int(onsets[best]), float(time_s[onsets[best]]),
                float(rss[i, best]), by_onset, float(x7[i, best7, 6] + gain_now[coil]),
                float(np.sqrt(cov7[best7][6, 6])), float(time_s[onsets[best7]]), float(rss7[i, best7])))
        return fits

    def detection_onsets(self) -> list[int]:
        """The onsets `_evaluate` detects on: the window's start and `detection_onsets` - 1 more,
        evenly spread, the last leaving min_window_s / 2 after it (a fault is seen on the part of
        the window after it without being diluted by the part before)."""
        n = len(self._records) - 1
        last = n - max(3, int(round(0.5 * self.settings.min_window_s / self.model.step_s)))
        count = max(1, self.settings.detection_onsets)
        return sorted({0} | {int(round(i * n / count)) for i in range(1, count) if round(i * n / count) <= last})

    def onset_candidates(self) -> list[int]:
        """Record indices tried as a fault's onset: the window's start, then every onset_step_s,
        leaving at least min_window_s / 2 after the last."""
        n = len(self._records) - 1
        step = max(1, int(round(self.settings.onset_step_s / self.model.step_s)))
        if self.settings.onset_step_s <= 0:
            step = 1
        last = n - max(3, int(round(0.5 * self.settings.min_window_s / self.model.step_s)))
        return [0] + list(range(step, last + 1, step))

    def _evaluate(self) -> list[FdirEvent]:
        """Detect, isolate, classify (module docstring).

        Per coil not yet latched, the single-fault hypothesis: only that coil differs from the
        belief, from its maximum-likelihood onset in the window (`isolation_fits`). Detection: d^2
        of its (g, s) to the nominal box, if the coil is excited enough (its gain's sigma at most
        max_gain_std; else not observable). Isolation, while a coil is alarmed: the coil whose
        hypothesis leaves the least residual, by at least `isolation_margin` (chi-square units)
        over the next one, is the faulty one, whichever coil raised the alarm (a coil hardly
        excited lets another coil's parameters take up its fault). Class: `classify` on that fit,
        which needs the coil's gain told apart from its offset after the onset."""
        s = self.settings
        self.evaluations += 1
        time_s = self._records[-1][0]
        lower = np.array([1.0 - s.gain_tolerance, -s.offset_tolerance_am2])
        upper = np.array([1.0 + s.gain_tolerance, s.offset_tolerance_am2])
        detect_on = self.detection_onsets()
        onsets = sorted(set(self.onset_candidates()) | set(detect_on))
        fits = self.isolation_fits_all([c for c in range(3) if self.beliefs[c].fault is None], onsets, keep=detect_on)
        statistic = 0.0
        for fit in fits:
            j = fit.coil
            if self.keep_statistics:
                self.gain_std_window[j].append(float(np.sqrt(fit.by_onset[0][1][0, 0])))
            judged = [fit.by_onset[o] for o in sorted(set(detect_on) | {fit.onset})
                      if np.sqrt(fit.by_onset[o][1][0, 0]) <= s.max_gain_std]
            if not judged:
                x, p = fit.by_onset[0]
                self.last[j] = CoilEstimate(float(x[0]), float(x[1]), p, False, float("nan"))
                self.not_observable[j] += 1
                continue
            self.judged[j] += 1
            scored = [(box_distance2(x, p, lower, upper), x, p) for x, p in judged]
            d2, x, p = max(scored, key=lambda item: item[0])
            for _, xk, _ in scored:
                self.worst_gain_deviation = max(self.worst_gain_deviation, abs(float(xk[0]) - 1.0))
                self.worst_offset_am2 = max(self.worst_offset_am2, abs(float(xk[1])))
            if self.keep_statistics:
                self.statistics.append((time_s, j, d2))
            if d2 > self.peak_statistic[j]:
                self.peak_statistic[j], self.peak_statistic_time_s[j] = d2, time_s
            self.last[j] = CoilEstimate(float(x[0]), float(x[1]), p, True, d2)
            statistic = max(statistic, d2)
            # A coil's alarm stands until it is judged below the threshold again (not observable
            # for a while: it stands, its fault may still be isolated).
            if d2 > s.threshold:
                self._alarmed.add(j)
            else:
                self._alarmed.discard(j)
        if not self._alarmed or not fits:
            self._clear()
            return []
        if self._alarm_since is None:
            self._alarm_since = time_s
        fits.sort(key=lambda f: f.rss)
        best = fits[0]
        isolated = len(fits) == 1 or (fits[1].rss - best.rss) / best.factor >= s.isolation_margin
        fault_class = None
        if isolated:
            fault_class, reading = classify(best, s.class_consistency, s.max_gain_std)
            if reading.onset_s >= self._records[onsets[-1]][0]:
                # The onset at the latest one tried: the true one may be later still (it is
                # only tried with min_window_s / 2 of data after it); a reading on a too early
                # onset blends healthy steps into the fault (an open coil read as gain 0.15).
                fault_class = None
        if fault_class is None:
            self._streak, self._streak_key = 0, None
            return []
        key = (best.coil, fault_class)
        self._streak = self._streak + 1 if self._streak_key == key else 1
        self._streak_key = key
        if self._streak < s.persistence:
            return []
        j, r = best.coil, reading
        event = FdirEvent(time_s, j, fault_class, r.gain, r.gain_std, r.offset_am2, r.offset_std_am2, statistic,
                          time_s - r.onset_s, self._alarm_since, r.onset_s)
        gain, offset = CLASS_MODELS[fault_class]
        self.beliefs[j] = CoilBelief(r.gain if gain is None else gain, r.offset_am2 if offset is None else offset,
                                     fault_class, time_s, r.onset_s)
        self.events.append(event)
        # The window restarts on the new belief: data fitted under the old one (the fault's onset
        # is known to a few steps only) must not be laid on the other coils.
        self.reset()
        return [event]

    def _clear(self) -> None:
        self._streak, self._streak_key, self._alarm_since = 0, None, None
        self._alarmed = set()

    def summary(self) -> dict:
        """What the run's fdir.json holds: settings, per-coil judgement counts, peak statistics, events."""
        s = self.settings
        return {
            "monitor": "FDIR",
            "settings": {k: getattr(s, k) for k in s.__dataclass_fields__},
            "rate_sample": self.model.rate_sample,
            "gyro_noise_std_radps": self.model.gyro_noise_std_radps,
            "evaluations": self.evaluations,
            "window_resets": self.resets,
            "coils": {AXES[j]: {"judged": self.judged[j], "not_observable": self.not_observable[j],
                                "peak_statistic": self.peak_statistic[j],
                                "peak_statistic_time_s": self.peak_statistic_time_s[j],
                                "fault": self.beliefs[j].fault, "detected_s": self.beliefs[j].detected_s,
                                "gain": self.beliefs[j].gain, "offset_am2": self.beliefs[j].offset_am2}
                      for j in range(3)},
            "events": [e.to_dict() for e in self.events],
        }


# ---- accommodation ------------------------------------------------------------------------------
def accommodate(dipole_am2: np.ndarray, field_body_t: np.ndarray, beliefs: list[CoilBelief],
                limit_am2: float) -> np.ndarray:
    """The dipole to command so that the coils, as believed, give the torque the law's dipole would
    on healthy coils. A reversed (or mis-gained) coil gets its command divided by its gain (the sign
    flipped); the torque an open or stuck coil cannot give is asked of the usable coils, least
    squares on m x B (any torque across B stays reachable with two coils while B has a component
    along the lost coil), scaled down as a whole to the limit so the torque keeps its direction."""
    m = np.asarray(dipole_am2, float)
    if all(b.fault is None for b in beliefs):
        return m
    field_t = np.asarray(field_body_t, float)
    usable = [j for j, b in enumerate(beliefs) if b.usable]
    lost = [j for j in range(3) if j not in usable]
    out = np.zeros(3)
    for j in usable:
        out[j] = m[j] / beliefs[j].gain
    if lost and usable and np.any(field_t):
        ecb = _unit_cross_field(field_t)            # rows: e_j x B
        # torque the lost coils should have given, minus what they give (a stuck coil's constant dipole)
        wanted = sum(m[j] * ecb[j] for j in lost) - sum(beliefs[j].offset_am2 * ecb[j] for j in lost)
        columns = np.array([ecb[j] for j in usable]).T         # 3 x n_usable: torque per unit dipole
        extra, *_ = np.linalg.lstsq(columns, wanted, rcond=1e-3)
        for i, j in enumerate(usable):
            out[j] += extra[i] / beliefs[j].gain
    largest = np.max(np.abs(out))
    if largest > limit_am2:
        out *= limit_am2 / largest
    return out
