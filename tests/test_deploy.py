"""Robot-side conversions: sensor readings -> the simulator's observation, actions -> Twist."""

import math

import jax
import numpy as np
import pytest
from conftest import LOPSIDED, ONE_ROW_ROOMS, start_in
from test_robot_side import ASTRA_VFOV, floor_image

from jaxnav.core.sensors import SensorConfig, ray_depths
from jaxnav.robot_side import observation as deploy
from jaxnav.robot_side.observation import Sensor

NAN, INF = float("nan"), float("inf")
# What an exported policy of the default settings carries (test_export checks the export writes it).
SENSOR = Sensor(fov=math.radians(60.0), num_sectors=8, range_min=0.6, range_max=8.0)
COMMANDS = np.array([[0.5, 0.0], [0.0, 1.5], [0.0, -1.5]], np.float32)  # forward, left, right


@pytest.fixture(scope="module")
def scene(one_row_env):
    """(obs [8], per-ray depths [24], ray angles [24], robot-side Sensor) of a lopsided room.

    Obstacles on the left and right differ so a mirrored sector order would fail; the room is 20 m
    long so the rays straight ahead read beyond range_max (clipped).
    """
    # One row of rays: what a LaserScan, or the horizon row of a depth image, reads.
    env, reset, _ = one_row_env
    state = start_in(env, reset, ONE_ROW_ROOMS.index(LOPSIDED))
    params = state.info["params"]
    depths = jax.jit(ray_depths, static_argnums=(2, 3))(
        params, state.data.qpos, env.sensor, env.robot
    )
    obs, depths = np.asarray(state.obs), np.asarray(depths)
    assert len(set(np.round(obs, 3))) >= 5 and obs.max() == env.sensor.range_max  # a varied scene
    cfg = env.sensor
    sensor = Sensor(cfg.fov, cfg.num_sectors, cfg.range_min, cfg.range_max)
    return obs, depths, cfg.ray_angles, sensor


def test_scan_reproduces_simulated_sectors(scene):
    obs, depths, angles, sensor = scene
    ranges = depths / np.cos(angles)  # what a LaserScan of the same rays would read
    np.testing.assert_allclose(deploy.scan_to_sectors(ranges, angles, sensor), obs, atol=1e-4)
    # A real scan is wider than the camera: beams beyond +-fov/2 must not count.
    wide = np.linspace(-math.pi / 2, math.pi / 2, 41)
    outside = np.abs(wide) > sensor.fov / 2
    ranges = np.concatenate([ranges, np.full(outside.sum(), 0.7)])
    angles = np.concatenate([angles, wide[outside]])
    np.testing.assert_allclose(deploy.scan_to_sectors(ranges, angles, sensor), obs, atol=1e-4)


def test_depth_image_reproduces_simulated_sectors(scene):
    obs, depths, angles, sensor = scene
    row = np.where(np.isinf(depths), 20.0, depths)[::-1]  # column 0 = leftmost ray
    np.testing.assert_allclose(deploy.depth_image_to_sectors(row[None], sensor), obs, atol=1e-4)
    # The floor below the horizon reads close; only the horizon row must count.
    image = np.stack([row, np.full_like(row, 0.7), np.full_like(row, 0.65)])
    got = deploy.depth_image_to_sectors(image, sensor, rows=[0])
    np.testing.assert_allclose(got, obs, atol=1e-4)
    got = deploy.depth_image_to_sectors(image, sensor, rows=slice(0, 1), column_angles=angles[::-1])
    np.testing.assert_allclose(got, obs, atol=1e-4)


