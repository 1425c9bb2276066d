"""Physics of the attitude plant against references it was not written from: conservation laws,
the closed-form gravity gradient and a finite-difference potential, published IGRF numbers, and the
SGP4 package's own verification vectors."""
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
import sgp4

from bench.plant.attitude import body_to_inertial, rk4_attitude_step
from bench.config.plant import (
    AttitudeConfigError, AttitudePlantConfig, FieldConfig, OrbitConfig, check_attitude_plant,
)
from bench.plant.attitude_plant import AttitudePlant
from bench.gnc.environment import (
    EARTH_MU_M3PS2, IGRF_REFERENCE_RADIUS_KM, IgrfAlongOrbit, Sgp4Orbit, TleError, gravity_gradient_torque_nm,
    igrf_field_inertial_t, inertial_from_earth_fixed, greenwich_angle_rad,
)
from bench.plant.attitude import CircularOrbit

# Vallado's verification TLE for satellite 00005 (SGP4-VER.TLE in the sgp4 package).
TLE_00005 = ("1 00005U 58002B   00179.78495062  .00000023  00000-0  28098-4 0  4753",
             "2 00005  34.2682 348.7242 1859667 331.7664  19.3264 10.82419157413667")


def test_torque_free_body_conserves_energy_and_angular_momentum_over_an_orbit():
    # Asymmetric body, full inertia, tumbling at ~10 deg/s: the plant's own 0.1 s step for one
    # 95-minute orbit. Kinetic energy and the inertial angular momentum are invariants.
    rng = np.random.default_rng(11)
    rotation = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    inertia = rotation @ np.diag([3.1e-3, 2.4e-3, 1.7e-3]) @ rotation.T
    q = np.array([0.5, 0.5, -0.5, 0.5])
    w = np.deg2rad([6.0, -7.0, 4.0])
    energy0 = 0.5 * w @ inertia @ w
    momentum0 = body_to_inertial(q).apply(inertia @ w)
    for _ in range(57_000):
        q, w = rk4_attitude_step(q, w, np.zeros(3), inertia, 0.1)
    assert abs(0.5 * w @ inertia @ w - energy0) / energy0 < 1e-9
    momentum = body_to_inertial(q).apply(inertia @ w)
    assert np.linalg.norm(momentum - momentum0) / np.linalg.norm(momentum0) < 1e-9
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12


def test_gravity_gradient_matches_the_pitch_closed_form():
    # Principal axes, radius vector in the body x-z plane at pitch theta from body z:
    # tau_y = (3 mu / 2 r^3) (Jz - Jx) sin(2 theta), tau_x = tau_z = 0 (Wie, Space Vehicle
    # Dynamics and Control, sec. 6.3).
    inertia = np.diag([4.0e-3, 3.0e-3, 1.5e-3])
    r_m = 6.878e6
    for theta in np.deg2rad([-80.0, -30.0, 5.0, 45.0, 110.0]):
        position_body = r_m * np.array([-np.sin(theta), 0.0, np.cos(theta)])
        torque = gravity_gradient_torque_nm(position_body, inertia)
        expected_y = 1.5 * EARTH_MU_M3PS2 / r_m**3 * (inertia[2, 2] - inertia[0, 0]) * np.sin(2 * theta)
        np.testing.assert_allclose(torque, [0.0, expected_y, 0.0], atol=1e-15 * abs(expected_y) + 1e-25)


