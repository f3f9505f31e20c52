"""Feature tracking on rendered images: tracks follow the true projection, detection spreads over the
grid, bad input is refused."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import R_from_euler321
from mavvo.odometry.frontend import Frontend, FrontendOptions
from mavvo.sim.scenarios.loader import load_scenario
from mavvo.sim.world.camera import CameraSpec
from mavvo.sim.world.render import Renderer, apply_effects
from mavvo.sim.world.scene import World, WorldSpec

SPEC = CameraSpec()
CAMERA = SPEC.camera_model()


@pytest.fixture(scope="module")
def renderer() -> Renderer:
    return Renderer(World.build(WorldSpec(texture_seed=5)), CAMERA)


def _pose(k: int) -> tuple[np.ndarray, np.ndarray]:
    """A nadir camera at 20 m, slightly tilted, moving 0.16 m and turning 0.2 deg per frame."""
    R = R_from_euler321(0.02, -0.01, np.radians(0.2 * k)) @ SPEC.R_body_cam()
    return R, np.array([0.15 * k, 0.05 * k, -20.0])


def test_tracks_follow_the_true_projection(renderer: Renderer) -> None:
    fe = Frontend(CAMERA)
    rng = np.random.default_rng(0)
    ground: dict[int, np.ndarray] = {}
    errors = []
    for k in range(15):
        R, p = _pose(k)
        tr = fe.process(apply_effects(renderer.render(R, p), noise_sigma=2.0, rng=rng))
        rays = tr.f_cam @ R.T
        for i, f, ray in zip(tr.ids, tr.f_cam, rays):
            if int(i) not in ground:
                ground[int(i)] = p - p[2] / ray[2] * ray  # where the track was first seen, on z = 0
                continue
            x = (ground[int(i)] - p) @ R
            errors.append(np.arccos(np.clip(f @ (x / np.linalg.norm(x)), -1, 1)) * CAMERA.fx_px)  # pixels
    errors = np.array(errors)
    assert len(errors) > 1000
    assert np.median(errors) < 0.15 and np.percentile(errors, 99) < 1.0


def test_ids_persist_and_new_ones_increase(renderer: Renderer) -> None:
    fe = Frontend(CAMERA)
    a = fe.process(renderer.render(*_pose(0)))
    b = fe.process(renderer.render(*_pose(3)))
    assert a.tracked == 0 and len(a.ids) == FrontendOptions().max_features
    assert np.all(np.diff(a.ids) > 0) and np.all(np.diff(b.ids) > 0)
    survivors = np.intersect1d(a.ids, b.ids)
    assert len(survivors) == b.tracked > 0.9 * len(a.ids)
    assert np.all(b.ids[b.tracked :] > a.ids.max())
    assert np.allclose(np.linalg.norm(b.f_cam, axis=1), 1.0)


def test_detection_spreads_over_the_grid_and_keeps_its_distance(renderer: Renderer) -> None:
    opt = FrontendOptions(max_features=192, grid_cols=8, grid_rows=6, min_distance_px=12.0)
    tr = Frontend(CAMERA, opt).process(renderer.render(*_pose(0)))
    cells = (tr.uv_px[:, 1] * 6 // CAMERA.height_px) * 8 + tr.uv_px[:, 0] * 8 // CAMERA.width_px
    counts = np.bincount(cells.astype(int), minlength=48)
    assert counts.min() >= 1 and counts.max() <= 192 // 48
    d = np.linalg.norm(tr.uv_px[:, None] - tr.uv_px[None], axis=2) + np.eye(len(tr.uv_px)) * 1e9
    assert d.min() >= 12.0 - 1e-6


def test_textureless_image_gives_no_tracks() -> None:
    rng = np.random.default_rng(1)
    flat = apply_effects(np.full((480, 640), 120, np.uint8), noise_sigma=2.0, rng=rng)
    assert len(Frontend(CAMERA).process(flat).ids) < 20


@pytest.mark.parametrize(
    "image, match",
    [
        (np.zeros((480, 640), np.float32), "uint8"),
        (np.zeros((480, 640, 3), np.uint8), "uint8"),
        (np.zeros((240, 320), np.uint8), "640x480"),
    ],
)
def test_bad_images_are_refused(image: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Frontend(CAMERA).process(image)


def test_pixels_without_a_bearing_never_become_tracks() -> None:
    """A strongly distorted lens whose corners the camera model cannot undistort (about 4% of the
    image here): those corners' tracks are dropped, counted, and the rest carry on."""
    cam = CameraModel(640, 480, 500, 500, 319.5, 239.5, "pinhole", (0.3, -0.8, 0.0, 0.0))
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.integers(0, 255, (480, 640), dtype=np.uint8), (5, 5), 1.5)
    fe = Frontend(cam, FrontendOptions(max_features=600))
    tracks = [fe.process(image) for _ in range(3)]
    assert fe.dropped_unmappable > 0
    for t in tracks:
        assert len(t.ids) > 100 and np.all(np.isfinite(t.f_cam)) and len(t.ids) == len(t.uv_px) == len(t.f_cam)
        assert 0 <= t.tracked <= len(t.ids)


