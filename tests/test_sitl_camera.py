"""The SITL camera: geometry oracles, and pupil-apriltags on rendered frames (ids, centres)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from companion.errors import ConfigError, InputError
from companion.rotation import quaternion_from_euler, rotation_from_quaternion
from companion.vision.camera import (
    BodyPose,
    CameraModel,
    camera_pose_ned,
    distort_normalized,
    ground_footprint,
    pixels_to_ground,
    project_points,
    undistort_normalized,
)
from companion.vision.tags import TagDetector, detect_centres
from sitl.camera import Renderer, Tag, tag_bitmap

FloatArray = NDArray[np.float64]

ALTITUDE_M = 8.0
TAG_SIZE_M = 0.5  # 20 px across at 8 m with the default camera
CENTRE_TOL_PX = 1.0
BARREL = (-0.2, 0.05, 0.001, -0.001, 0.0)

# Tags spread over the view of a level camera at 8 m (north +-6 m, east +-8 m), all yaws.
LAYOUT = [(0.0, 0.0, 0.0), (3.0, 2.0, 0.3), (-2.0, -4.0, 1.0), (4.0, -5.0, 2.0),
          (-4.0, 5.0, -1.0), (1.5, 6.0, 0.7), (-3.5, -6.5, 0.2)]
TAGS = [Tag(10 + i, n, e, TAG_SIZE_M, yaw) for i, (n, e, yaw) in enumerate(LAYOUT)]


@pytest.fixture(scope="module")
def detector() -> TagDetector:
    return TagDetector(families="tag36h11", quad_decimate=1.0, nthreads=1)


def _detect(detector: TagDetector, image: NDArray[np.uint8]) -> dict[int, FloatArray]:
    """Detected tag id -> centre in OpenCV pixel convention."""
    ids, centres = detect_centres(detector, image)
    assert len(set(ids.tolist())) == len(ids), "one tag detected twice"
    return {int(i): c for i, c in zip(ids, centres, strict=True)}


def _expected(camera: CameraModel, pose: BodyPose, tags: list[Tag],
              margin_px: float = 4.0) -> dict[int, FloatArray]:
    """Tags whose printed square lies margin_px inside the image: id -> projected centre."""
    out: dict[int, FloatArray] = {}
    for tag in tags:
        corners, front = project_points(camera, pose, tag.corners_ned(10))
        inside = (front.all() and np.all(corners >= margin_px)
                  and np.all(corners[:, 0] <= camera.width_px - 1 - margin_px)
                  and np.all(corners[:, 1] <= camera.height_px - 1 - margin_px))
        if inside:
            centre, _ = project_points(camera, pose, np.array([[tag.north_m, tag.east_m, 0.0]]))
            out[tag.tag_id] = centre[0]
    return out


def _render_and_check(detector: TagDetector, camera: CameraModel, pose: BodyPose,
                      tags: list[Tag], min_expected: int) -> dict[int, FloatArray]:
    image = Renderer(camera, texture_seed=7).render(pose, tags, np.random.default_rng(1))
    found = _detect(detector, image)
    expected = _expected(camera, pose, tags)
    assert len(expected) >= min_expected
    assert set(expected) <= set(found)
    # A tag cut by the frame edge may still decode (field notes); one wholly outside may not.
    assert set(found) <= set(_expected(camera, pose, tags, margin_px=-200.0))
    for tag_id, centre in expected.items():
        error = float(np.hypot(*(found[tag_id] - centre)))
        assert error < CENTRE_TOL_PX, f"tag {tag_id}: centre error {error:.2f} px"
    return found


def _axis_ground_point(camera: CameraModel, pose: BodyPose) -> tuple[float, float]:
    """Where the optical axis meets the ground (north, east)."""
    r_ned_cam, centre = camera_pose_ned(camera, pose)
    axis = r_ned_cam[:, 2]
    t = -centre[2] / axis[2]
    return float(centre[0] + t * axis[0]), float(centre[1] + t * axis[1])


# ---------------------------------------------------------------------------------------------
# Detection on rendered frames


@pytest.mark.parametrize("camera", [
    CameraModel(),
    CameraModel(dist=BARREL),
    CameraModel(dist=(0.08, -0.02, 0.0, 0.0, 0.0)),
    CameraModel(mount_offset_m=(0.3, -0.2, 0.1)),
    CameraModel(width_px=1280, height_px=720),
], ids=["default", "barrel", "pincushion", "mount-offset", "720p"])
def test_level_hover_detects_every_tag_at_its_projection(
        detector: TagDetector, camera: CameraModel) -> None:
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M)
    _render_and_check(detector, camera, pose, TAGS, min_expected=len(TAGS) - 2)


def test_level_hover_image_is_a_map_view_north_up(detector: TagDetector) -> None:
    """Default mount, heading north, 8 m: 1 m on the ground is fx / 8 = 40 px; north is up."""
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M)
    tags = [Tag(1, 3.0, 2.0, TAG_SIZE_M)]
    found = _detect(detector, Renderer(CameraModel(), 3).render(pose, tags,
                                                                 np.random.default_rng(0)))
    np.testing.assert_allclose(found[1], [319.5 + 2.0 * 40.0, 239.5 - 3.0 * 40.0], atol=1.0)


@pytest.mark.parametrize(("roll_deg", "pitch_deg", "yaw_deg"), [
    (0.0, 5.0, 0.0), (-5.0, 0.0, 0.0), (0.0, 0.0, 90.0), (8.0, -6.0, 30.0), (15.0, 20.0, -120.0),
])
def test_attitude_moves_detections_as_projected(
        detector: TagDetector, roll_deg: float, pitch_deg: float,
        yaw_deg: float) -> None:
    pose = BodyPose.from_euler(0.0, 1.0, -0.5, -ALTITUDE_M, math.radians(roll_deg),
                               math.radians(pitch_deg), math.radians(yaw_deg))
    for camera in (CameraModel(), CameraModel(dist=BARREL, mount_offset_m=(0.1, 0.05, 0.1))):
        _render_and_check(detector, camera, pose, TAGS, min_expected=3)


def test_pitch_shifts_and_yaw_rotates_the_image(detector: TagDetector) -> None:
    """Signs by hand: nose up 5 deg moves the nadir tag ~fx tan 5 deg down the image; facing
    east puts a tag 3 m north on the left of the image."""
    camera = CameraModel()
    renderer = Renderer(camera, 3)
    tags = [Tag(1, 0.0, 0.0, TAG_SIZE_M), Tag(2, 3.0, 0.0, TAG_SIZE_M)]
    rng = np.random.default_rng(0)
    level = _detect(detector, renderer.render(
        BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M), tags, rng))
    pitched = _detect(detector, renderer.render(
        BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M, pitch_rad=math.radians(5.0)), tags, rng))
    yawed = _detect(detector, renderer.render(
        BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M, yaw_rad=math.radians(90.0)), tags, rng))
    shift = pitched[1] - level[1]
    assert shift[0] == pytest.approx(0.0, abs=1.0)
    assert shift[1] == pytest.approx(320.0 * math.tan(math.radians(5.0)), abs=1.0)
    np.testing.assert_allclose(level[2], [319.5, 239.5 - 120.0], atol=1.0)
    np.testing.assert_allclose(yawed[2], [319.5 - 120.0, 239.5], atol=1.0)


def test_hidden_tags_are_missed_and_distractors_detected(
        detector: TagDetector) -> None:
    camera = CameraModel()
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M)
    distractors = [Tag(300, -1.0, 3.0, TAG_SIZE_M, 0.4), Tag(301, 2.0, -2.0, 0.6)]
    image = Renderer(camera, 5).render(pose, TAGS, np.random.default_rng(2),
                                       distractors=distractors, hidden={10, 12})
    found = _detect(detector, image)
    expected = _expected(camera, pose, TAGS + distractors)
    assert {10, 12} <= set(expected)
    assert set(found) == set(expected) - {10, 12}
    for tag in distractors:
        assert float(np.hypot(*(found[tag.tag_id] - expected[tag.tag_id]))) < CENTRE_TOL_PX


def test_every_tag36h11_id_is_drawn_decodable(detector: TagDetector) -> None:
    """Bitmaps from OpenCV's table decode as the same id in pupil-apriltags (sampled ids)."""
    for tag_id in (0, 1, 42, 311, 586):
        cells = tag_bitmap(tag_id)
        image = np.full((160, 160), 128, dtype=np.uint8)
        image[30:130, 30:130] = cv2.resize(cells, (100, 100),
                                           interpolation=cv2.INTER_NEAREST).astype(np.uint8)
        assert list(_detect(detector, image)) == [tag_id]


