"""The attitude loop's Estimator section: the smoother's attitude and gyro bias against the truth.

From the recording: the estimator's `estimate/attitude` (quaternion, 3x3 attitude covariance in
rad², gyro bias) and the plant's `truth/attitude` of the same step (seq). The attitude error is the
rotation from the true attitude to the estimate, `q_err = q_true* ⊗ q_est`, as a rotation vector
in the body frame (the frame of the smoother's covariance), per axis with the estimator's own ±3σ
bound; NEES is `e^T P^-1 e` (3 degrees of freedom: its mean is 3 for a consistent estimator, and
95 % of the steps lie in the χ²(3) interval [0.216, 9.35]). The star tracker's outages (no fix:
the attitude drifts on the gyro) are shaded. Steps before the smoother's first fix (valid false)
are left out.

When the smoother estimates the magnetometer's calibration (`[estimator.attitude]
estimate_magnetometer_calibration`; measured = scale * B_body + bias + noise), its estimates carry
`magnetometer_bias_t` and `magnetometer_scale`: the section then compares them with the plant's
own bias and scale, which come from the scenario's sensors (what the plant was built with), not
from the estimator, and with the smoother's belief before the run (its prior mean). Without it,
the section, its figure and its metrics are as before.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bench.bus import keys  # noqa: E402
from bench.plant.attitude_plant import sensor_spec  # noqa: E402
from bench.report import plots  # noqa: E402
from bench.report.document import Figure, Section, Table, fmt  # noqa: E402

NEES_DOF = 3
NEES_95 = (0.216, 9.35)       # χ²(3) 2.5 % and 97.5 % quantiles
PLOT_FILE = "attitude_estimator.png"
T_TO_UT = 1e6


@dataclass
class MagnetometerCalibration:
    """The smoother's magnetometer calibration over the run beside the truth and its prior belief."""
    bias_est_t: np.ndarray        # (n, 3) body axes, T; NaN at steps whose estimate carried none
    scale_est: np.ndarray         # (n,), NaN likewise
    bias_true_t: np.ndarray       # (3,) the plant's, from the scenario's sensors
    scale_true: float
    bias_prior_t: np.ndarray      # (3,) the smoother's belief before the run (the mean of its prior)
    scale_prior: float

    def final(self) -> tuple[np.ndarray, float]:
        """The last estimate that carried a calibration."""
        last = np.flatnonzero(np.isfinite(self.bias_est_t).all(axis=1))[-1]
        return self.bias_est_t[last], float(self.scale_est[last])

    def to_metrics(self) -> dict:
        bias_t, scale = self.final()
        bias_error_t = bias_t - self.bias_true_t

        def ut(v) -> list[float]:
            return [float(x) for x in np.asarray(v) * T_TO_UT]

        return {
            "bias_estimated_final_ut": ut(bias_t),
            "bias_true_ut": ut(self.bias_true_t),
            "bias_error_final_ut": ut(bias_error_t),
            "bias_error_final_norm_ut": float(np.linalg.norm(bias_error_t) * T_TO_UT),
            # how far the smoother started from the truth: the error its estimate had to remove
            "bias_prior_ut": ut(self.bias_prior_t),
            "bias_prior_error_norm_ut": float(np.linalg.norm(self.bias_prior_t - self.bias_true_t) * T_TO_UT),
            "scale_estimated_final": scale,
            "scale_true": self.scale_true,
            "scale_error_final": scale - self.scale_true,
            "scale_prior": self.scale_prior,
        }