def test_gravity_gradient_is_minus_the_gradient_of_its_potential():
    # U(R) = -(mu / 2 r^3) (tr J - 3 r_b' J r_b), the second-order term of -integral mu dm / |r + rho|,
    # with r_b = R' r_hat; a small body rotation R Exp(e) changes U by -tau . e. Full, non-diagonal inertia; central differences.
    rng = np.random.default_rng(5)
    a = rng.normal(size=(3, 3)) * 1e-3
    inertia = a @ a.T + np.eye(3) * 1e-3
    r_inertial = np.array([3.1e6, -5.2e6, 3.0e6])
    r = np.linalg.norm(r_inertial)
    from scipy.spatial.transform import Rotation
    attitude = Rotation.from_rotvec([0.3, -1.1, 0.7])

    def potential(rot):
        r_b = rot.inv().apply(r_inertial) / r
        return -EARTH_MU_M3PS2 / (2 * r**3) * (np.trace(inertia) - 3 * r_b @ inertia @ r_b)

    h = 1e-6
    gradient = np.array([(potential(attitude * Rotation.from_rotvec(h * e)) -
                          potential(attitude * Rotation.from_rotvec(-h * e))) / (2 * h) for e in np.eye(3)])
    torque = gravity_gradient_torque_nm(attitude.inv().apply(r_inertial), inertia)
    np.testing.assert_allclose(torque, -gradient, rtol=1e-6)


# IGRF-14 (Alken et al., IGRF-14 release, doi:10.5281/zenodo.14012302), DGRF 2020.0 dipole
# coefficients in nT; IGRF-13's provisional 2020 values (Alken et al. 2021, Earth Planets Space
# 73:49, Table 2: -29404.8, -1450.9, 4652.5) differ by under 2 nT.
G10, G11, H11 = -29403.41, -1451.37, 4653.35


@pytest.mark.parametrize("colat_deg, lon_deg, altitude_km", [(30.0, 10.0, 0.0), (90.0, -60.0, 500.0),
                                                             (140.0, 150.0, 800.0)])
def test_igrf_dipole_part_equals_the_closed_form_of_the_published_coefficients(colat_deg, lon_deg, altitude_km):
    import ppigrf

    r_km = IGRF_REFERENCE_RADIUS_KM + altitude_km
    br, bt, bp = (float(np.ravel(b)[0]) for b in ppigrf.igrf_gc(r_km, colat_deg, lon_deg, datetime(2020, 1, 1),
                                                                max_degree=1))
    theta, phi = np.deg2rad(colat_deg), np.deg2rad(lon_deg)
    s = (IGRF_REFERENCE_RADIUS_KM / r_km) ** 3
    equatorial = G11 * np.cos(phi) + H11 * np.sin(phi)
    expected = [2 * s * (G10 * np.cos(theta) + equatorial * np.sin(theta)),
                s * (G10 * np.sin(theta) - equatorial * np.cos(theta)),
                s * (G11 * np.sin(phi) - H11 * np.cos(phi))]
    np.testing.assert_allclose([br, bt, bp], expected, rtol=1e-6, atol=1e-3)


def test_igrf_surface_intensity_spans_the_published_range():
    # NOAA/BGS WMM2020 technical report (Chulliat et al. 2020), Fig. 17 / sec. 4: total intensity at
    # the surface ranges from about 22,000 nT (South Atlantic anomaly) to about 67,000 nT (south of
    # Australia). A 2-degree grid through our inertial conversion (t = 0, so Earth-fixed = rotated).
    epoch = datetime(2020, 1, 1, tzinfo=timezone.utc)
    colat, lon = np.meshgrid(np.deg2rad(np.arange(1.0, 180.0, 2.0)), np.deg2rad(np.arange(-180.0, 180.0, 2.0)))
    r = IGRF_REFERENCE_RADIUS_KM * 1e3
    fixed = r * np.stack([np.sin(colat) * np.cos(lon), np.sin(colat) * np.sin(lon), np.cos(colat)], axis=-1).reshape(-1, 3)
    inertial = fixed @ inertial_from_earth_fixed(greenwich_angle_rad(epoch, 0.0)).T
    intensity_nt = np.linalg.norm(igrf_field_inertial_t(inertial, np.zeros(len(inertial)), epoch), axis=1) * 1e9
    assert 21_500 < intensity_nt.min() < 23_000
    assert 65_500 < intensity_nt.max() < 68_000


