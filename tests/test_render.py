"""The renderer's geometry and texture: world points appear where the camera model projects them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import R_BODY_CAM_FORWARD, R_BODY_CAM_NADIR, R_from_euler321, rot_y
from mavvo.sim.world.render import Renderer, apply_effects
from mavvo.sim.world.scene import BoxSpec, PatchSpec, TextureLayer, World, WorldSpec, concrete_tile, grass_tile

PINHOLE = CameraModel(640, 480, 500.0, 500.0, 319.5, 239.5)
RADTAN = CameraModel(640, 480, 420.0, 420.0, 322.0, 236.0, "pinhole", (-0.28, 0.07, 0.0005, -0.0003))
FISHEYE = CameraModel(640, 480, 260.0, 260.0, 320.0, 240.0, "fisheye", (0.02, -0.01, 0.003, -0.001))


def _grid_corners_px(camera: CameraModel, R_ned_cam: np.ndarray, p_ned_cam: np.ndarray, square_m: float) -> np.ndarray:
    """Pixels of the checkerboard's X-corners (integer multiples of square_m on z = 0) well inside the
    image and with squares big enough around them (>= 25 px; smaller ones are minified, and aliasing then moves edges by up to half a pixel) for a corner detector to resolve."""
    n, e = np.meshgrid(np.arange(-40, 41), np.arange(-40, 41))
    X = np.column_stack([n.ravel() * square_m, e.ravel() * square_m, np.zeros(n.size)])

    def project(points: np.ndarray) -> np.ndarray:
        x_cam = (points - p_ned_cam) @ R_ned_cam
        uv = camera.bearings_to_pixels(x_cam)
        uv[x_cam[:, 2] < 0.5] = np.nan
        return uv

    uv = project(X)
    for step in ([square_m, 0, 0], [-square_m, 0, 0], [0, square_m, 0], [0, -square_m, 0]):
        uv[~(np.linalg.norm(project(X + step) - uv, axis=1) >= 25.0)] = np.nan
    margin = 12
    inside = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] > margin) & (uv[:, 0] < camera.width_px - margin)
    inside &= (uv[:, 1] > margin) & (uv[:, 1] < camera.height_px - margin)
    return uv[inside]


@pytest.mark.parametrize(
    "camera, rpy, height_m, mount",
    [
        (PINHOLE, (0.0, 0.0, 0.0), 6.0, R_BODY_CAM_NADIR),
        (PINHOLE, (0.12, -0.08, 0.7), 7.5, R_BODY_CAM_NADIR),
        (PINHOLE, (0.05, 0.0, -0.4), 3.0, rot_y(-0.9) @ R_BODY_CAM_FORWARD),  # oblique: 52 deg down
        (RADTAN, (0.1, 0.05, 0.3), 6.0, R_BODY_CAM_NADIR),
        (FISHEYE, (-0.05, 0.1, 1.2), 5.0, R_BODY_CAM_NADIR),
    ],
)
def test_checkerboard_corners_appear_where_projected(camera, rpy, height_m, mount):
    world = World.build(WorldSpec(texture="checker", checker_size_m=1.0))
    R_ned_cam = R_from_euler321(*rpy) @ mount
    p = np.array([0.23, -0.41, -height_m])
    img = Renderer(world, camera).render(R_ned_cam, p)
    expected = _grid_corners_px(camera, R_ned_cam, p, 1.0)
    assert len(expected) >= 12

    found = cv2.goodFeaturesToTrack(img, 2000, 0.05, 5, blockSize=5)[:, 0, :]
    found = cv2.cornerSubPix(
        img, found.astype(np.float32), (5, 5), (-1, -1), (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-3)
    )
    d = np.linalg.norm(expected[:, None, :] - found[None, :, :], axis=2).min(axis=1)
    assert np.mean(d < 0.5) >= 0.9, f"median miss {np.median(d):.3f} px, worst {d.max():.3f} px"
    assert np.median(d) < 0.25


def test_box_covers_its_projected_silhouette():
    box = BoxSpec(north_m=1.0, east_m=-0.5, length_m=2.0, width_m=1.5, height_m=1.2, yaw_deg=25.0)
    plain = World.build(WorldSpec(texture_seed=3))
    boxed = World.build(WorldSpec(texture_seed=3, boxes=(box,)))
    R = R_from_euler321(0.05, -0.1, 0.4) @ R_BODY_CAM_NADIR
    p = np.array([-1.0, 0.5, -8.0])
    a = Renderer(plain, PINHOLE).render(R, p)
    b = Renderer(boxed, PINHOLE).render(R, p)
    corners = boxed.boxes[0].corners_ned
    uv = PINHOLE.bearings_to_pixels((corners - p) @ R)
    hull = np.zeros_like(a)
    cv2.fillConvexPoly(hull, np.round(cv2.convexHull(uv.astype(np.float32))[:, 0, :]).astype(np.int32), 1)
    changed = cv2.morphologyEx(
        (np.abs(a.astype(int) - b.astype(int)) > 0).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8)
    )
    inter = np.sum(hull & changed)
    union = np.sum(hull | changed)
    assert hull.sum() > 2000
    assert inter / union > 0.93


def test_a_plain_patch_is_flat_grey_inside_its_projected_outline_and_textured_outside():
    """A turned 1 x 0.6 m patch seen tilted from 1.5 m: the image inside its outline (2 px in from it) is
    the patch's mid-grey, and the floor around it keeps its texture and no corner inside."""
    patch = PatchSpec(north_m=0.2, east_m=-0.1, length_m=1.0, width_m=0.6, yaw_deg=30.0)
    world = World.build(WorldSpec(texture_seed=3, plain_patches=(patch,)))
    R = R_from_euler321(0.05, -0.08, 0.3) @ R_BODY_CAM_NADIR
    p = np.array([0.0, 0.0, -1.5])
    img = Renderer(world, PINHOLE).render(R, p)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    half = np.array([[0.5, -0.3], [0.5, 0.3], [-0.5, 0.3], [-0.5, -0.3]])  # north, east before the turn
    ne = half @ np.array([[c, s], [-s, c]]) + [0.2, -0.1]
    uv = PINHOLE.bearings_to_pixels((np.column_stack([ne, np.zeros(4)]) - p) @ R)
    inside = np.zeros(img.shape, np.uint8)
    cv2.fillConvexPoly(inside, np.round(uv).astype(np.int32), 1)
    core = cv2.erode(inside, np.ones((5, 5), np.uint8)).astype(bool)
    around = ~cv2.dilate(inside, np.ones((5, 5), np.uint8)).astype(bool)
    assert core.sum() > 20000
    assert np.all(img[core] == 128)
    assert img[around].std() > 20  # the floor's texture
    pts = cv2.goodFeaturesToTrack(img, 500, 0.01, 5)[:, 0, :]
    assert not np.any(core[pts[:, 1].astype(int), pts[:, 0].astype(int)])