def test_tags_outside_the_footprint_change_no_pixel() -> None:
    camera = CameraModel(dist=BARREL)
    pose = BodyPose.from_euler(0.0, 2.0, 1.0, -6.0, 0.2, -0.1, 0.8)
    polygon = ground_footprint(camera, pose, samples_per_edge=16).astype(np.float32)
    outside = [Tag(i, n, e, 0.4) for i, (n, e) in enumerate(
        [(30.0, 0.0), (-30.0, 5.0), (0.0, 40.0), (15.0, -25.0)])]
    for tag in outside:
        corners = tag.corners_ned(10)[:, :2].astype(np.float32)
        assert all(cv2.pointPolygonTest(polygon, (float(c[0]), float(c[1])), False) < 0
                   for c in corners)
    renderer = Renderer(camera, 9)
    inside = [Tag(50, *_axis_ground_point(camera, pose), 0.4)]
    with_outside = renderer.render(pose, inside + outside, np.random.default_rng(4))
    without = renderer.render(pose, inside, np.random.default_rng(4))
    assert np.array_equal(with_outside, without)


# ---------------------------------------------------------------------------------------------
# Rendering: determinism, options, odd poses


def test_same_seeds_same_image_and_seeds_matter() -> None:
    camera = CameraModel()
    pose = BodyPose.from_euler(0.0, 3.0, -2.0, -7.0, 0.05, 0.02, 0.3)
    a = Renderer(camera, 11).render(pose, TAGS, np.random.default_rng(5))
    b = Renderer(camera, 11).render(pose, TAGS, np.random.default_rng(5))
    c = Renderer(camera, 11).render(pose, TAGS, np.random.default_rng(6))
    d = Renderer(camera, 12).render(pose, TAGS, np.random.default_rng(5))
    assert a.dtype == np.uint8 and a.shape == (480, 640)
    assert np.array_equal(a, b)
    diff_noise = np.abs(a.astype(int) - c.astype(int))
    assert 0.5 < diff_noise.mean() < 4.0  # exposure noise only (std 2 per frame)
    assert np.abs(a.astype(int) - d.astype(int)).mean() > 5.0  # another ground texture


