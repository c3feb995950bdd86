"""Real camera images of dot targets (../shared/data/real-dots, see its SOURCE.md): every dot
found, centres against OpenCV's findCirclesGrid / SimpleBlobDetector, and a pose for every
grid view. Skipped when the shared data is absent."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from estimator import CameraModel, Estimator
from estimator.blobs import detect_blobs
from fakes.render import grid_target
from tests.support.paths import SHARED

DATA = SHARED / "data" / "real-dots"
if not DATA.is_dir():
    DATA = Path("/work/shared/data/real-dots")
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/real-dots is absent")

GRIDS = {"circles": 34.0, "grid36": 30.0}  # pitch (mm; grid36's is not given: rms ignores it)
CENTRE_TOL_PX = 0.25


def _grey(name: str) -> np.ndarray:
    img = cv2.imread(str(DATA / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None, name
    return np.asarray(img)


def _views(prefix: str) -> list[str]:
    return sorted(p.name for p in DATA.glob(f"{prefix}-*"))


def _nearest(ours: np.ndarray, theirs: np.ndarray) -> np.ndarray:
    """For each of their centres, the distance to our nearest one."""
    return np.linalg.norm(theirs[:, None] - ours[None], axis=2).min(axis=1)


def _centres(blobs: list) -> np.ndarray:
    return np.array([[b.u, b.v] for b in blobs])


def _opencv_grid(img: np.ndarray) -> np.ndarray:
    ok, centres = cv2.findCirclesGrid(img, (6, 6), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
    assert ok
    return np.asarray(centres, float).reshape(-1, 2)


@pytest.mark.parametrize("prefix", sorted(GRIDS))
def test_every_grid_dot_is_found_where_opencv_finds_it(prefix: str) -> None:
    views = _views(prefix)
    assert len(views) >= 4
    for name in views:
        img = _grey(name)
        blobs = detect_blobs(img)
        assert len(blobs) == 36, name
        d = _nearest(_centres(blobs), _opencv_grid(img))
        assert d.max() < CENTRE_TOL_PX, (name, d.max())


@pytest.mark.parametrize("prefix", sorted(GRIDS))
def test_every_grid_view_gets_a_pose(prefix: str) -> None:
    """Intrinsics from OpenCV's calibration on the same views (the files carry none), then
    our full search and pose on each view: all 36 dots matched, rms under 0.5 px."""
    views = _views(prefix)
    target = grid_target(6, 6, GRIDS[prefix], 10.0)
    imgs = [_grey(n) for n in views]
    h, w = imgs[0].shape
    obj = np.array(target.points_mm, np.float32)
    _, K, dist, _, _ = cv2.calibrateCamera(
        [obj] * len(imgs), [_opencv_grid(i).astype(np.float32) for i in imgs], (w, h),
        None, None, flags=cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST)
    camera = CameraModel(K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(np.ravel(dist)[:5]), w, h)
    for name, img in zip(views, imgs, strict=True):
        result = Estimator(camera, target, tracking=False).estimate(img)
        assert len(result.matched_ids) == 36, name
        assert result.rms_px < 0.5, (name, result.rms_px)
        # A square grid has four labellings that fit alike: the fresh search says so.
        assert result.ambiguous and len(result.equivalent_poses) == 3


def _sbd(img: np.ndarray, light: bool) -> np.ndarray:
    params = cv2.SimpleBlobDetector_Params()  # type: ignore[attr-defined]
    if light:  # mire.jpg's dots are ~10800 px: above the default maxArea (5000)
        params.blobColor = 255
        params.maxArea = 50000
    kps = cv2.SimpleBlobDetector_create(params).detect(img)  # type: ignore[attr-defined]
    return np.array([k.pt for k in kps], float).reshape(-1, 2)


@pytest.mark.parametrize(("name", "polarity"), [("square.jpg", "dark"), ("mire.jpg", "light")])
def test_four_dot_photos_match_simple_blob_detector(name: str, polarity: str) -> None:
    img = _grey(name)
    blobs = detect_blobs(img, polarity)  # type: ignore[arg-type]
    assert len(blobs) == 4, [(round(b.u), round(b.v)) for b in blobs]
    ours = _centres(blobs)
    theirs = _sbd(img, polarity == "light")
    # SimpleBlobDetector also reports a false blob on square.jpg: compare at our dots.
    d = np.linalg.norm(ours[:, None] - theirs[None], axis=2).min(axis=1)
    assert d.max() < CENTRE_TOL_PX, d


@pytest.mark.parametrize("prefix", sorted(GRIDS))
def test_a_real_grid_tracked_at_its_own_mid_level(prefix: str) -> None:
    """Real photos, their brightness scaled frame to frame: tracks begun 10 grey levels either
    side of the photo's Otsu level cut at the dots' own mid level after two frames, so they
    measure the same centres, and those stay where OpenCV's findCirclesGrid puts the dots."""
    from estimator.blobs import detect_blobs_thresholded
    from estimator.tracking import BlobTracker

    for name in _views(prefix):
        img = _grey(name)
        frames = [np.clip(img.astype(float) * g, 0, 255).astype(np.uint8)
                  for g in (1.0, 0.94, 1.05, 0.97, 1.03)]
        blobs, thr = detect_blobs_thresholded(img)
        assert thr is not None and len(blobs) == 36, name
        starts = _centres(blobs)
        runs = []
        for start in (thr - 10.0, thr + 10.0):
            tracker = BlobTracker("dark")
            tracker.start(blobs, list(range(36)), start)
            run = []
            for frame in frames:
                tracked = tracker.track(frame, starts)
                assert tracked is not None, name
                run.append(_centres(tracked))
            runs.append(np.asarray(run)[2:])
        assert np.abs(runs[0] - runs[1]).max() < 1e-3, name
        d = _nearest(runs[0][-1], _opencv_grid(img))
        assert d.max() < CENTRE_TOL_PX, (name, d.max())