def test_blind_zone_reads_near():
    """The Astra's 0 (too close or no return) must never read far: a mostly blind sector is near."""
    zeros = deploy.depth_image_to_sectors(np.zeros((480, 640), np.float32), SENSOR)
    np.testing.assert_array_equal(zeros, np.full(8, 0.6, np.float32))
    assert zeros.dtype == np.float32
    image = np.full((6, 80), 5.0, np.float32)  # 10 columns per sector, sector 0 = columns 70..79
    image[:, 75:] = 0.0  # sector 0: half its pixels unknown -> near
    image[:3, 60:70] = np.nan  # sector 1: half unknown (NaN) -> near
    image[:2, 50:60] = 0.0  # sector 2: a third unknown -> the minimum of the rest
    image[5, 52] = 2.5
    image[:, 40:50] = [[3.0], [4.0], [0.0], [-1.0], [np.inf], [3.5]]  # sector 3: 2 of 6 unknown
    image[:, 30:40] = 0.3  # sector 4: nearer than range_min -> range_min
    image[:, 20:30] = 9.0  # sector 5: beyond range_max -> range_max
    image[0, 0] = np.inf  # sector 7: +inf is no return within range, not unknown
    got = deploy.depth_image_to_sectors(image, SENSOR)
    np.testing.assert_allclose(got, [0.6, 0.6, 2.5, 3.0, 0.6, 8.0, 5.0, 5.0])
    # blind_fraction is the share from which a sector reads near; 1: only an all-unknown sector.
    got = deploy.depth_image_to_sectors(image, SENSOR, blind_fraction=0.3)
    np.testing.assert_allclose(got[:4], [0.6, 0.6, 0.6, 0.6])
    got = deploy.depth_image_to_sectors(image, SENSOR, blind_fraction=1.0)
    np.testing.assert_allclose(got[:4], [5.0, 5.0, 2.5, 3.0])
    with pytest.raises(ValueError, match=r"blind_fraction: must be in \(0, 1\], got 0"):
        deploy.depth_image_to_sectors(image, SENSOR, blind_fraction=0)
    # Only the rows considered count: a blind floor row outside them changes nothing.
    image[5] = 0.0
    assert deploy.depth_image_to_sectors(image, SENSOR, rows=slice(0, 5))[6] == 5.0


def test_reduce_sectors_rule():
    """The rule the simulator mirrors, on readings given directly (NaN = unknown)."""
    depth = [NAN, 2.0, 1.0, 3.0, NAN, NAN, 0.2, INF, -INF, 4.0]
    sector = [0, 0, 1, 1, 2, 2, 3, 4, 5, 7]  # sector 6 has no reading
    got = deploy.reduce_sectors(depth, sector, SENSOR)
    np.testing.assert_allclose(got, [0.6, 1.0, 0.6, 0.6, 8.0, 0.6, 0.6, 4.0])


def test_scan_reading_rules():
    # One sector per beam triple, right to left; expected sector values after the rules.
    beams = [
        [0.0, 7.0, 2.0],  # 0: nearer than measurable -> range_min
        [INF, -1.0, 3.0],  # negative -> range_min
        [NAN, NAN, INF],  # NaN unknown (REP 117): 2 of 3 unknown -> range_min
        [0.3, 5.0, 6.0],  # below range_min -> range_min
        [9.0, 12.0, INF],  # beyond range_max -> range_max
        [-INF, 1.5, 1.0],  # -> range_min
        [4.0, 4.0, 4.0],
        [7.0, NAN, 2.5],  # -> 2.5
    ]
    want = [0.6, 0.6, 0.6, 0.6, 8.0, 0.6, 4.0, 2.5]
    depth = np.array(beams, np.float64).ravel()  # [24], right to left
    angles = (np.arange(24) + 0.5) / 24 * SENSOR.fov - 0.5 * SENSOR.fov  # the simulator's rays
    with np.errstate(invalid="ignore"):
        ranges = depth / np.cos(angles)
    np.testing.assert_allclose(deploy.scan_to_sectors(ranges, angles, SENSOR), want, rtol=1e-6)