def test_pixel_settings_scale_with_the_image_and_the_count_does_not() -> None:
    small = CameraSpec(width_px=320, height_px=240, fx_px=230.0, fy_px=230.0, cx_px=159.5, cy_px=119.5)
    f320, f640 = Frontend(small.camera_model()), Frontend(CAMERA.camera_model())
    assert (f640.min_distance_px, f640._win, f640.klt_levels, f640.border_px) == (12.0, (15, 15), 3, 8)
    assert (f320.min_distance_px, f320._win, f320.klt_levels, f320.border_px) == (6.0, (11, 11), 2, 4)
    assert f320.options.max_features == f640.options.max_features


def test_a_faint_floor_is_tracked_and_noise_alone_gives_no_corners() -> None:
    """A floor of soft, low-contrast blobs (6 grey levels, 1 sigma, under noise of 1.5): FAST finds a
    handful even at half its threshold; the tracks still fill up and follow a known shift of the floor.
    Sensor noise alone (a blank or a dark frame) gives almost no corners: corners in noise would be
    tracks that stand still whatever the camera does."""
    rng = np.random.default_rng(4)
    blobs = cv2.GaussianBlur(rng.normal(0, 1, (500, 680)).astype(np.float32), (0, 0), 4)
    blobs *= 6.0 / blobs.std()

    def floor(dx: int) -> np.ndarray:
        window = blobs[10:490, 20 - dx : 660 - dx]
        return np.clip(128 + window + rng.normal(0, 1.5, window.shape), 0, 255).astype(np.uint8)

    assert len(cv2.FastFeatureDetector_create(10, True).detect(floor(0))) < 50
    f = Frontend(CAMERA.camera_model())
    first = f.process(floor(0))
    moved = f.process(floor(3))  # the floor moves 3 px right
    assert len(first.ids) >= 200 and moved.tracked >= 150, (len(first.ids), moved.tracked)
    shift = moved.uv_px[: moved.tracked] - first.uv_px[np.searchsorted(first.ids, moved.ids[: moved.tracked])]
    assert np.median(np.abs(shift[:, 0] - 3.0)) < 0.1 and np.median(np.abs(shift[:, 1])) < 0.1
    for sigma in (2.0, 6.0):
        blank = np.clip(rng.normal(128, sigma, (480, 640)), 0, 255).astype(np.uint8)
        dark = np.clip(rng.normal(8, sigma, (480, 640)), 0, 255).astype(np.uint8)
        for image in (blank, dark):
            g = Frontend(CAMERA.camera_model())
            assert len(g.process(image).ids) <= 5, sigma


def test_a_retired_key_is_refused_with_what_replaced_it(tmp_path) -> None:
    from mavvo.errors import ConfigError
    from mavvo.service.settings import load_config

    cfg = tmp_path / "old.yaml"
    cfg.write_text("odometry:\n  frontend:\n    fast_threshold_adapts: true\n")
    with pytest.raises(
        ConfigError, match=r"old.yaml: odometry.frontend.fast_threshold_adapts: no longer a key: .*remove"
    ):
        load_config(cfg)


def test_an_exposure_step_under_vignetting_does_not_drag_the_tracks() -> None:
    """A faint floor (6 grey levels, 1 sigma) behind a lens 30% darker in the corners moves 4 px
    while the exposure steps up 3%: KLT on the raw images reads the brighter frame's vignetting ramp as
    motion (median error 0.36 px); on the image less its local mean (``klt_highpass_px``, used where
    the texture is faint, as here) the tracks follow the floor (0.04 px)."""
    v, u = np.mgrid[0:480, 0:640].astype(np.float32)
    r2 = (u - 319.5) ** 2 + (v - 239.5) ** 2
    vignette = 1.0 - 0.3 * r2 / r2.max()
    rng = np.random.default_rng(7)
    blobs = cv2.GaussianBlur(rng.normal(0, 1, (500, 700)).astype(np.float32), (0, 0), 2)
    blobs *= 6.0 / blobs.std()

    def floor(dx: int, gain: float) -> np.ndarray:
        window = blobs[10:490, 30 - dx : 670 - dx]
        return np.clip(gain * (128 + window) * vignette + rng.normal(0, 1.0, window.shape), 0, 255).astype(np.uint8)

    images = floor(0, 1.0), floor(4, 1.03)
    errors = {}
    for filtered in (False, True):  # never, and where the texture is faint (the default)
        # The consensus check off: it would drop the raw images' dragged tracks, whose drag is measured here.
        opt = FrontendOptions(consensus_max_px=0.0)
        f = Frontend(CAMERA, opt if filtered else dataclasses.replace(opt, klt_highpass_below=0.0))
        first, moved = f.process(images[0]), f.process(images[1])
        assert moved.tracked >= 80
        shift = moved.uv_px[: moved.tracked] - first.uv_px[np.searchsorted(first.ids, moved.ids[: moved.tracked])]
        errors[filtered] = float(np.median(np.abs(shift - [4.0, 0.0])))
    assert errors[False] > 0.15 and errors[True] < 0.08, errors