@dataclass
class AttitudeEstimation:
    sim_time_s: np.ndarray        # (n,)
    error_rad: np.ndarray         # (n, 3) body-frame rotation vector from truth to estimate
    bound_3sigma_rad: np.ndarray  # (n, 3), NaN without a covariance
    nees: np.ndarray              # (n,), NaN without a covariance
    bias_est_radps: np.ndarray    # (n, 3)
    bias_true_radps: np.ndarray   # (n, 3), NaN where the truth has none
    outages_s: list[tuple[float, float]]
    magnetometer: MagnetometerCalibration | None = None   # only when the estimates carry one

    def to_metrics(self) -> dict:
        total_deg = np.rad2deg(np.linalg.norm(self.error_rad, axis=1))
        has = np.isfinite(self.bound_3sigma_rad)
        inside = np.abs(self.error_rad)[has] <= self.bound_3sigma_rad[has]
        nees = self.nees[np.isfinite(self.nees)]
        bias_err = self.bias_est_radps - self.bias_true_radps
        in_outage = np.zeros(len(self.sim_time_s), bool)
        for a, b in self.outages_s:
            in_outage |= (self.sim_time_s >= a) & (self.sim_time_s < b)
        return {
            "samples": int(len(self.sim_time_s)),
            "attitude_error_deg": {"rms": float(np.sqrt(np.mean(total_deg**2))), "max": float(total_deg.max()),
                                   "final": float(total_deg[-1]),
                                   "max_in_star_tracker_outage": float(total_deg[in_outage].max()) if in_outage.any() else None},
            "fraction_within_3sigma": float(inside.mean()) if inside.size else None,
            "mean_nees": float(nees.mean()) if nees.size else None,
            "nees_dof": NEES_DOF,
            "fraction_nees_in_95": float(((nees >= NEES_95[0]) & (nees <= NEES_95[1])).mean()) if nees.size else None,
            "gyro_bias_error_final_dph": [float(v) for v in np.rad2deg(bias_err[-1]) * 3600.0]
            if np.isfinite(bias_err[-1]).all() else None,
            "star_tracker_outages_s": [list(w) for w in self.outages_s],
        } | ({} if self.magnetometer is None else {"magnetometer_calibration": self.magnetometer.to_metrics()})


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a.T
    w2, x2, y2, z2 = b.T
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], axis=1)


def rotation_vector(q_true: np.ndarray, q_est: np.ndarray) -> np.ndarray:
    """(n, 3) rotation vectors of q_true* ⊗ q_est (the shorter way round)."""
    conj = q_true * np.array([1.0, -1.0, -1.0, -1.0])
    q = _quat_mul(conj, q_est)
    q = q * np.where(q[:, :1] < 0, -1.0, 1.0)
    v = q[:, 1:]
    norm = np.linalg.norm(v, axis=1)
    angle = 2.0 * np.arctan2(norm, q[:, 0])
    scale = np.where(norm > 1e-15, angle / np.where(norm > 1e-15, norm, 1.0), 2.0)
    return v * scale[:, None]


def attitude_estimation(run) -> AttitudeEstimation | None:
    """None where no estimator of the attitude ran (truth mode) or nothing was recorded."""
    if run.scenario is None or run.scenario.kind != "attitude" or run.scenario.estimator.mode == "truth":
        return None
    truth = {m.seq: m.body for m in run.on(keys.TRUTH_ATTITUDE)}
    rows = []
    for m in run.on(keys.ESTIMATE_ATTITUDE):
        if m.seq not in truth or not m.body.get("valid", True):
            continue
        cov = m.body.get("attitude_covariance_rad2")
        # Optional fields: an outside estimator, or a smoother without the calibration, leaves them null.
        mag_bias, mag_scale = m.body.get("magnetometer_bias_t"), m.body.get("magnetometer_scale")
        rows.append((m.body["header"]["sim_time_s"], m.body["q_wxyz"], truth[m.seq]["q_wxyz"],
                     np.reshape(cov, (3, 3)) if cov else np.full((3, 3), np.nan),
                     m.body["gyro_bias_radps"], truth[m.seq].get("gyro_bias_radps") or [np.nan] * 3,
                     mag_bias if mag_bias is not None else [np.nan] * 3,
                     mag_scale if mag_scale is not None else np.nan))
    if not rows:
        return None
    rows.sort(key=lambda r: r[0])
    t, q_est, q_true, cov, bias, bias_true, mag_bias, mag_scale = zip(*rows)
    error = rotation_vector(np.asarray(q_true, float), np.asarray(q_est, float))
    cov = np.asarray(cov, float)
    bound = 3.0 * np.sqrt(np.abs(np.diagonal(cov, axis1=1, axis2=2)))
    nees = np.full(len(t), np.nan)
    for i, (e, p) in enumerate(zip(error, cov)):
        if np.isfinite(p).all():
            try:
                nees[i] = float(e @ np.linalg.solve(p, e))
            except np.linalg.LinAlgError:
                pass
    outages = [(float(a), float(b)) for a, b in run.scenario.attitude.sensors.star_tracker_outages_s]
    return AttitudeEstimation(np.asarray(t, float), error, bound, nees, np.asarray(bias, float),
                              np.asarray(bias_true, float), outages,
                              _magnetometer_calibration(run, np.asarray(mag_bias, float), np.asarray(mag_scale, float)))


