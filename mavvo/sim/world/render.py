"""Render what a camera sees of the world, with OpenCV.

The ground is drawn layer by layer through plane-induced homographies (``cv2.warpPerspective`` with
wrapped borders, since the textures are periodic), cross-faded by each pixel's ground sample distance;
boxes follow in painter's order. Everything is drawn in an ideal pinhole image; a camera with
distortion gets one precomputed ``cv2.remap`` from that image, so its pixels land exactly where
``CameraModel.bearings_to_pixels`` says.

Poses: ``R_ned_cam`` takes camera vectors (x right, y down, z forward) to NED; ``p_ned_cam_m`` is the
camera centre in NED (the ground is z = 0, so the height above it is ``-p_ned_cam_m[2]``).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from mavvo.geometry.camera_model import CameraModel
from mavvo.geometry.frames import as_rotation
from mavvo.sim.world.scene import World

SKY_LEVEL = 200
_GRID_PX = 16  # pixel spacing at which the layer weights are computed, then interpolated
_MIN_HEIGHT_M = 0.05
_NEAR_M = 0.05
_MAX_VIRTUAL_SCALE = 3  # the virtual pinhole image of a distorted camera is at most this much bigger
_MIN_COS_FOV = 0.2  # distorted pixels more than ~78 deg off axis stay black
_LAYER_CENTRE = 0.5  # a layer weighs most where one image pixel spans this many texels' width
_LOG_RATIO = np.log(8.0)


class Renderer:
    """Renders grey images of one world through one camera.

    Rendering allocates only the output arrays; the distortion maps and ray grids are made once here,
    each layer's 2x2 mosaic on its first use.
    """

    def __init__(self, world: World, camera: CameraModel) -> None:
        self.world = world
        self.camera = camera
        self._distorted = camera.model != "pinhole" or any(camera.distortion)
        if self._distorted:
            self._K, self._size, self._maps = _virtual_pinhole(camera)
        else:
            self._K, self._size, self._maps = camera.K, (camera.width_px, camera.height_px), None
        w, h = self._size
        gu, gv = np.meshgrid(
            np.arange(0, w + _GRID_PX, _GRID_PX, dtype=float), np.arange(0, h + _GRID_PX, _GRID_PX, dtype=float)
        )
        rays = np.stack([gu.ravel(), gv.ravel(), np.ones(gu.size)], axis=1) @ np.linalg.inv(self._K).T
        self._grid_rays_cam = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        self._grid_shape = gu.shape
        self._f_px = float(self._K[0, 0])
        self._mosaics: dict[int, np.ndarray] = {}  # id of a layer's tile (T,T): the tile repeated 2x2 (2T,2T)

    def render(self, R_ned_cam: np.ndarray, p_ned_cam_m: np.ndarray) -> np.ndarray:
        """(H,W) uint8 image of the world from the given camera pose, no noise or blur."""
        R = as_rotation("R_ned_cam", R_ned_cam)
        p = np.asarray(p_ned_cam_m, dtype=float).reshape(3)
        if not np.all(np.isfinite(p)):
            raise ValueError(f"p_ned_cam_m: expected a finite (3,) position, got {p}")
        p = p.copy()
        p[2] = min(p[2], -_MIN_HEIGHT_M)  # never below the ground
        img = self._ground(R, p)
        for quad in self.world.patches_ned:
            self._plain_patch(img, R, p, quad)
        if self.world.boxes:
            self._boxes(img, R, p)
        if self._maps is not None:
            img = cv2.remap(
                img, self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
            )
        return img

    def _ground(self, R: np.ndarray, p: np.ndarray) -> np.ndarray:
        w, h = self._size
        weights, sky = self._layer_weights(R, p)
        images = [
            (self._warp_layer(layer.tile, self._H_img_tile(R, p, layer.tile.shape[0], layer.m_per_px), wgrid), wgrid)
            for layer, wgrid in zip(self.world.layers, weights)
            if wgrid.max() > 0.0
        ]
        if sky.max() > 0.0:
            images.append((np.full((h, w), SKY_LEVEL, np.uint8), sky))
        if len(images) == 1:
            return images[0][0]
        # cross-fade one image at a time: blendLinear is (w1 a + w2 b) / (w1 + w2), in uint8
        img, wsum = images[0][0], _upsample(images[0][1], w, h)
        for other, wgrid in images[1:]:
            wfull = _upsample(wgrid, w, h)
            img = cv2.blendLinear(img, other, wsum, wfull)
            wsum += wfull
        return img

    def _warp_layer(self, tile: np.ndarray, H_img_tile: np.ndarray, wgrid: np.ndarray) -> np.ndarray:
        """The layer's texture in the image, drawn only inside the box where its weight grid is not zero
        (the layers of a forward view are bands of rows); zero elsewhere."""
        w, h = self._size
        rows, cols = np.nonzero(wgrid)
        # the weights are interpolated between grid points (cv2.resize places them a little off k * _GRID_PX):
        # two zero points beyond the last non-zero one, the pixels between still count
        x0, x1 = max((cols.min() - 2) * _GRID_PX, 0), min((cols.max() + 2) * _GRID_PX + 1, w)
        y0, y1 = max((rows.min() - 2) * _GRID_PX, 0), min((rows.max() + 2) * _GRID_PX + 1, h)
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        mosaic = self._mosaics.get(id(tile))
        if mosaic is None:  # made on first use: the coarse layers of a world are often never seen
            mosaic = self._mosaics[id(tile)] = np.tile(tile, (2, 2))
        roi = cv2.warpPerspective(
            mosaic, shift @ H_img_tile, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        )
        if (x0, y0, x1, y1) == (0, 0, w, h):
            return roi
        out = np.zeros((h, w), np.uint8)
        out[y0:y1, x0:x1] = roi
        return out

    def _H_img_tile(self, R: np.ndarray, p: np.ndarray, tile_px: int, m: float) -> np.ndarray:
        """Homography from texels (col, row, 1) of the layer's 2x2 mosaic to image pixels, for the mosaic
        copy that has the camera in its middle half (the origin shift keeps texel coordinates small; the
        texture is periodic). A view that stays within half a tile of the point below the camera then
        samples inside the mosaic, where warpPerspective is several times faster than at wrapped borders."""
        period = tile_px * m
        n0 = (np.floor(p[0] / period - 0.5) + 2.0) * period  # rows run southwards: the camera at row T/2..3T/2
        e0 = np.floor(p[1] / period - 0.5) * period  # ... and at column T/2..3T/2
        # ground point minus camera centre, as a function of (col, row, 1)
        M = np.array([[0.0, -m, n0 - 0.5 * m - p[0]], [m, 0.0, e0 + 0.5 * m - p[1]], [0.0, 0.0, -p[2]]])
        return self._K @ R.T @ M

    def _layer_weights(self, R: np.ndarray, p: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        """Per-layer weight grids and the sky/haze weight grid, each summing to one per grid point."""
        d = self._grid_rays_cam @ R.T
        dz = d[:, 2]
        ground = dz > 1e-3
        height = -p[2]
        dist = np.where(ground, height / np.where(ground, dz, 1.0), np.inf)
        gsd = dist / (self._f_px * np.sqrt(np.where(ground, dz, 1.0)))
        layers = self.world.layers
        weights = []
        if len(layers) == 1:
            weights.append(ground.astype(np.float32))
        else:
            s = np.log(np.maximum(gsd, 1e-12) / (_LAYER_CENTRE * layers[0].m_per_px)) / _LOG_RATIO
            s = np.maximum(s, 0.0)
            for k in range(len(layers)):
                weights.append(np.where(ground, np.maximum(0.0, 1.0 - np.abs(s - k)), 0.0).astype(np.float32))
        sky = 1.0 - np.sum(weights, axis=0)
        shape = self._grid_shape
        return [wk.reshape(shape) for wk in weights], np.maximum(sky, 0.0).reshape(shape).astype(np.float32)

    def _plain_patch(self, img: np.ndarray, R: np.ndarray, p: np.ndarray, quad_ned: np.ndarray) -> None:
        """A plain patch of the ground (4 corners, (4,3)) painted mid-grey, its edges anti-aliased."""
        uv = self._project_quad(quad_ned, R, p)
        if uv is not None:
            cv2.fillConvexPoly(img, np.round(uv * 16).astype(np.int32), 128, lineType=cv2.LINE_AA, shift=4)

    def _project_quad(self, quad_ned: np.ndarray, R: np.ndarray, p: np.ndarray) -> np.ndarray | None:
        """(4,2) pixels of the ideal pinhole image of a quad's corners (4,3), or None when it crosses the
        camera plane (not drawn rather than clipped)."""
        x_cam = (quad_ned - p) @ R
        if np.any(x_cam[:, 2] < _NEAR_M):
            return None
        uv = x_cam @ self._K.T
        return uv[:, :2] / uv[:, 2:]

    def _boxes(self, img: np.ndarray, R: np.ndarray, p: np.ndarray) -> None:
        faces = []
        for box in self.world.boxes:
            centre = box.corners_ned.mean(axis=0)
            for face in box.faces:
                quad = box.corners_ned[list(face)]
                fc = quad.mean(axis=0)
                if (fc - centre) @ (p - fc) <= 0.0:
                    continue  # facing away
                faces.append((float(np.linalg.norm(p - fc)), quad, box.texture, _shade(fc - centre)))
        faces.sort(key=lambda f: -f[0])  # painter's order: far first
        h, w = img.shape
        for _, quad, tex, shade in faces:
            uv = self._project_quad(quad, R, p)
            if uv is None:
                continue
            x0, y0 = np.floor(uv.min(axis=0)).astype(int)
            x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 1
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
            if x1 <= x0 or y1 <= y0:
                continue
            s = tex.shape[0] - 1
            src = np.array([[0, 0], [s, 0], [s, s], [0, s]], np.float32)
            H = cv2.getPerspectiveTransform(src, (uv - [x0, y0]).astype(np.float32))
            patch = cv2.warpPerspective(
                tex, H, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
            mask = np.zeros_like(patch)
            cv2.fillConvexPoly(mask, np.round((uv - [x0, y0]) * 16).astype(np.int32), 255, lineType=cv2.LINE_8, shift=4)
            roi = img[y0:y1, x0:x1]
            np.copyto(roi, (patch * shade).astype(np.uint8), where=mask > 0)


def _shade(normal: np.ndarray) -> float:
    """Brightness of a face by its direction (light from above and the south-west), so edges show."""
    n = normal / np.linalg.norm(normal)
    return float(0.65 + 0.35 * max(0.0, n @ np.array([-0.3, -0.3, -0.9]) / np.linalg.norm([0.3, 0.3, 0.9])))


def _upsample(grid: np.ndarray, w: int, h: int) -> np.ndarray:
    """Grid values interpolated to (h,w) pixels (to within a few pixels; the weights vary slowly)."""
    gh, gw = grid.shape
    sx, sy = (gw - 1) * _GRID_PX, (gh - 1) * _GRID_PX
    full = cv2.resize(grid, (sx + 1, sy + 1), interpolation=cv2.INTER_LINEAR)
    return full[:h, :w]


def _virtual_pinhole(camera: CameraModel) -> tuple[np.ndarray, tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """An ideal pinhole that sees every pixel of ``camera`` (up to ~78 deg off axis), and the remap
    maps from ``camera``'s pixels into it."""
    w, h = camera.width_px, camera.height_px
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    f = camera.pixels_to_bearings(np.stack([u.ravel(), v.ravel()], axis=1))
    ok = np.isfinite(f[:, 2]) & (f[:, 2] > _MIN_COS_FOV)
    xy = np.full((f.shape[0], 2), np.nan)
    xy[ok] = f[ok, :2] / f[ok, 2:]
    fx, fy = camera.fx_px, camera.fy_px
    # at most _MAX_VIRTUAL_SCALE times the image each way; pixels beyond stay black
    half = np.array([_MAX_VIRTUAL_SCALE * w / (2 * fx), _MAX_VIRTUAL_SCALE * h / (2 * fy)])
    ok &= np.all(np.abs(np.nan_to_num(xy, nan=np.inf)) < half, axis=1)
    xy[~ok] = np.nan
    lo = np.nanmin(xy, axis=0)
    hi = np.nanmax(xy, axis=0)
    cx = -lo[0] * fx + 1.0
    cy = -lo[1] * fy + 1.0
    vw = int(np.ceil((hi[0] - lo[0]) * fx) + 3)
    vh = int(np.ceil((hi[1] - lo[1]) * fy) + 3)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    mx = np.where(ok, fx * xy[:, 0] + cx, -1.0).reshape(h, w).astype(np.float32)
    my = np.where(ok, fy * xy[:, 1] + cy, -1.0).reshape(h, w).astype(np.float32)
    return K, (vw, vh), cv2.convertMaps(mx, my, cv2.CV_16SC2)