def test_noise_std_is_the_configured_exposure_noise() -> None:
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M)
    quiet = Renderer(CameraModel(noise_std=0.0), 1).render(pose, [], np.random.default_rng(0))
    noisy = Renderer(CameraModel(noise_std=4.0), 1).render(pose, [], np.random.default_rng(0))
    residual = noisy.astype(float) - quiet.astype(float)
    assert abs(residual.mean()) < 0.1
    assert residual.std() == pytest.approx(4.0, rel=0.05)


def test_ground_has_moderate_contrast_and_no_visible_period() -> None:
    image = Renderer(CameraModel(noise_std=0.0), 2).render(
        BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M), [], np.random.default_rng(0))
    assert 80.0 < image.mean() < 160.0
    assert 10.0 < image.std() < 50.0
    assert np.percentile(image, 1) > 15 and np.percentile(image, 99) < 240


def test_bgr_option_and_sky_above_the_horizon() -> None:
    camera = CameraModel(mount_rpy_deg=(0.0, 60.0, 0.0))  # looking 60 deg forward of nadir
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M, pitch_rad=0.1)
    image = Renderer(camera, 1).render(pose, [], np.random.default_rng(0), bgr=True)
    assert image.shape == (480, 640, 3)
    assert np.array_equal(image[:, :, 0], image[:, :, 2])
    top = image[:40, :, 0].astype(float)
    assert abs(top.mean() - 200.0) < 2.0 and top.std() < 3.0  # uniform sky
    footprint = ground_footprint(camera, pose, max_range_m=60.0, samples_per_edge=4)
    _, centre = camera_pose_ned(camera, pose)
    ranges = np.hypot(*(footprint - centre[:2]).T)
    assert np.isclose(ranges, 60.0).sum() >= 3  # the sky rays are clipped at max range
    assert np.all(ranges <= 60.0 + 1e-9)


def test_landed_vehicle_renders_without_error() -> None:
    camera = CameraModel(mount_offset_m=(0.0, 0.0, 0.2))  # camera below the body origin
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, 0.0)
    image = Renderer(camera, 1).render(pose, [Tag(1, 0.0, 0.0, 0.5)], np.random.default_rng(0))
    assert image.shape == (480, 640)
    assert ground_footprint(camera, pose).shape == (4, 2)


def test_render_rejects_bad_arguments() -> None:
    renderer = Renderer(CameraModel(), 1)
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -ALTITUDE_M)
    with pytest.raises(InputError, match="rng"):
        renderer.render(pose, [], 3)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="tags"):
        renderer.render(pose, [(1, 2.0)], np.random.default_rng(0))  # type: ignore[list-item]


# ---------------------------------------------------------------------------------------------
# Geometry oracles