@pytest.mark.parametrize("height_m", [2.0, 10.0, 40.0, 100.0])
def test_corner_texture_has_corners_everywhere_at_every_height(height_m):
    world = World.build(WorldSpec())
    img = Renderer(world, PINHOLE).render(R_from_euler321(0.02, -0.03, 0.3) @ R_BODY_CAM_NADIR, [3.0, -7.0, -height_m])
    pts = cv2.goodFeaturesToTrack(img, 1000, 0.01, 8)[:, 0, :]
    cells = set(map(tuple, (pts // [160, 120]).astype(int)))
    assert len(pts) >= 300
    assert len(cells) == 16  # every cell of a 4x4 grid holds corners


def test_forward_camera_sees_sky_above_the_horizon():
    world = World.build(WorldSpec())
    img = Renderer(world, PINHOLE).render(R_BODY_CAM_FORWARD, [0.0, 0.0, -5.0])
    assert np.all(img[:200] > 150)  # the horizon is the middle row for a level forward camera
    assert img[300:].std() > 20


def test_world_and_render_are_deterministic_for_a_seed():
    R = R_from_euler321(0.1, 0.0, 0.2) @ R_BODY_CAM_NADIR
    a = Renderer(World.build(WorldSpec(texture_seed=5)), PINHOLE).render(R, [0, 0, -9.0])
    b = Renderer(World.build(WorldSpec(texture_seed=5)), PINHOLE).render(R, [0, 0, -9.0])
    c = Renderer(World.build(WorldSpec(texture_seed=6)), PINHOLE).render(R, [0, 0, -9.0])
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_effects_gain_noise_and_blur():
    img = np.zeros((100, 100), np.uint8)
    img[:, 50:] = 200
    dark = apply_effects(img, gain=0.05)
    assert dark.max() == 10
    noisy = apply_effects(np.full((200, 200), 100, np.uint8), noise_sigma=3.0, rng=np.random.default_rng(1))
    assert abs(noisy.astype(float).std() - 3.0) < 0.2
    # Successive frames get fresh noise: no correlation between them, nor between neighbouring pixels.
    rng = np.random.default_rng(2)
    flat = np.full((200, 200), 100, np.uint8)
    n1, n2 = (apply_effects(flat, noise_sigma=3.0, rng=rng).astype(float) - 100.0 for _ in range(2))
    assert abs(np.corrcoef(n1.ravel(), n2.ravel())[0, 1]) < 0.05
    assert abs(np.corrcoef(n1[:, 1:].ravel(), n1[:, :-1].ravel())[0, 1]) < 0.05
    blurred = apply_effects(img, blur_px=(9.0, 0.0))
    ramp = blurred[50, 40:60].astype(float)
    assert np.all(np.diff(ramp) >= 0) and 3 < np.count_nonzero((ramp > 5) & (ramp < 195)) <= 10
    vertical = apply_effects(img, blur_px=(0.0, 9.0))
    assert np.array_equal(vertical[10:90], img[10:90])  # blur along the edge changes nothing
    with pytest.raises(ValueError, match="rng"):
        apply_effects(img, noise_sigma=1.0, rng=None)


@pytest.mark.parametrize(
    "mount, pitch_rad, height_m, greys",
    [
        (
            R_BODY_CAM_FORWARD,
            -0.25,
            2.0,
            (101, 105),
        ),  # the horizon in view: layers in bands of rows, then the sky's haze
        (R_BODY_CAM_FORWARD, -0.6, 1.0, (101, 105)),
        (R_BODY_CAM_NADIR, 0.0, 40.0, (101, 105)),  # every layer spans the whole image: one box
    ],
)
def test_every_layer_is_drawn_wherever_it_has_weight(mount, pitch_rad, height_m, greys):
    """Each layer is warped only inside the box where its weights are not zero: with layers of constant
    grey 101..105 and sky at 200, a pixel darker than 101 would be a layer cut off where it still counts."""
    layers = tuple(TextureLayer(np.full((64, 64), 101 + k, np.uint8), 0.004 * 8**k) for k in range(5))
    world = World(layers, (), WorldSpec())
    R_ned_cam = R_from_euler321(0.03, pitch_rad, 0.4) @ mount
    img = Renderer(world, PINHOLE).render(R_ned_cam, np.array([3.7, -1.2, -height_m]))
    assert img.min() >= 101, f"{np.count_nonzero(img < 101)} pixels darker than every layer"
    lo, hi = greys
    assert np.count_nonzero((img >= lo) & (img <= hi)) > 0.3 * img.size  # ground, blended from the layers


@pytest.mark.parametrize("draw", [grass_tile, concrete_tile])
def test_ground_textures_are_seeded_and_repeat_without_a_seam(draw):
    tile = draw(512, np.random.default_rng(3)).astype(np.int16)
    assert np.array_equal(tile, draw(512, np.random.default_rng(3)))  # the same floor every time
    assert not np.array_equal(tile, draw(512, np.random.default_rng(4)))
    # The step across the tile's wrap-around edge is one more step between neighbours, row-wise and
    # column-wise: inside the spread of the steps between the tile's own rows and columns.
    for t in (tile, tile.T):
        inner = np.abs(np.diff(t, axis=0)).mean(axis=1)
        seam = np.abs(t[0] - t[-1]).mean()
        assert np.percentile(inner, 0.5) <= seam <= np.percentile(inner, 99.5), (
            seam,
            np.percentile(inner, [0.5, 99.5]),
        )


def test_grass_lets_the_soil_show_between_the_blades():
    tile = grass_tile(512, np.random.default_rng(3))
    # The soil (grey 30) and the dimmest blades of the darkest clumps: with a third more blades (0.08 a
    # texel instead of 0.06) this share was 4.5%, and the test failed.
    assert np.mean(tile < 50) >= 0.05