def _magnetometer_calibration(run, bias_est_t: np.ndarray, scale_est: np.ndarray) -> MagnetometerCalibration | None:
    """None unless some estimate carried a calibration. The truth is what the plant was built with
    (bench.plant.attitude_plant.sensor_spec of the scenario), the same source as the plant's."""
    if not np.isfinite(bias_est_t).all(axis=1).any():
        return None
    plant = sensor_spec(run.scenario.attitude)
    belief = run.scenario.estimator.attitude
    return MagnetometerCalibration(bias_est_t, scale_est, np.asarray(plant.magnetometer_bias_t, float),
                                   float(plant.magnetometer_scale), np.asarray(belief.magnetometer_bias_t, float),
                                   float(belief.magnetometer_scale))


def _shade_outages(ax, outages, t_end: float, first: bool) -> None:
    for i, (a, b) in enumerate(outages):
        if a < t_end:
            ax.axvspan(a, min(b, t_end), color="0.6", alpha=0.3,
                       label="star tracker outage (no fix)" if first and i == 0 else None)


def estimator_figure(est: AttitudeEstimation, path: Path) -> Path:
    """Per axis the attitude error with its ±3σ bound, then NEES with its 95 % band, then the gyro
    bias estimate against the truth; outages shaded. With a magnetometer calibration, two panels
    more below: its bias per axis and its scale against the truth."""
    t = est.sim_time_s
    mag = est.magnetometer
    fig, axes = plt.subplots(5 if mag is None else 7, 1, figsize=(11, 12 if mag is None else 16), sharex=True)
    for i, axis in enumerate("xyz"):
        ax = axes[i]
        ax.plot(t, np.rad2deg(est.error_rad[:, i]), color="C0", lw=1, label=f"attitude error {axis} (estimate − truth)")
        ax.plot(t, np.rad2deg(est.bound_3sigma_rad[:, i]), color="C3", lw=0.8, ls="--", label="±3σ (smoother)")
        ax.plot(t, -np.rad2deg(est.bound_3sigma_rad[:, i]), color="C3", lw=0.8, ls="--")
        _shade_outages(ax, est.outages_s, t[-1], i == 0)
        ax.set_ylabel(f"{axis} [deg]")
        ax.legend(fontsize="small", loc="upper right")
    ax = axes[3]
    ax.semilogy(t, np.maximum(est.nees, 1e-6), color="C0", lw=1, label=f"NEES ({NEES_DOF} dof)")
    ax.axhline(NEES_DOF, color="k", lw=0.8, label=f"expected mean {NEES_DOF}")
    ax.axhspan(*NEES_95, color="C2", alpha=0.15, label="χ²(3) 95 % interval")
    _shade_outages(ax, est.outages_s, t[-1], False)
    ax.set_ylabel("NEES")
    ax.legend(fontsize="small", loc="upper right")
    ax = axes[4]
    to_dph = np.rad2deg(1.0) * 3600.0
    for i, axis in enumerate("xyz"):
        ax.plot(t, est.bias_est_radps[:, i] * to_dph, color=f"C{i}", lw=1, label=f"bias {axis} estimate")
        if np.isfinite(est.bias_true_radps[:, i]).any():
            ax.plot(t, est.bias_true_radps[:, i] * to_dph, color=f"C{i}", lw=0.8, ls=":", label=f"bias {axis} true")
    _shade_outages(ax, est.outages_s, t[-1], False)
    ax.set_ylabel("gyro bias [deg/h]")
    ax.legend(fontsize="small", ncol=3, loc="upper right")
    if mag is not None:
        _magnetometer_panels(axes[5], axes[6], t, mag)
    axes[-1].set_xlabel("simulated time [s]")
    for a in axes:
        a.grid(True, alpha=0.3)
    return plots.save(fig, path, dpi=90)