def apply_effects(
    image: np.ndarray,
    *,
    gain: float | np.ndarray = 1.0,
    blur_px: tuple[float, float] = (0.0, 0.0),
    noise_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Exposure gain (a number, or (H,W) per pixel), linear motion blur along ``blur_px`` (image motion during the exposure, pixels)
    and Gaussian pixel noise (grey levels) applied to a rendered (H,W) uint8 image."""
    out = image.astype(np.float32)
    length = float(np.hypot(*blur_px))
    if length >= 0.5:
        n = int(np.ceil(length)) | 1
        kernel = np.zeros((n, n), np.float32)
        c = n // 2
        d = np.asarray(blur_px) / length * (length / 2)
        cv2.line(
            kernel,
            (int(round(c - d[0])), int(round(c - d[1]))),
            (int(round(c + d[0])), int(round(c + d[1]))),
            1.0,
            1,
            cv2.LINE_AA,
        )
        out = cv2.filter2D(out, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REFLECT)
    if not (np.isscalar(gain) and gain == 1.0):
        out *= gain
    if noise_sigma > 0.0:
        if rng is None:
            raise ValueError("apply_effects: noise_sigma > 0 needs a seeded rng")
        # A window at a random offset into a fixed field of unit Gaussian noise twice the image each way:
        # every pixel's noise is Gaussian and independent of its neighbours', and drawing it costs a slice
        # instead of a fresh draw of H x W normals (a large share of rendering a frame).
        h, w = out.shape[:2]
        bank = _noise_field(h, w)
        dy, dx = (int(v) for v in rng.integers(0, (h, w)))
        out += bank[dy : dy + h, dx : dx + w].reshape(out.shape) * noise_sigma
    return np.clip(out + 0.5, 0, 255).astype(np.uint8)


@lru_cache(maxsize=4)
def _noise_field(h: int, w: int) -> np.ndarray:
    """(2h, 2w) unit Gaussian noise, float32, the same on every run (seeded), read-only."""
    field = np.random.default_rng(20101005).standard_normal((2 * h, 2 * w), dtype=np.float32)
    field.setflags(write=False)
    return field
