"""Synthetic camera images of the dot target, exact enough to test sub-pixel detection.

Dots are rasterised by sending every supersample of a pixel back through the lens (undistort)
to a ray and intersecting it with the dot's plane, so each dot has the true perspective shape of
a circle, including the offset between the imaged centroid and the image of the circle centre
that the perspective-bias correction has to remove. Drawing circles at projected centres would
hide exactly the errors the estimator must handle. The plate and the optional frame are flat
polygons, drawn anti-aliased by OpenCV from densely sampled (and distorted) edges: their exact
shape matters less than speed, since the simulated camera renders several frames per second.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from estimator.camera import CameraModel
from estimator.target import Target
from estimator.transforms import make_T

_AA_SHIFT = 4  # fixed-point bits for cv2.fillPoly sub-pixel vertices
_EDGE_SAMPLES = 48  # points per straight edge, so distortion bends edges smoothly


def _plane_hits(
    x: NDArray[np.float64], y: NDArray[np.float64], R: NDArray[np.float64],
    origin_cam: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """Intersect rays (x, y, 1) with the plane through ``origin_cam`` spanned by R's x and y.

    Returns the in-plane coordinates (a, b) in mm, measured along R's x and y axes from the
    origin, and a mask of rays that hit the plane in front of the camera. ``x`` and ``y``
    broadcast against each other; written per component, without (N, 3) temporaries.
    """
    n = R[:, 2]
    denom = x * n[0] + y * n[1] + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (origin_cam @ n) / denom
    # P = t (x, y, 1) - origin; a = P . R[:, 0], b = P . R[:, 1]
    a = t * (x * R[0, 0] + y * R[1, 0] + R[2, 0]) - origin_cam @ R[:, 0]
    b = t * (x * R[0, 1] + y * R[1, 1] + R[2, 1]) - origin_cam @ R[:, 1]
    return a, b, np.isfinite(t) & (t > 0)


def _fill_polygons(
    shape: tuple[int, int], polys_px: list[NDArray[np.float64]]
) -> NDArray[np.float32]:
    """Anti-aliased coverage (0..1) of filled polygons given in pixel coordinates."""
    canvas = np.zeros(shape, np.uint8)
    pts = [np.round(p * (1 << _AA_SHIFT)).astype(np.int32).reshape(-1, 1, 2) for p in polys_px]
    cv2.fillPoly(canvas, pts, 255, cv2.LINE_AA, _AA_SHIFT)
    return canvas.astype(np.float32) * np.float32(1.0 / 255.0)


def _rect_outline(x0: float, y0: float, x1: float, y1: float) -> NDArray[np.float64]:
    """Densely sampled closed rectangle in plane coordinates (mm), counter-clockwise."""
    s = np.linspace(0.0, 1.0, _EDGE_SAMPLES, endpoint=False)
    edges = [
        np.column_stack((x0 + (x1 - x0) * s, np.full_like(s, y0))),
        np.column_stack((np.full_like(s, x1), y0 + (y1 - y0) * s)),
        np.column_stack((x1 - (x1 - x0) * s, np.full_like(s, y1))),
        np.column_stack((np.full_like(s, x0), y1 - (y1 - y0) * s)),
    ]
    return np.vstack(edges)


@dataclass(frozen=True)
class _Disc:
    """A circle on a plane parallel to the target plane: centre (target frame, mm), radius."""

    centre_mm: NDArray[np.float64]
    radius_mm: float


class _Scene:
    """Geometry shared by the drawing steps of one render call."""

    def __init__(self, camera: CameraModel, T_camera_target: NDArray[np.float64], distort: bool):
        self.camera = camera if distort else CameraModel(
            camera.fx, camera.fy, camera.cx, camera.cy, (), camera.width, camera.height
        )
        self.R = np.asarray(T_camera_target, dtype=float)[:3, :3]
        self.T = np.asarray(T_camera_target, dtype=float)

    def to_camera(self, pts_target_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        pts = np.asarray(pts_target_mm, dtype=float).reshape(-1, 3)
        return np.asarray(pts @ self.R.T + self.T[:3, 3], dtype=float)

    def project_plane(self, ab_mm: NDArray[np.float64], z_mm: float) -> NDArray[np.float64] | None:
        """Pixels of plane points, or None when part of the outline is behind the camera
        (such a shape is not drawn: a real camera would not see it whole either)."""
        pts = np.column_stack((ab_mm, np.full(len(ab_mm), z_mm)))
        cam = self.to_camera(pts)
        if np.any(cam[:, 2] <= 1e-6):
            return None
        return self.camera.project(cam)

    def disc_coverage(
        self, disc: _Disc, supersample: int
    ) -> tuple[int, int, NDArray[np.float32]] | None:
        """Exact-perspective coverage of one disc in its pixel bounding box: (x0, y0, patch)."""
        ang = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
        rim = np.column_stack((np.cos(ang), np.sin(ang))) * disc.radius_mm + disc.centre_mm[:2]
        rim_px = self.project_plane(rim, float(disc.centre_mm[2]))
        if rim_px is None:
            return None
        x0 = max(int(np.floor(rim_px[:, 0].min())) - 2, 0)
        y0 = max(int(np.floor(rim_px[:, 1].min())) - 2, 0)
        x1 = min(int(np.ceil(rim_px[:, 0].max())) + 3, self.camera.width)
        y1 = min(int(np.ceil(rim_px[:, 1].max())) + 3, self.camera.height)
        if x1 <= x0 or y1 <= y0:
            return None
        # Supersample positions: pixel centres are integers, samples spread over [-0.5, 0.5).
        off = (np.arange(supersample) + 0.5) / supersample - 0.5
        xs = (np.arange(x0, x1)[:, None] + off[None, :]).ravel()
        ys = (np.arange(y0, y1)[:, None] + off[None, :]).ravel()
        cam = self.camera
        if cam.has_distortion:
            gx, gy = np.meshgrid(xs, ys)
            norm = cam.undistort_points(np.column_stack((gx.ravel(), gy.ravel())))
            nx, ny = norm[:, 0].reshape(gx.shape), norm[:, 1].reshape(gx.shape)
        else:  # a pinhole's ray depends on the column and the row alone
            nx, ny = ((xs - cam.cx) / cam.fx)[None, :], ((ys - cam.cy) / cam.fy)[:, None]
        origin = self.to_camera(disc.centre_mm)[0]
        a, b, ok = _plane_hits(nx, ny, self.R, origin)
        r_mm = np.where(ok, np.hypot(a, b), np.inf)
        inside = _sample_coverage(np.broadcast_to(r_mm, (len(ys), len(xs))), disc.radius_mm)
        h, w = y1 - y0, x1 - x0
        cov = inside.reshape(h, supersample, w, supersample).mean(axis=(1, 3))
        return x0, y0, cov.astype(np.float32)


def _sample_coverage(r_mm: NDArray[np.float64], radius_mm: float) -> NDArray[np.float64]:
    """Each sample's share of the disc, from its distance to the disc's rim: 1 inside, 0
    outside, and between them a ramp one sample spacing wide across the rim, the rim's
    distance in spacings from the local gradient of ``r_mm`` (the sample's distance from the
    disc's centre on its plane, over the grid of samples).

    A sample that is simply in or out quantises a dot's imaged centre by the samples its rim
    crosses: a pattern that depends on the pose alone (up to ~0.01 px at 4 x 4 samples), which
    no averaging of frames removes and which a sensor integrating light continuously does not
    have. The ramp makes the coverage, and so the centre, continuous in the pose."""
    with np.errstate(invalid="ignore"):  # rays that miss the plane: r is inf, and so a gradient
        gy, gx = np.gradient(r_mm)
        spacing_mm = np.maximum(np.hypot(gx, gy), 1e-12)  # r's change per sample spacing
        share = np.clip(0.5 - (r_mm - radius_mm) / spacing_mm, 0.0, 1.0)
    return np.asarray(np.where(np.isfinite(share), share, r_mm < radius_mm), dtype=float)


def default_levels(polarity: str) -> tuple[float, float]:
    """(plate, dot) grey levels for a polarity: strong but not saturated contrast."""
    return (205.0, 40.0) if polarity == "dark" else (50.0, 215.0)


def _clutter_discs(
    rng: np.random.Generator, target: Target, z_mm: float, count: int
) -> list[_Disc]:
    """Dot-like distractors among the real dots (inside any frame), apart from each other."""
    r = target.dot_diameter_mm / 2.0
    taken = [p[:2] for p in target.points_mm]
    out: list[_Disc] = []
    lo = target.points_mm[:, :2].min(axis=0) - 0.4 * r
    hi = target.points_mm[:, :2].max(axis=0) + 0.4 * r
    for _ in range(400 * max(count, 1)):
        if len(out) == count:
            break
        rad = r * rng.uniform(0.7, 1.2)
        c = rng.uniform(lo, hi)
        if all(np.hypot(*(c - t)) > 3.2 * r for t in taken):
            taken.append(c)
            out.append(_Disc(np.array([c[0], c[1], z_mm]), rad))
    return out


class _Steps:
    """Wall time per drawing step, summed into ``out`` (the render benchmark's breakdown);
    nothing is timed when ``out`` is None."""

    def __init__(self, out: dict[str, float] | None) -> None:
        self.out = out
        self.t = time.perf_counter() if out is not None else 0.0

    def mark(self, name: str) -> None:
        if self.out is None:
            return
        now = time.perf_counter()
        self.out[name] = self.out.get(name, 0.0) + now - self.t
        self.t = now


_BLOCK_BYTES = 1 << 20  # the float32 rows of one pass of the whole-frame loop: in a core's L2


@dataclass(frozen=True)
class _PartLayout:
    """What one part draws, in pixels: its plate's outline, its frame's sides, and each disc's
    coverage patch (x0, y0, patch), far discs first so that a near one covers a far one."""

    plate_px: NDArray[np.float64] | None
    frame_px: list[NDArray[np.float64]]
    discs: list[tuple[int, int, NDArray[np.float32]]]
    plate_level: float
    dot_level: float


@dataclass(frozen=True)
class _Layout:
    """What one frame draws: its parts, far ones first, so that a nearer part (its plate and
    its dots) covers what lies behind it where they overlap in the image."""

    parts: list[_PartLayout]

    def bbox(self, width: int, height: int) -> tuple[int, int, int, int] | None:
        """Pixel box (x0, y0, x1, y1) holding everything drawn, None when nothing is."""
        boxes = []
        for part in self.parts:
            boxes += [(x0, y0, x0 + p.shape[1], y0 + p.shape[0]) for x0, y0, p in part.discs]
            polys = ([part.plate_px] if part.plate_px is not None else []) + part.frame_px
            for poly in polys:
                boxes.append((int(np.floor(poly[:, 0].min())) - 2,
                              int(np.floor(poly[:, 1].min())) - 2,
                              int(np.ceil(poly[:, 0].max())) + 3,
                              int(np.ceil(poly[:, 1].max())) + 3))
        if not boxes:
            return None
        b = np.array(boxes)
        x0, y0 = max(int(b[:, 0].min()), 0), max(int(b[:, 1].min()), 0)
        x1, y1 = min(int(b[:, 2].max()), width), min(int(b[:, 3].max()), height)
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None


def _layout(
    camera: CameraModel, scene: Sequence[tuple[Target, NDArray[np.float64]]],
    plate_size_mm: tuple[float, float] | None, plate_margin_mm: float | None, distort: bool,
    clutter: int, rng: np.random.Generator, frame: bool, supersample: int,
) -> _Layout:
    """The scene's geometry (see :func:`render_scene`), the parts ordered far to near by the
    depth of their dots' centre: the only random draw is the clutter."""
    parts = [_part_layout(camera, target, T, plate_size_mm, plate_margin_mm, distort, clutter,
                          rng, frame, supersample) for target, T in scene]
    depth = [float((np.asarray(T, dtype=float) @ np.r_[t.points_mm.mean(axis=0), 1.0])[2])
             for t, T in scene]
    return _Layout([parts[i] for i in np.argsort(depth, kind="stable")[::-1]])


def _part_layout(
    camera: CameraModel, target: Target, T_camera_target: NDArray[np.float64],
    plate_size_mm: tuple[float, float] | None, plate_margin_mm: float | None, distort: bool,
    clutter: int, rng: np.random.Generator, frame: bool, supersample: int,
) -> _PartLayout:
    """One part's geometry; its only random draw is the clutter."""
    scene = _Scene(camera, np.asarray(T_camera_target, dtype=float), distort)
    plate_level, dot_level = default_levels(target.polarity)
    d = target.dot_diameter_mm
    pts = target.points_mm
    z_plate = float(pts[:, 2].max())
    z_extent = float(np.ptp(pts[:, 2]))  # so dots on posts still appear over the plate
    margin = (
        plate_margin_mm if plate_margin_mm is not None
        else (2.6 if frame else 2.0) * d + 1.5 * z_extent
    )
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    if plate_size_mm is not None:
        c = (lo + hi) / 2.0
        half = np.asarray(plate_size_mm, dtype=float) / 2.0
        plate = (c[0] - half[0], c[1] - half[1], c[0] + half[0], c[1] + half[1])
    else:
        plate = (lo[0] - margin, lo[1] - margin, hi[0] + margin, hi[1] + margin)
    plate_px = scene.project_plane(_rect_outline(*plate), z_plate)

    frame_px: list[NDArray[np.float64]] = []
    if frame:
        inner_gap, width_mm = 0.9 * d, 0.45 * d
        fx0, fy0 = lo[0] - inner_gap - width_mm, lo[1] - inner_gap - width_mm
        fx1, fy1 = hi[0] + inner_gap + width_mm, hi[1] + inner_gap + width_mm
        sides = [
            (fx0, fy0, fx1, fy0 + width_mm), (fx0, fy1 - width_mm, fx1, fy1),
            (fx0, fy0, fx0 + width_mm, fy1), (fx1 - width_mm, fy0, fx1, fy1),
        ]
        projected = [scene.project_plane(_rect_outline(*s), z_plate) for s in sides]
        frame_px = [p for p in projected if p is not None]

    discs = [_Disc(p, d / 2.0) for p in pts]
    discs += _clutter_discs(rng, target, z_plate, clutter)
    depth = [float(scene.to_camera(disc.centre_mm)[0, 2]) for disc in discs]
    patches = []
    for i in np.argsort(depth)[::-1]:
        got = scene.disc_coverage(discs[i], supersample)
        if got is not None:
            patches.append(got)
    return _PartLayout(plate_px, frame_px, patches, plate_level, dot_level)


def _gradient_axes(
    width: int, height: int, lighting_gradient: float, rng: np.random.Generator
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The lighting gain as an outer sum: gain[y, x] = rows[y] + cols[x] (float32), for a
    random direction; 1 everywhere (and no draw) without a gradient."""
    if not lighting_gradient:
        return np.ones(height, np.float32), np.zeros(width, np.float32)
    direction = rng.uniform(0.0, 2.0 * np.pi)
    gx = np.linspace(-1.0, 1.0, width, dtype=np.float32) * np.float32(np.cos(direction))
    gy = np.linspace(-1.0, 1.0, height, dtype=np.float32) * np.float32(np.sin(direction))
    k = np.float32(lighting_gradient) / np.float32(np.sqrt(2.0))  # 1 + g (gy + gx) / sqrt 2
    return np.float32(1.0) + k * gy, k * gx


def _noise_seed(rng: np.random.Generator) -> int:
    return int(rng.integers(0, 2**31 - 1))


def render_target(
    camera: CameraModel,
    target: Target,
    T_camera_target: NDArray[np.float64],
    *,
    plate_size_mm: tuple[float, float] | None = None,
    plate_margin_mm: float | None = None,
    blur_sigma_px: float = 0.7,
    noise_std: float = 1.5,
    lighting_gradient: float = 0.15,
    distort: bool = True,
    clutter: int = 0,
    rng: np.random.Generator | None = None,
    background: float = 110.0,
    frame: bool = False,
    supersample: int = 4,
    timings: dict[str, float] | None = None,
) -> NDArray[np.uint8]:
    """Grey image (height x width, uint8) of the target seen from ``T_camera_target``: the scene
    of one part (:func:`render_scene`)."""
    return render_scene(
        camera, [(target, T_camera_target)], plate_size_mm=plate_size_mm,
        plate_margin_mm=plate_margin_mm, blur_sigma_px=blur_sigma_px, noise_std=noise_std,
        lighting_gradient=lighting_gradient, distort=distort, clutter=clutter, rng=rng,
        background=background, frame=frame, supersample=supersample, timings=timings)


def render_scene(
    camera: CameraModel,
    scene: Sequence[tuple[Target, NDArray[np.float64]]],
    *,
    plate_size_mm: tuple[float, float] | None = None,
    plate_margin_mm: float | None = None,
    blur_sigma_px: float = 0.7,
    noise_std: float = 1.5,
    lighting_gradient: float = 0.15,
    distort: bool = True,
    clutter: int = 0,
    rng: np.random.Generator | None = None,
    background: float = 110.0,
    frame: bool = False,
    supersample: int = 4,
    timings: dict[str, float] | None = None,
) -> NDArray[np.uint8]:
    """Grey image (height x width, uint8) of the parts in ``scene`` (each a target and its
    ``T_camera_target``; none: the background alone), a nearer part's plate and dots over a
    farther one's where they overlap in the image.

    Each part's plate is centred on its dots' bounding box, ``plate_margin_mm`` (default 2 dot
    diameters, 2.6 with ``frame``, plus 1.5x the dots' z range) beyond it, unless
    ``plate_size_mm`` (w, h) is given; it lies in the target plane at the largest dot z, so
    dots with smaller z stand out of it towards the camera. ``lighting_gradient`` scales
    brightness by up to +-that fraction across the frame; ``clutter`` adds that many dot-like
    blobs among the dots; ``frame`` adds a dark rectangular frame around the dots (a classic
    false detection). ``distort`` applies the camera's lens distortion. ``timings``: seconds
    per step are added to it (the render benchmark).

    The image is :func:`render_target_full_frame`'s (same ``rng``: within one grey level, from
    float rounding) at a cost that scales with what is drawn. Away from the drawn box the
    scene is the background times the lighting gain, a linear field that the Gaussian blur
    leaves unchanged; so the drawing, the gain and the blur act on the drawn content minus the
    background in its box plus the blur's reach, and the whole frame gets the noise, the lit
    background and the rounding in one pass of cache-sized row blocks.
    """
    rng = rng if rng is not None else np.random.default_rng()
    steps = _Steps(timings)
    h, w = camera.height, camera.width
    lay = _layout(camera, scene, plate_size_mm, plate_margin_mm, distort, clutter, rng, frame,
                  supersample)
    steps.mark("geometry + discs")
    rows, cols = _gradient_axes(w, h, lighting_gradient, rng)
    box = lay.bbox(w, h)
    drawn = _drawn(lay, box, rows, cols, float(background), blur_sigma_px, w, h, steps)
    # Row blocks, each noised, lit, given its part of the drawn box and rounded while it sits
    # in the cache: the frame goes through memory once, as the uint8 image. cv2.randn over the
    # blocks in turn draws the same numbers as over the whole frame at once.
    seed = _noise_seed(rng) if noise_std > 0 else None
    if seed is not None:
        cv2.setRNGSeed(seed)
    mean, std = np.full(1, 0.5), np.full(1, float(noise_std))  # +0.5: round half up
    lit_rows = np.float32(background) * rows
    lit_cols = (np.float32(background) * cols)[None, :]
    step = max(1, _BLOCK_BYTES // (4 * w))
    block = np.empty((min(step, h), w), np.float32)
    image = np.empty((h, w), np.uint8)
    for y in range(0, h, step):
        n = min(step, h - y)
        v = block[:n]
        if seed is not None:
            cv2.randn(v, mean, std)
        else:
            v.fill(0.5)
        steps.mark("noise")
        np.add(v, lit_rows[y : y + n, None], out=v)
        if lighting_gradient:
            np.add(v, lit_cols, out=v)
        steps.mark("lit background")
        if drawn is not None:
            (x0, y0, x1, y1), delta = drawn
            ya, yb = max(y, y0), min(y + n, y1)
            if ya < yb:
                v[ya - y : yb - y, x0:x1] += delta[ya - y0 : yb - y0]
            steps.mark("add box")
        np.clip(v, 0, 255, out=v)
        image[y : y + n] = v  # truncates: with the +0.5, rounds half up
        steps.mark("clip + uint8")
    return image


def _drawn(
    lay: _Layout, box: tuple[int, int, int, int] | None, rows: NDArray[np.float32],
    cols: NDArray[np.float32], background: float, blur_sigma_px: float, width: int,
    height: int, steps: _Steps,
) -> tuple[tuple[int, int, int, int], NDArray[np.float32]] | None:
    """The drawn content minus the background, lit and blurred, and the region it covers
    (x0, y0, x1, y1); None when nothing is drawn.

    The difference is zero outside ``box``, so ``box`` plus the kernel's reach holds all of its
    blurred image; where that region meets the frame's edge the blur reflects as it does over
    the whole frame."""
    if box is None:
        return None
    reach = math.ceil(4.0 * blur_sigma_px) + 1 if blur_sigma_px > 0 else 0
    x0, y0 = max(box[0] - reach, 0), max(box[1] - reach, 0)
    x1, y1 = min(box[2] + reach, width), min(box[3] + reach, height)
    shape = (y1 - y0, x1 - x0)
    origin = np.array([x0, y0], dtype=float)
    delta = np.zeros(shape, np.float32)
    for part in lay.parts:
        if part.plate_px is not None:
            cov = _fill_polygons(shape, [part.plate_px - origin])
            delta += (part.plate_level - background - delta) * cov
        if part.frame_px:
            cov = np.minimum(sum(_fill_polygons(shape, [p - origin]) for p in part.frame_px),
                             1.0)
            delta += (part.dot_level - background - delta) * cov
        steps.mark("plate + frame (box)")
        for px, py, cov in part.discs:
            patch = delta[py - y0 : py - y0 + cov.shape[0], px - x0 : px - x0 + cov.shape[1]]
            patch += (part.dot_level - background - patch) * cov
        steps.mark("discs (paint)")
    delta *= np.add(rows[y0:y1, None], cols[None, x0:x1])
    steps.mark("gradient (box)")
    if blur_sigma_px > 0:
        delta = np.asarray(cv2.GaussianBlur(delta, (0, 0), blur_sigma_px), dtype=np.float32)
    steps.mark("blur (box)")
    return (x0, y0, x1, y1), delta


def render_target_full_frame(
    camera: CameraModel,
    target: Target,
    T_camera_target: NDArray[np.float64],
    *,
    plate_size_mm: tuple[float, float] | None = None,
    plate_margin_mm: float | None = None,
    blur_sigma_px: float = 0.7,
    noise_std: float = 1.5,
    lighting_gradient: float = 0.15,
    distort: bool = True,
    clutter: int = 0,
    rng: np.random.Generator | None = None,
    background: float = 110.0,
    frame: bool = False,
    supersample: int = 4,
    timings: dict[str, float] | None = None,
) -> NDArray[np.uint8]:
    """:func:`render_target` computed step by step over the whole frame: the definition the
    fast path is checked against (tests) and the benchmark's "before"."""
    rng = rng if rng is not None else np.random.default_rng()
    steps = _Steps(timings)
    h, w = camera.height, camera.width
    lay = _layout(camera, [(target, T_camera_target)], plate_size_mm, plate_margin_mm, distort,
                  clutter, rng, frame, supersample)
    steps.mark("geometry + discs")
    img = np.full((h, w), background, np.float32)
    steps.mark("background fill")
    for part in lay.parts:
        if part.plate_px is not None:
            img += (part.plate_level - img) * _fill_polygons((h, w), [part.plate_px])
        if part.frame_px:
            frame_cov = np.minimum(sum(_fill_polygons((h, w), [p]) for p in part.frame_px),
                                   1.0)
            img += (part.dot_level - img) * frame_cov
        steps.mark("plate + frame (frame)")
        for x0, y0, cov in part.discs:
            patch = img[y0 : y0 + cov.shape[0], x0 : x0 + cov.shape[1]]
            patch += (part.dot_level - patch) * cov
        steps.mark("discs (paint)")
    rows, cols = _gradient_axes(w, h, lighting_gradient, rng)
    if lighting_gradient:
        np.multiply(img, np.add(rows[:, None], cols[None, :]), out=img)
    steps.mark("gradient (frame)")
    if blur_sigma_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), blur_sigma_px), dtype=np.float32)
    steps.mark("blur (frame)")
    if noise_std > 0:
        noise = np.empty((h, w), np.float32)
        cv2.setRNGSeed(_noise_seed(rng))
        cv2.randn(noise, np.zeros(1), np.full(1, float(noise_std)))
        img += noise
    steps.mark("noise")
    np.add(img, np.float32(0.5), out=img)  # round half up
    np.clip(img, 0, 255, out=img)
    image = img.astype(np.uint8)
    steps.mark("clip + uint8")
    return image


