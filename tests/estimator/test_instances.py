"""Several parts in one frame: every plate found with its own pose, cut-off and overlapping
plates flagged, one plate exactly as the single-target search sees it."""

from __future__ import annotations

import numpy as np
import pytest

from estimator import CameraModel, Estimator, Target
from estimator.instances import Instance, InstanceFinder
from estimator.transforms import pose_distance
from fakes.render import random_target
from tests.support.parts_scene import Plate, plate_at, render_plates

CAM = CameraModel(800.0, 800.0, 639.5, 399.5, (), 1280, 800)
CAM_DIST = CameraModel(800.0, 800.0, 639.5, 399.5, (-0.12, 0.05, 0.0, 0.0, 0.0), 1280, 800)
_LAYOUTS = np.random.default_rng(3)
SIX = random_target(_LAYOUTS, 6)
EIGHT = random_target(_LAYOUTS, 8)
CELLS_PX = [(160 + 320 * (i % 4), 133 + 266 * (i // 4)) for i in range(12)]


def _plates(rng: np.random.Generator, n: int, mixed: bool, camera: CameraModel = CAM
            ) -> list[Plate]:
    cells = rng.permutation(len(CELLS_PX))[:n]
    out = []
    for i, c in enumerate(cells.tolist()):
        name, target = ("eight", EIGHT) if mixed and i % 2 else ("six", SIX)
        T = plate_at(camera, target, CELLS_PX[c], rng.uniform(850.0, 950.0),
                     rng.uniform(-180.0, 180.0), rng.uniform(0.0, 20.0), rng.uniform(0, 360))
        out.append(Plate(name, target, T))
    return out


def _truth_of(inst: Instance, plates: list[Plate]) -> tuple[Plate, float, float]:
    """The plate nearest the instance's pose, and the distance (mm, deg) to it."""
    scored = [(p, *pose_distance(inst.pose.T_camera_target, p.T_camera_target))
              for p in plates]
    return min(scored, key=lambda s: s[1])


@pytest.mark.parametrize(("n", "mixed", "camera"), [
    (2, False, CAM), (3, True, CAM), (5, False, CAM_DIST), (7, True, CAM), (10, False, CAM),
    (10, True, CAM_DIST),
])
def test_every_plate_is_found_at_its_true_pose(n: int, mixed: bool, camera: CameraModel
                                               ) -> None:
    rng = np.random.default_rng(100 + n + 20 * mixed)
    plates = _plates(rng, n, mixed, camera)
    image = render_plates(camera, plates, rng)
    layouts = {"six": SIX, "eight": EIGHT} if mixed else {"six": SIX}
    found = InstanceFinder(camera, layouts).find(image)
    assert len(found.instances) == n and not found.unresolved
    matched = set()
    for inst in found.instances:
        plate, dt, dr = _truth_of(inst, plates)
        matched.add(id(plate))
        assert inst.layout == plate.layout
        assert dt < 1.5 and dr < 1.0, (dt, dr)  # 8 mm dots at ~900 mm, up to 20 deg tilt
        assert not inst.flags and not inst.pose.ambiguous, inst.reasons
        assert len(inst.pose.matched_ids) == plate.target.n_points
    assert len(matched) == n  # each plate once


def test_two_identical_plates_are_two_parts_not_one_ambiguous_pose() -> None:
    rng = np.random.default_rng(7)
    plates = [Plate("six", SIX, plate_at(CAM, SIX, (400, 400), 800.0, 30.0)),
              Plate("six", SIX, plate_at(CAM, SIX, (880, 400), 800.0, -60.0))]
    image = render_plates(CAM, plates, rng)
    assert Estimator(CAM, SIX).estimate(image).ambiguous  # one target's search cannot tell
    found = InstanceFinder(CAM, {"six": SIX}).find(image)
    assert sorted(_truth_of(i, plates)[1] < 1.0 for i in found.instances) == [True, True]
    assert {id(_truth_of(i, plates)[0]) for i in found.instances} == {id(p) for p in plates}
    assert not any(i.pose.ambiguous for i in found.instances)


def test_one_plate_gives_the_single_target_pose() -> None:
    rng = np.random.default_rng(11)
    for _ in range(3):
        T = plate_at(CAM, EIGHT, tuple(rng.uniform((300, 250), (980, 550))),
                     rng.uniform(500.0, 800.0), rng.uniform(-180, 180), rng.uniform(0, 30),
                     rng.uniform(0, 360))
        image = render_plates(CAM, [Plate("eight", EIGHT, T)], rng)
        single = Estimator(CAM, EIGHT).estimate(image)
        found = InstanceFinder(CAM, {"eight": EIGHT}).find(image)
        assert len(found.instances) == 1
        dt, dr = pose_distance(found.instances[0].pose.T_camera_target, single.T_camera_target)
        assert dt < 1e-6 and dr < 1e-6


def test_touching_plates_are_split_and_each_found() -> None:
    """Plates edge to edge: their dots form one group, which is split by position."""
    rng = np.random.default_rng(5)
    big = Target(SIX.points_mm, 8.0)
    T1 = plate_at(CAM, big, (470, 400), 900.0, 0.0)
    T2 = T1.copy()
    T2[:3, 3] += T1[:3, 0] * (np.ptp(SIX.points_mm[:, 0]) + 4.0 * 8.0)
    plates = [Plate("six", big, T1), Plate("six", big, T2)]
    found = InstanceFinder(CAM, {"six": big}).find(render_plates(CAM, plates, rng))
    assert len(found.instances) == 2
    assert all(_truth_of(i, plates)[1] < 1.5 for i in found.instances)


def test_a_plate_cut_by_the_image_border_is_flagged() -> None:
    rng = np.random.default_rng(13)
    whole = Plate("eight", EIGHT, plate_at(CAM, EIGHT, (500, 400), 900.0, 10.0))
    mostly_out = Plate("eight", EIGHT, plate_at(CAM, EIGHT, (1275, 400), 900.0, 10.0))
    found = InstanceFinder(CAM, {"eight": EIGHT}).find(
        render_plates(CAM, [whole, mostly_out], rng))
    good = [i for i in found.instances if not i.flags]
    assert len(good) == 1 and _truth_of(good[0], [whole])[1] < 1.5
    cut = [i for i in found.instances if i.flags] + list(found.unresolved)
    assert cut and all("border" in c.flags for c in cut)


def test_a_plate_missing_one_dot_past_the_border_is_solved_and_flagged() -> None:
    """One dot over the edge: the pose is solved from the rest, and marked as cut."""
    rng = np.random.default_rng(17)
    centred = EIGHT.points_mm - EIGHT.points_mm.mean(axis=0)
    scale = CAM.fx / 500.0

    def left_px(spin_deg: float) -> np.ndarray:
        c, s = np.cos(np.radians(spin_deg)), np.sin(np.radians(spin_deg))
        return np.sort(scale * (c * centred[:, 0] - s * centred[:, 1]))

    # the spin whose leftmost dot stands clearest of the next one
    spin = max(range(0, 360, 5), key=lambda a: left_px(a)[1] - left_px(a)[0])
    dx_px = left_px(spin)
    assert dx_px[1] - dx_px[0] > 35.0
    T = plate_at(CAM, EIGHT, (-0.5 * (dx_px[0] + dx_px[1]), 400.0), 500.0, float(spin))
    found = InstanceFinder(CAM, {"eight": EIGHT}).find(
        render_plates(CAM, [Plate("eight", EIGHT, T)], rng))
    assert len(found.instances) == 1
    inst = found.instances[0]
    assert len(inst.pose.matched_ids) == EIGHT.n_points - 1
    assert inst.flags == ("border",), inst.reasons
    assert pose_distance(inst.pose.T_camera_target, T)[0] < 3.0


def test_overlapping_plates_are_flagged_not_reported_whole() -> None:
    """A plate lying partly over another hides some of its dots."""
    rng = np.random.default_rng(19)
    under = plate_at(CAM, EIGHT, (600, 400), 900.0, 0.0)
    over = plate_at(CAM, EIGHT, (680, 440), 850.0, 40.0)
    image = render_plates(CAM, [Plate("eight", EIGHT, under)], rng, noise_std=0.0)
    top = render_plates(CAM, [Plate("eight", EIGHT, over)], rng, noise_std=0.0)
    covered = _plate_mask(top)
    image[covered] = top[covered]  # the upper plate hides what lies under it
    found = InstanceFinder(CAM, {"eight": EIGHT}).find(image)
    whole = [i for i in found.instances if not i.flags]
    for i in whole:  # only the upper plate may come out whole, and then at its pose
        assert pose_distance(i.pose.T_camera_target, over)[0] < 1.5
    flagged = [i for i in found.instances if i.flags] + list(found.unresolved)
    assert len(whole) <= 1 and flagged
    for f in flagged:
        assert f.flags, f


def _plate_mask(image: np.ndarray) -> np.ndarray:
    """Where a plate was drawn on the flat background (plate and dots differ from it)."""
    import cv2
    diff = (np.abs(image.astype(np.float64) - 110.0) > 3).astype(np.uint8)
    filled = cv2.morphologyEx(diff, cv2.MORPH_CLOSE, np.ones((25, 25), np.uint8))
    return filled.astype(bool)