def test_igrf_spline_along_the_orbit_matches_direct_evaluation():
    epoch = datetime(2025, 3, 1, tzinfo=timezone.utc)
    orbit = CircularOrbit(radius_m=6.878e6, inclination_rad=np.deg2rad(97.4))
    table = IgrfAlongOrbit.tabulate(orbit, epoch, 600.0, grid_s=10.0)
    midpoints = np.arange(5.0, 600.0, 37.0)
    direct = igrf_field_inertial_t(np.array([orbit.position_m(t) for t in midpoints]), midpoints, epoch)
    splined = np.array([table.field_t(None, t) for t in midpoints])
    assert np.max(np.linalg.norm(splined - direct, axis=1) / np.linalg.norm(direct, axis=1)) < 1e-5


def test_sgp4_orbit_reproduces_the_packages_verification_vectors():
    # tcppver.out: Vallado's C++ output for the verification TLEs, "tsince x y z ..." in min and km.
    reference = Path(sgp4.__file__).parent / "tcppver.out"
    rows, in_block = [], False
    for line in reference.read_text().splitlines():
        if line.split()[:2] == ["5", "xx"]:
            in_block = True
            continue
        if in_block:
            if "xx" in line:
                break
            rows.append([float(v) for v in line.split()[:4]])
    assert len(rows) >= 10
    orbit = Sgp4Orbit.from_tle(*TLE_00005)
    for tsince_min, *position_km in rows:
        # Tolerance: the run epoch is a datetime (microsecond resolution, 7.5 mm at 7.5 km/s).
        np.testing.assert_allclose(orbit.position_m(tsince_min * 60.0), np.array(position_km) * 1e3, atol=0.05)


@pytest.mark.parametrize("tle, message", [
    (("1 00005U garbage", TLE_00005[1]), "69-character"),
    ((TLE_00005[0], TLE_00005[1].replace("34.2682", "3x.2682")), "line 2 checksum"),
    ((TLE_00005[0], TLE_00005[1].replace("34.2682", "35.2682")), "line 2 checksum"),
])
def test_bad_tle_is_an_error_naming_the_field(tle, message):
    with pytest.raises(TleError, match=message):
        Sgp4Orbit.from_tle(*tle)
    config = AttitudePlantConfig(orbit=OrbitConfig(model="sgp4", tle=list(tle)))
    with pytest.raises(AttitudeConfigError, match=r"^attitude\.orbit\.tle: "):
        check_attitude_plant(config)


@pytest.mark.parametrize("change, field", [
    (dict(inertia_kgm2=[1e-3, -1e-3, 1e-3]), "attitude.inertia_kgm2"),
    (dict(inertia_kgm2=[1e-3, 1e-3, 5e-3]), "attitude.inertia_kgm2"),
    (dict(inertia_kgm2=[1e-3, 1e-4, 0, 2e-4, 1e-3, 0, 0, 0, 1e-3]), "attitude.inertia_kgm2"),
    (dict(initial_q_wxyz=[1.0, 0.1, 0.0, 0.0]), "attitude.initial_q_wxyz"),
    (dict(initial_q_wxyz=[float("nan"), 0.0, 0.0, 1.0]), "attitude.initial_q_wxyz"),
])
def test_impossible_body_is_an_error_naming_the_field(change, field):
    with pytest.raises(AttitudeConfigError, match=f"^{field.replace('.', chr(92) + '.')}: "):
        check_attitude_plant(AttitudePlantConfig(**change))


def test_plant_on_sgp4_and_igrf_runs_and_sees_a_leo_field():
    config = AttitudePlantConfig(orbit=OrbitConfig(model="sgp4", tle=list(TLE_00005)), field=FieldConfig(model="igrf"),
                                 initial_rate_dps=[2.0, 0.0, 0.0])
    plant = AttitudePlant(config, 50, seed=1)
    for _ in range(50):
        plant.sense()
        plant.apply(np.array([0.1, 0.0, 0.0]))
    field = plant.trajectory()["att_field_body_t"]
    assert np.all((np.linalg.norm(field, axis=1) > 1e-5) & (np.linalg.norm(field, axis=1) < 6.5e-5))