def _magnetometer_panels(ax_bias, ax_scale, t: np.ndarray, mag: MagnetometerCalibration) -> None:
    for i, axis in enumerate("xyz"):
        ax_bias.plot(t, mag.bias_est_t[:, i] * T_TO_UT, color=f"C{i}", lw=1, label=f"bias {axis} estimate")
        ax_bias.axhline(mag.bias_true_t[i] * T_TO_UT, color=f"C{i}", lw=0.8, ls=":", label=f"bias {axis} true")
    ax_bias.set_ylabel("magnetometer bias [µT]")
    ax_bias.legend(fontsize="small", ncol=3, loc="best")    # the true lines span the panel: let it find room
    ax_scale.plot(t, mag.scale_est, color="C0", lw=1, label="scale estimate")
    ax_scale.axhline(mag.scale_true, color="C0", lw=0.8, ls=":", label="scale true")
    ax_scale.set_ylabel("magnetometer scale")
    ax_scale.legend(fontsize="small", loc="upper right")


def _magnetometer_rows(m: dict) -> list[list[str]]:
    def xyz(values) -> str:
        return ", ".join(fmt(v) for v in values)

    return [["magnetometer bias estimated at the end [µT] (x, y, z)", xyz(m["bias_estimated_final_ut"])],
            ["magnetometer bias true, the plant's [µT] (x, y, z)", xyz(m["bias_true_ut"])],
            ["magnetometer bias error at the end [µT] (x, y, z); norm",
             f"{xyz(m['bias_error_final_ut'])}; {fmt(m['bias_error_final_norm_ut'])}"],
            ["magnetometer bias believed before the run (the smoother's prior) [µT] (x, y, z)",
             xyz(m["bias_prior_ut"])],
            ["magnetometer scale estimated at the end / true / error",
             f"{fmt(m['scale_estimated_final'], 5)} / {fmt(m['scale_true'], 5)} / {fmt(m['scale_error_final'])}"]]


def attitude_estimation_section(run, plot_dir: Path) -> tuple[Section | None, dict | None]:
    est = attitude_estimation(run)
    if est is None:
        return None, None
    m = est.to_metrics()
    err = m["attitude_error_deg"]
    rows = [["attitude error RMS / max / final [deg]", f"{fmt(err['rms'])} / {fmt(err['max'])} / {fmt(err['final'])}"],
            ["largest attitude error in a star tracker outage [deg]",
             fmt(err["max_in_star_tracker_outage"]) if err["max_in_star_tracker_outage"] is not None
             else "no outage in the run"],
            ["errors inside ±3σ (per axis and step)", fmt(m["fraction_within_3sigma"])],
            [f"mean NEES ({NEES_DOF} expected)", fmt(m["mean_nees"])],
            ["steps with NEES in the χ²(3) 95 % interval", fmt(m["fraction_nees_in_95"])],
            ["gyro bias error at the end [deg/h] (x, y, z)",
             ", ".join(fmt(v) for v in m["gyro_bias_error_final_dph"]) if m["gyro_bias_error_final_dph"] else "no truth"],
            ["star tracker outages [s]", ", ".join(
                f"{fmt(a)}–{fmt(b)}" + (" (after this run's end)" if a >= est.sim_time_s[-1] else "")
                for a, b in est.outages_s) or "none"]]
    paragraph = (f"The attitude smoother ({run.scenario.estimator.mode}) against the plant's truth, {m['samples']} "
                 "steps after its first fix: the attitude error (the rotation from the true attitude to the estimate, "
                 "body axes) with the smoother's own ±3σ, NEES, and the gyro bias it estimates. Shaded: star tracker "
                 "outages, where the attitude runs on the gyro alone and its error and bound grow.")
    caption = "Attitude error with ±3σ, NEES, gyro bias; star tracker outages shaded"
    if "magnetometer_calibration" in m:
        rows += _magnetometer_rows(m["magnetometer_calibration"])
        paragraph += (" The smoother also estimates the magnetometer's calibration (measured = scale × B + bias): "
                      "its bias and scale against the plant's, which come from the scenario's sensors.")
        caption += "; magnetometer bias and scale against the truth"
    path = estimator_figure(est, plot_dir / PLOT_FILE)
    section = Section("Estimator", [paragraph], [Table(["", "value"], rows)],
                      [Figure(Path("plots") / path.name, caption)])
    return section, m