def test_uneven_widths_and_geometry_helpers():
    # 10 columns into 8 sectors: slices of 1 or 2 columns, rightmost first.
    image = np.arange(1.0, 11.0)[None]  # column 0 (left) = 1 m ... column 9 (right) = 10 m
    got = deploy.depth_image_to_sectors(image, Sensor(SENSOR.fov, 8, 0.6, 20.0))
    assert got[0] == 10.0 and got[-1] == 1.0 and np.all(np.diff(got) < 0)
    with pytest.raises(ValueError, match="fewer than 8 sectors"):
        deploy.depth_image_to_sectors(np.ones((2, 5)), SENSOR)
    angles = deploy.pinhole_column_angles(640, SENSOR.fov)
    assert angles[0] > 0 > angles[-1] and np.allclose(angles, -angles[::-1])
    assert abs(angles[0] - math.radians(30)) < math.radians(0.1)
    rows = deploy.horizon_rows(480, math.radians(49.5), 2.0)
    assert rows[0] + rows[-1] == 479 and 30 < len(rows) < 40  # symmetric about the centre
    tilted = deploy.horizon_rows(480, math.radians(49.5), 2.0, tilt=math.radians(5))
    assert tilted.mean() < rows.mean()  # looking down: the horizon is higher in the image
    assert len(deploy.horizon_rows(480, math.radians(49.5), 0.0)) == 1


FIVE_ROWS = SensorConfig(rows=5)


def rows_sensor(**changes):
    """The robot-side `Sensor` of a 5-row policy of the TurtleBot 2i (camera 0.295 m, level)."""
    base = dict(elevations=tuple(FIVE_ROWS.elevations), camera_height=0.295)
    return Sensor(SENSOR.fov, 8, 0.6, 8.0, **{**base, **changes})