def ellipse_centre_px(
    camera: CameraModel, T_camera_target: NDArray[np.float64], centre_mm: NDArray[np.float64],
    radius_mm: float,
) -> NDArray[np.float64]:
    """Centre of the image of a circle (pinhole, no distortion): the centroid a perfect
    detector should return, which differs from the projected circle centre under perspective.

    Computed from the conic of the imaged circle, so tests have an analytic reference.
    """
    T = np.asarray(T_camera_target, dtype=float)
    R = T[:3, :3]
    c = R @ np.asarray(centre_mm, dtype=float) + T[:3, 3]
    # Plane homography: (a, b, 1) on the dot plane -> homogeneous normalised image point.
    H = np.column_stack((R[:, 0], R[:, 1], c))
    C_plane = np.diag([1.0, 1.0, -radius_mm**2])
    Hinv = np.linalg.inv(H)
    C = Hinv.T @ C_plane @ Hinv  # conic of the image ellipse in normalised coordinates
    centre_norm = np.linalg.solve(C[:2, :2], -C[:2, 2])
    return np.array(
        [camera.fx * centre_norm[0] + camera.cx, camera.fy * centre_norm[1] + camera.cy]
    )


def random_pose(
    rng: np.random.Generator, camera: CameraModel, target: Target, *,
    distance_mm: tuple[float, float] = (350.0, 700.0), max_tilt_deg: float = 40.0,
    border_px: float = 40.0, min_tilt_deg: float = 0.0,
) -> NDArray[np.float64]:
    """A random front-facing pose that keeps every dot at least ``border_px`` inside the image,
    tilted by ``min_tilt_deg`` to ``max_tilt_deg`` from facing the camera."""
    centre = target.points_mm.mean(axis=0)
    for _ in range(1000):
        axis = rng.normal(size=3)
        axis[2] = 0.0
        axis /= np.linalg.norm(axis)
        tilt = Rotation.from_rotvec(axis * np.radians(rng.uniform(min_tilt_deg, max_tilt_deg)))
        spin = Rotation.from_rotvec([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
        R = (tilt * spin).as_matrix()
        z = rng.uniform(*distance_mm)
        xy = rng.uniform(-0.25, 0.25, 2) * np.array([camera.width / camera.fx,
                                                     camera.height / camera.fy]) * z
        T = make_T(R, np.array([xy[0], xy[1], z]) - R @ centre)
        cam = target.points_mm @ R.T + T[:3, 3]
        if np.any(cam[:, 2] <= 0):
            continue
        px = camera.project(cam)
        inside = (
            (px[:, 0] >= border_px) & (px[:, 0] <= camera.width - 1 - border_px)
            & (px[:, 1] >= border_px) & (px[:, 1] <= camera.height - 1 - border_px)
        )
        # Dots on posts can hide each other; keep them clearly apart in the image.
        gap = np.linalg.norm(px[:, None] - px[None], axis=2) + np.eye(len(px)) * 1e9
        dot_px = camera.fx * target.dot_diameter_mm / cam[:, 2].min()
        if inside.all() and gap.min() > 2.5 * dot_px:
            return T
    raise RuntimeError("could not find a pose that keeps the target in view")


def grid_target(rows: int, cols: int, pitch_mm: float, dot_diameter_mm: float,
                polarity: str = "dark") -> Target:
    """A regular circle grid (rows x cols dots, ``pitch_mm`` apart) in z = 0."""
    yy, xx = np.mgrid[0:rows, 0:cols]
    pts = np.column_stack((xx.ravel() * pitch_mm, yy.ravel() * pitch_mm, np.zeros(rows * cols)))
    return Target(pts, dot_diameter_mm, "dark" if polarity == "dark" else "light")


def symmetric_target(dot_diameter_mm: float = 10.0, polarity: str = "dark") -> Target:
    """A 2-fold symmetric 5-dot plate: the corners of a 140 x 120 mm rectangle and its centre
    (the layout of the hand-held sequence the estimator once lost track of)."""
    pts = [[0, 0, 0], [140, 0, 0], [140, 120, 0], [0, 120, 0], [70, 60, 0]]
    return Target(pts, dot_diameter_mm, "dark" if polarity == "dark" else "light")


def random_target(rng: np.random.Generator, n_dots: int, *, planar: bool = True,
                  dot_diameter_mm: float = 8.0, polarity: str = "dark") -> Target:
    """An asymmetric random target: dots at least 3 diameters apart in a ~120 x 90 mm area."""
    pts: list[NDArray[np.float64]] = []
    while len(pts) < n_dots:
        p = rng.uniform([0.0, 0.0], [120.0, 90.0])
        if all(np.hypot(*(p - q)) > 3.0 * dot_diameter_mm for q in pts):
            pts.append(p)
    z = rng.uniform(-20.0, 0.0, n_dots) if not planar else np.zeros(n_dots)
    return Target(np.column_stack((np.array(pts), z)), dot_diameter_mm,
                  "dark" if polarity == "dark" else "light")


@dataclass(frozen=True)
class Scene:
    """A rendered test scene with its ground truth."""

    image: NDArray[np.uint8]
    T_camera_target: NDArray[np.float64]
    target: Target
    camera: CameraModel


def random_scene(
    rng: np.random.Generator, camera: CameraModel, target: Target | None = None, *,
    n_dots: int = 6, planar: bool = True, **render_options: object,
) -> Scene:
    """Random target (unless given) at a random in-view pose, rendered with ``render_options``."""
    tgt = target if target is not None else random_target(rng, n_dots, planar=planar)
    T = random_pose(rng, camera, tgt)
    image = render_target(camera, tgt, T, rng=rng, **render_options)  # type: ignore[arg-type]
    return Scene(image, T, tgt, camera)


def motion_smear(image: NDArray[np.uint8], smear_px: tuple[float, float],
                 min_px: float = 0.3) -> NDArray[np.uint8]:
    """The image averaged over a straight motion of ``smear_px`` (dx, dy) during the exposure.

    One convolution with a line kernel, sub-pixel by bilinear splatting of samples along the
    segment: what a rendering averaged over many instants of the exposure gives for a
    translating image, at the cost of a single filter pass. Rotation during the exposure
    (a blur that differs across the image) is not modelled."""
    dx, dy = float(smear_px[0]), float(smear_px[1])
    length = math.hypot(dx, dy)
    if length < min_px:
        return image
    half = math.ceil(max(abs(dx), abs(dy)) / 2.0) + 1
    size = 2 * half + 1
    kernel = np.zeros((size, size), np.float64)
    n = max(4, math.ceil(length * 4))
    for t in np.linspace(-0.5, 0.5, n):
        x, y = half + t * dx, half + t * dy
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    kernel /= kernel.sum()
    out = cv2.filter2D(image, -1, kernel.astype(np.float32), borderType=cv2.BORDER_REPLICATE)
    return np.asarray(out, dtype=np.uint8)