def test_default_mount_maps_camera_axes_to_body() -> None:
    r_body_cam = CameraModel().rotation_body_camera()
    np.testing.assert_allclose(r_body_cam @ [1, 0, 0], [0, 1, 0], atol=1e-15)  # x -> right
    np.testing.assert_allclose(r_body_cam @ [0, 1, 0], [-1, 0, 0], atol=1e-15)  # y -> back
    np.testing.assert_allclose(r_body_cam @ [0, 0, 1], [0, 0, 1], atol=1e-15)  # z -> down


def test_quaternion_from_euler_matches_elementary_rotations() -> None:
    yaw = rotation_from_quaternion(quaternion_from_euler(0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(yaw @ [1, 0, 0], [0, 1, 0], atol=1e-15)  # forward -> east
    pitch = rotation_from_quaternion(quaternion_from_euler(0.0, math.pi / 2, 0.0))
    np.testing.assert_allclose(pitch @ [1, 0, 0], [0, 0, -1], atol=1e-15)  # nose up
    roll = rotation_from_quaternion(quaternion_from_euler(math.pi / 2, 0.0, 0.0))
    np.testing.assert_allclose(roll @ [0, 1, 0], [0, 0, 1], atol=1e-15)  # right wing down


@settings(deadline=None, max_examples=40)
@given(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-math.pi, math.pi),
       st.floats(-0.2, 0.2), st.floats(0.0, 0.1))
def test_project_points_matches_opencv(roll: float, pitch: float, yaw: float, k1: float,
                                       p: float) -> None:
    camera = CameraModel(dist=(k1, 0.02, p * 0.01, -p * 0.01, 0.0),
                         mount_offset_m=(0.1, -0.05, 0.08), mount_rpy_deg=(2.0, -3.0, 1.0))
    pose = BodyPose.from_euler(1.0, 2.0, -3.0, -9.0, roll, pitch, yaw)
    points = np.random.default_rng(0).uniform([-10, -12, -1], [14, 8, 0.5], (50, 3))
    pixels, front = project_points(camera, pose, points)
    r_ned_cam, centre = camera_pose_ned(camera, pose)
    rvec, _ = cv2.Rodrigues(r_ned_cam.T)
    tvec = -r_ned_cam.T @ centre
    reference, _ = cv2.projectPoints(points[front], rvec, tvec, camera.matrix(),
                                     np.array(camera.dist))
    np.testing.assert_allclose(pixels[front], reference.reshape(-1, 2), atol=1e-6)
    assert np.isnan(pixels[~front]).all()


def test_points_behind_the_camera_are_not_in_front() -> None:
    pose = BodyPose.from_euler(0.0, 0.0, 0.0, -5.0)
    pixels, front = project_points(CameraModel(), pose, np.array([[0.0, 0.0, -10.0],
                                                                  [0.0, 0.0, 0.0]]))
    assert front.tolist() == [False, True]
    assert np.isnan(pixels[0]).all()
    np.testing.assert_allclose(pixels[1], [319.5, 239.5])


def test_level_footprint_is_the_hand_computed_rectangle() -> None:
    """90 deg hFOV, 4:3, 8 m: east +-8 m, north +-6 m, image top = north."""
    footprint = ground_footprint(CameraModel(), BodyPose.from_euler(0.0, 5.0, -3.0, -8.0))
    expected = [[5 + 6, -3 - 8], [5 + 6, -3 + 8], [5 - 6, -3 + 8], [5 - 6, -3 - 8]]
    np.testing.assert_allclose(footprint, expected, atol=1e-9)


@settings(deadline=None, max_examples=40)
@given(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-math.pi, math.pi),
       st.floats(2.0, 40.0), st.sampled_from([(0.0,) * 5, BARREL]))
def test_footprint_projects_back_onto_the_image_border(
        roll: float, pitch: float, yaw: float, height_m: float,
        dist: tuple[float, float, float, float, float]) -> None:
    """Tilts up to ~24 deg keep the whole border (51 deg off-axis at the corners) on the ground."""
    camera = CameraModel(dist=dist, mount_offset_m=(0.1, 0.0, 0.05))
    pose = BodyPose.from_euler(0.0, -4.0, 7.0, -height_m, roll, pitch, yaw)
    footprint = ground_footprint(camera, pose, max_range_m=1e4, samples_per_edge=4)
    points = np.column_stack([footprint, np.zeros(len(footprint))])
    pixels, front = project_points(camera, pose, points)
    assert front.all()
    on_vertical = np.isclose(pixels[:, 0], -0.5, atol=1e-6) | np.isclose(pixels[:, 0], 639.5,
                                                                          atol=1e-6)
    on_horizontal = (np.isclose(pixels[:, 1], -0.5, atol=1e-6)
                     | np.isclose(pixels[:, 1], 479.5, atol=1e-6))
    assert np.all(on_vertical | on_horizontal)
    corners = pixels[::4]  # the first vertex of each edge is an image corner
    np.testing.assert_allclose(corners, [[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5],
                                         [-0.5, 479.5]], atol=1e-6)