def test_ray_pixels_follow_the_simulators_rays():
    sensor = rows_sensor()
    pixels = deploy.ray_pixels(sensor, 480, 640, ASTRA_VFOV, azimuths=FIVE_ROWS.ray_angles)
    focal = 240 / math.tan(0.5 * ASTRA_VFOV)
    across = (319.5 - pixels.cols) / focal
    up = (239.5 - pixels.rows) / focal
    azimuth, elevation = np.arctan(across), np.arctan(up / np.hypot(1.0, across))
    one_pixel = 1 / focal
    assert np.abs(azimuth - FIVE_ROWS.ray_angles).max() < one_pixel
    assert np.abs(elevation - FIVE_ROWS.elevations[:, None]).max() < one_pixel
    np.testing.assert_array_equal(pixels.sector, np.arange(24) // 3)
    np.testing.assert_allclose(pixels.rise, up)  # a level camera: height per metre of depth
    dense = deploy.ray_pixels(sensor, 480, 640, ASTRA_VFOV)  # every column within +-30 deg
    assert 600 < dense.cols.size < 620 and np.all(np.diff(dense.cols) == 1)
    assert np.all(np.diff(dense.sector) <= 0) and dense.sector[-1] == 0  # sector 0 on the right
    low = deploy.ray_pixels(rows_sensor(elevations=(-0.45,)), 480, 640, ASTRA_VFOV)
    assert low.rows.max() == 479  # beyond the image: its edge row


def test_floor_is_left_out_of_a_depth_image():
    """A 5-row policy's rays see the floor from 0.64-0.74 m out: it is no obstacle on the robot
    either, while what stands above the floor margin (2 cm + 1 cm per metre) is."""

    def obs(image, sensor=None):
        return deploy.depth_image_to_sectors(image, sensor or rows_sensor(), vfov=ASTRA_VFOV)

    np.testing.assert_allclose(obs(floor_image()), 5.0, rtol=1e-6)  # the wall, not the floor
    unruled = obs(floor_image(), rows_sensor(camera_height=None))  # no floor rule
    assert 0.6 < unruled.min() and unruled.max() < 0.74  # the lowest row's floor, as obstacle
    # A 10 cm face 1 m ahead: the second row meets it 4.8 cm up ahead (obstacle), but 0.9 cm up
    # at +-30 deg, within the floor margin (taken for floor, as in the simulator).
    np.testing.assert_allclose(obs(floor_image(box=(1.0, 0.1)))[1:7], 1.0, rtol=1e-6)
    # A camera 5 cm lower than the robot side believes sees the floor 5 cm up: obstacles
    # (calibrate the mount); 5 cm higher, the floor 5 cm down: still floor.
    assert obs(floor_image(camera_height=0.245)).max() < 1.0
    np.testing.assert_allclose(obs(floor_image(camera_height=0.345)), 5.0, rtol=1e-6)
    with pytest.raises(ValueError, match="give vfov, or rows and column_angles"):
        deploy.depth_image_to_sectors(floor_image(), rows_sensor(), rows=[0], vfov=ASTRA_VFOV)


def test_floor_mask_rule():
    sensor = rows_sensor()  # range 0.6-8 m, margin 0.02 m + 0.01 m per metre
    rise = np.array([-0.4, -0.4, -0.4, -0.4, -0.04, 0.1, -0.4, -0.4])
    reading = np.array([0.7375, 0.675, 0.65, 1.0, 0.0, 0.0, 0.0, np.inf])
    known = np.array([True, True, True, True, False, False, False, True])
    # On the floor; 2.5 cm up (margin 2.7 cm); 3.5 cm up (margin 2.65 cm); below the floor
    # (noise); unknown, floor 7.4 m out (in range: not floor); unknown, looking up; unknown,
    # floor at 0.74 m (in range: not floor); +inf looking down: through the floor.
    want = [True, True, False, True, False, False, False, True]
    got = deploy.floor_mask(reading, known, rise, 0.295, sensor)
    np.testing.assert_array_equal(got, want)
    # Unknown where the camera cannot read the floor (nearer than 0.6 m, beyond 8 m): floor.
    far = deploy.floor_mask(np.zeros(2), np.zeros(2, bool), np.array([-0.6, -0.03]), 0.295, sensor)
    np.testing.assert_array_equal(far, [True, True])


def test_action_to_twist():
    assert deploy.action_to_twist(0, COMMANDS) == (0.5, 0.0)
    assert deploy.action_to_twist(1, COMMANDS) == (0.0, 1.5)  # left = positive yaw rate
    assert deploy.action_to_twist(2, COMMANDS) == (0.0, -1.5)
    assert deploy.action_to_twist(np.int64(0), COMMANDS, speed_calibration=1.25) == (0.625, 0.0)
    assert deploy.action_to_twist(2, COMMANDS * 0.8, speed_calibration=1.25) == pytest.approx(
        (0.0, -1.5)
    )
    with pytest.raises(ValueError, match=r"action must be in 0\.\.2, got 3"):
        deploy.action_to_twist(3, COMMANDS)


def test_sensor_checks_name_the_field():
    with pytest.raises(ValueError, match="Sensor.num_sectors"):
        Sensor(SENSOR.fov, 0, 0.6, 8.0)
    with pytest.raises(ValueError, match="Sensor.range_min/range_max"):
        Sensor(SENSOR.fov, 8, 8.0, 0.6)


class TurnAway:
    """A stand-in policy: turns away from the nearer side; carries what a NumpyPolicy carries."""

    sensor, commands = Sensor(SENSOR.fov, 8, 0.6, 8.0), COMMANDS * 0.5

    def __call__(self, obs):
        return 1 if obs[0] < obs[-1] else 2


def test_controller_in_one_call():
    controller = deploy.Controller(TurnAway(), speed_calibration=1.1)
    image = np.full((3, 80), 5.0, np.float32)
    image[:, -10:] = 1.0  # close on the right
    assert controller.image_to_twist(image) == pytest.approx((0.0, 0.75 * 1.1))
    angles = np.linspace(-0.5, 0.5, 30)
    ranges = np.where(angles > 0.3, 1.0, 5.0)  # close on the left
    assert controller.scan_to_twist(ranges, angles) == pytest.approx((0.0, -0.75 * 1.1))
    with pytest.raises(ValueError, match="Controller.speed_calibration"):
        deploy.Controller(TurnAway(), speed_calibration=0.0)
