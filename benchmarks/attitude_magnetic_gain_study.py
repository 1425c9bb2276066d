"""Why the sliding-mode and PD laws do not converge with magnetorquers only on the bench's 1U body:
a lean closed loop (the plant's RK4 rigid body, a tilted dipole along a 500 km, 97.4 deg circular
orbit, 1 Hz, the laws of bench.gnc.attitude_law through the least-norm dipole map) with switches
for what is idealised. Prints the pointing error (deg) at 13 instants and the final error.

    PYTHONPATH=$PWD python benchmarks/attitude_magnetic_gain_study.py hold 5670 sm,0.03,0.01 pd,2e-6,1e-4
    NODIST=1 NOQ=1 ... (no disturbances, no board quantisation)   FULL=1 ... (3-axis torque: the reference)
    DITHER=1 NOQ=1 ... (the board's step with the law's quantisation error feedback)

A spec is `sm,lambda,k` (sliding mode) or `pd,kp,kd`. `slew` starts 200 deg from the target
(160 the short way), `hold` 3 deg. Disturbances: gravity gradient and a 1e-4 A m^2 residual dipole
(a 1e-3 A m^2 dipole calibrated to 10 %); the board rounds the dipole to 1e-3 A m^2.
"""
import os
import sys

import numpy as np

from bench.gnc import quaternion as qt
from bench.gnc.attitude_law import (AttitudeControlInput, PdTracking, QuantisationErrorFeedback, SlidingModeTracking,
                                    inertial_hold)
from bench.gnc.environment import gravity_gradient_torque_nm
from bench.plant.attitude import CircularOrbit, TiltedDipole, rk4_attitude_step

J = np.diag([2.2e-3, 2.3e-3, 2.0e-3])
J_INV = np.linalg.inv(J)
ORBIT = CircularOrbit(radius_m=6.8712e6, inclination_rad=np.deg2rad(97.4))
FIELD = TiltedDipole()
RESIDUAL_AM2 = np.zeros(3) if os.environ.get("NODIST") else np.array([1e-4, 0.0, 0.0])
GRAVITY_GRADIENT = 0.0 if os.environ.get("NODIST") else 1.0
START = {"slew": [-0.173648178, 0.296020129, -0.493366882, 0.799254348],
         "hold": [0.999657325, 0.0178988407, -0.0119325605, 0.0149157006]}


def run(law, q0, steps, dt=1.0):
    q, w, errors = np.array(q0, float), np.zeros(3), []
    for k in range(steps):
        t = k * dt
        r = ORBIT.position_m(t)
        c = qt.rotation_matrix(q)
        b = c.T @ FIELD.field_t(r, t)
        x = AttitudeControlInput(t, q, w, b)
        if os.environ.get("FULL"):
            torque = law.torque_nm(x)[0]
        else:
            m, _ = law.eval(x)
            m = m if os.environ.get("NOQ") else np.round(m, 3)
            torque = np.cross(m + RESIDUAL_AM2, b) + GRAVITY_GRADIENT * gravity_gradient_torque_nm(c.T @ r, J)
        errors.append(np.rad2deg(qt.angle_between_rad(qt.IDENTITY_WXYZ, q)))
        q, w = rk4_attitude_step(q, w, torque, J, dt, J_INV)
    return np.array(errors)


def main():
    start, steps = START[sys.argv[1]], int(sys.argv[2])
    for spec in sys.argv[3:]:
        kind, a, b = spec.split(",")
        target = inertial_hold(qt.IDENTITY_WXYZ)
        law = (SlidingModeTracking(target, J, 0.2, float(a), float(b)) if kind == "sm"
               else PdTracking(target, 0.2, float(a), float(b)))
        if os.environ.get("DITHER"):      # the board's step with the law's error feedback (then NOQ=1)
            law = QuantisationErrorFeedback(law, 1e-3, 0.2)
        e = run(law, start, steps)
        idx = np.linspace(0, len(e) - 1, 13).astype(int)
        print(f"{spec}: final {e[-1]:.2f} deg; at t = {idx.tolist()} s: {[round(float(e[i]), 1) for i in idx]}", flush=True)


if __name__ == "__main__":
    main()