@settings(deadline=None, max_examples=60)
@given(st.floats(-1.2, 1.2), st.floats(-0.9, 0.9))
def test_undistort_inverts_distort(x: float, y: float) -> None:
    xy = np.array([[x, y]])
    back = undistort_normalized(BARREL, distort_normalized(BARREL, xy))
    np.testing.assert_allclose(back, xy, atol=1e-10)


def test_camera_defaults_and_from_hfov() -> None:
    camera = CameraModel()
    assert (camera.fx_px, camera.fy_px, camera.cx_px, camera.cy_px) == (320.0, 320.0, 319.5,
                                                                        239.5)
    wide = CameraModel.from_hfov(120.0, 1280, 720)
    assert wide.fx_px == pytest.approx(640.0 / math.tan(math.radians(60.0)))
    assert (wide.cx_px, wide.cy_px) == (639.5, 359.5)
    np.testing.assert_allclose(camera.matrix(), np.array([[320.0, 0.0, 319.5], [0.0, 320.0, 239.5],
                                                          [0.0, 0.0, 1.0]]))


@pytest.mark.parametrize(("kwargs", "key"), [
    ({"width_px": 0}, "camera.width_px"),
    ({"height_px": 480.0}, "camera.height_px"),
    ({"fx_px": -1.0}, "camera.fx_px"),
    ({"fy_px": math.inf}, "camera.fy_px"),
    ({"cx_px": 1000.0}, "camera.cx_px"),
    ({"cy_px": "centre"}, "camera.cy_px"),
    ({"dist": (0.1, 0.2)}, "camera.dist"),
    ({"dist": (-0.9, 0.0, 0.0, 0.0, 0.0)}, "camera.dist"),  # folds over inside the image
    ({"dist": (0.0, 0.0, math.nan, 0.0, 0.0)}, "camera.dist"),
    ({"mount_rpy_deg": "down"}, "camera.mount_rpy_deg"),
    ({"mount_offset_m": (100.0, 0.0, 0.0)}, "camera.mount_offset_m"),
    ({"rate_hz": 0.0}, "camera.rate_hz"),
    ({"noise_std": -1.0}, "camera.noise_std"),
])
def test_bad_camera_parameters_name_the_key(kwargs: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        CameraModel(**kwargs)  # type: ignore[arg-type]
    assert info.value.key == key


def test_bad_renderer_parameters_name_the_key() -> None:
    with pytest.raises(ConfigError, match="ground_m_per_px"):
        Renderer(CameraModel(), 1, ground_m_per_px=0.0)
    with pytest.raises(ConfigError, match="texture_seed"):
        Renderer(CameraModel(), 1.5)  # type: ignore[arg-type]


def test_bad_poses_and_tags_raise_input_error() -> None:
    with pytest.raises(InputError, match="q_wxyz"):
        BodyPose(0.0, 0.0, 0.0, -5.0, (1.0, 1.0, 0.0, 0.0))
    with pytest.raises(InputError, match="down_m"):
        BodyPose(0.0, 0.0, 0.0, math.nan, (1.0, 0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="tag_id"):
        Tag(587, 0.0, 0.0, 0.5)
    with pytest.raises(InputError, match="size_m"):
        Tag(1, 0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="points_ned"):
        project_points(CameraModel(), BodyPose.from_euler(0, 0, 0, -5), np.zeros((3, 2)))


def test_pixels_to_ground_inverts_project_points_under_any_attitude() -> None:
    camera = CameraModel(dist=(-0.05, 0.01, 0.001, -0.001, 0.0), mount_offset_m=(0.1, 0.0, 0.05))
    pose = BodyPose.from_euler(0.0, 3.0, -2.0, -8.0, roll_rad=0.1, pitch_rad=-0.15, yaw_rad=1.2)
    rng = np.random.default_rng(4)
    ground = np.column_stack([rng.uniform(-3, 9, 20), rng.uniform(-8, 4, 20), np.zeros(20)])
    pixels, in_front = project_points(camera, pose, ground)
    assert in_front.all()
    np.testing.assert_allclose(pixels_to_ground(camera, pose, pixels), ground[:, :2], atol=1e-6)
    # A ray above the horizon never meets the ground.
    level_ahead = CameraModel(mount_rpy_deg=(0.0, 90.0, 0.0))
    top = np.array([[319.5, 0.0]])
    assert np.isnan(pixels_to_ground(level_ahead, pose, top)).all()