def test_tracks_over_a_faint_carpet_3_m_below_survive_its_noise() -> None:
    """`indoor_carpet`'s floor 3 m below (a few grey levels of texture, noise 2 sigma) moving 5 mm a
    frame: KLT's round trips there scatter past the 0.5 px that strong texture allows, and with them
    a third of the tracks died within four frames (the keyframe rule then made a keyframe every few
    frames, each placed with the filter's lag). On faint texture the round trip may be
    ``fb_max_faint_px`` and KLT sees the high-pass doubled rather than halved (less of it rounding)."""
    scenario = load_scenario("indoor_carpet")
    camera = scenario.camera.camera_model()
    render = Renderer(World.build(scenario.world), camera)
    rng = np.random.default_rng(3)
    R = R_from_euler321(0.01, -0.01, 0.0) @ scenario.camera.R_body_cam()

    def alive(options: FrontendOptions) -> float:
        f = Frontend(camera, options)
        tracks = [
            f.process(apply_effects(render.render(R, np.array([0.005 * k, 0.0, -3.0])), noise_sigma=2.0, rng=rng))
            for k in range(5)
        ]
        return float(np.isin(tracks[0].ids, tracks[-1].ids).mean())

    assert alive(FrontendOptions()) >= 0.8
    assert alive(FrontendOptions(fb_max_faint_px=0.5)) < 0.75  # the strong texture's round trip


def test_tracks_that_slipped_a_period_are_off_the_pairs_consensus() -> None:
    """200 tracks moved by one affine map (a zoom and 7 px across, KLT's 0.3 px of scatter), a quarter of
    them a further period (6 px: a 3 cm pattern 1.2 m below a 320 px camera) either way along u or v:
    the fit stays on the majority and exactly the slipped ones are more than 4 px off it."""
    from mavvo.geometry.affine_consensus import off_affine_consensus

    rng = np.random.default_rng(3)
    uv0 = rng.uniform([10, 10], [310, 230], (200, 2))
    uv1 = uv0 @ np.array([[1.02, 0.01], [-0.01, 1.02]]).T + [7.0, -2.0] + rng.normal(0, 0.3, (200, 2))
    slipped = np.arange(200) % 4 == 0
    uv1[slipped] += rng.choice([-6.0, 6.0], (50, 1)) * np.eye(2)[rng.integers(0, 2, 50)]
    off = off_affine_consensus(uv0, uv1, np.ones(200, bool), 4.0)
    assert np.array_equal(off, slipped)


def test_the_consensus_fit_is_the_least_squares_affine_map_of_the_tracks_it_keeps() -> None:
    """Without slipped tracks every refit keeps them all, so the fit is numpy's least squares over the
    kept tracks: the tracks more than 0.5 px off it (some of 0.8 px of scatter) are the same; tracks not
    kept do not pull the fit (one 30 px off is marked); tracks all on a line
    give no affine map, and nothing is marked."""
    from mavvo.geometry.affine_consensus import off_affine_consensus

    rng = np.random.default_rng(5)
    uv0 = rng.uniform([0, 0], [640, 480], (120, 2))
    # Scatter within 0.8 px a coordinate: every kept track inside the refits' 2 px band.
    uv1 = uv0 @ np.array([[0.98, 0.03], [-0.02, 1.01]]).T + [-4.0, 9.0] + rng.uniform(-0.8, 0.8, (120, 2))
    keep = np.arange(120) % 10 != 0
    uv1[0] += 30.0  # not kept
    x = np.column_stack([uv0, np.ones(120)])
    a = np.linalg.lstsq(x[keep], uv1[keep], rcond=None)[0]
    want = np.hypot(*(x @ a - uv1).T) > 0.5
    off = off_affine_consensus(uv0, uv1, keep, 0.5)
    assert 10 < np.count_nonzero(want[keep]) < 100 and want[0]
    assert np.array_equal(off, want)
    line = np.column_stack([np.linspace(0, 600, 50), np.full(50, 100.0)])
    assert not off_affine_consensus(line, line + 3.0, np.ones(50, bool), 0.5).any()
