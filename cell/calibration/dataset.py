"""Hand-eye datasets on disk: ViSP's eye-in-hand folder as it is, and the project's own format.

ViSP's folder (``apps/calibration/hand-eye``): ``<prefix>_pose_rPe_N.yaml`` robot poses as a 6x1
vector [t (m), theta-u (rad)] base -> end-effector, ``<prefix>_image-N.png``, a camera xml
(vpXmlParserCamera) and ``chessboard-data.txt``.

The project's format is a folder with a ``dataset.json``::

    {"format": "ur-vision-cell/hand-eye-dataset", "version": 1,
     "camera": {"fx", "fy", "cx", "cy", "width", "height", "dist": []},
     "board": {"kind": "chessboard", "cols": 9, "rows": 6, "pitch_mm": 23.6},
     "views": [{"image": "view-01.png",
                "T_base_flange": {"position_mm": [...], "rotvec_rad": [...]},
                "joints_rad": [q1, ..., q6]}, ...],
     "arm": {"model": "ur5e"}}

``joints_rad`` (each view's joint angles) and ``arm`` (whose published DH table they go with)
are optional; the guided routine writes them, so a re-solve fits the arm's geometry as the
routine did.

Instead of ``"board"``, a dataset may name the cell's dot target, as the guided routine on a
cell writes it: ``"target": {"points_mm": [[x, y, z], ...], "dot_diameter_mm": 8.0,
"polarity": "dark"}``. Image paths are relative to the folder. Every failure is a
:class:`DatasetError` whose message names the file and what is wrong with it.
"""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from cell.error_codes import ErrorCode
from cell.errors import CellError
from estimator import CameraModel, Target
from estimator.calib.board import Board
from estimator.kinematics import UR_DH
from estimator.transforms import T_from_pose_dict, T_from_ur_pose, pose_dict

FORMAT_NAME = "ur-vision-cell/hand-eye-dataset"
DATASET_FILE = "dataset.json"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


class DatasetError(CellError):
    """The folder is missing, incomplete or holds a file that cannot be read."""

    kind = "invalid"


@dataclass(frozen=True)
class View:
    """One robot pose and the image taken there."""

    name: str
    image_path: Path
    T_base_flange: NDArray[np.float64]  # 4x4, mm
    joints_rad: NDArray[np.float64] | None = None  # (6,), as the arm reported them

    def load_image(self) -> NDArray[np.uint8]:
        img = cv2.imread(str(self.image_path), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DatasetError(ErrorCode.image_unreadable, f"cannot read image {self.image_path}")
        return np.asarray(img, dtype=np.uint8)


@dataclass(frozen=True)
class HandEyeDataset:
    camera: CameraModel
    board: Board | None  # the calibration pattern: a board, or else ...
    views: tuple[View, ...]
    source: str  # "visp" or "project"
    folder: Path
    target: Target | None = None  # ... the cell's dot target
    arm_model: str | None = None  # the arm whose published DH table the joints go with

    def joints(self) -> list[NDArray[np.float64]] | None:
        """Every view's joints, or None when the dataset cannot fit the arm's geometry."""
        joints = [v.joints_rad for v in self.views]
        if self.arm_model is None or any(q is None for q in joints):
            return None
        return [q for q in joints if q is not None]


def load_dataset(folder: str | Path) -> HandEyeDataset:
    """Read either format, recognised by its files."""
    d = Path(folder)
    if not d.is_dir():
        raise DatasetError(ErrorCode.dataset_not_found, f"{d} is not a folder")
    if (d / DATASET_FILE).is_file():
        return load_project_dataset(d)
    if any(d.glob("*_rPe_*.yaml")):
        return load_visp_dataset(d)
    raise DatasetError(
        ErrorCode.dataset_not_found,
        f"{d} holds neither a {DATASET_FILE} nor ViSP robot poses (*_rPe_N.yaml)",
    )


# --- ViSP ----------------------------------------------------------------------------------

_POSE_RE = re.compile(r"^(?P<prefix>.*)_rPe_(?P<n>\d+)\.yaml$")


def load_visp_dataset(folder: str | Path) -> HandEyeDataset:
    d = Path(folder)
    poses = sorted(
        ((int(m["n"]), p) for p in d.glob("*_rPe_*.yaml") if (m := _POSE_RE.match(p.name))),
        key=lambda item: item[0],
    )
    if not poses:
        raise DatasetError(ErrorCode.dataset_not_found, f"no *_rPe_N.yaml robot poses in {d}")
    images = _numbered_images(d)
    views = []
    for n, pose_path in poses:
        if n not in images:
            raise DatasetError(
                ErrorCode.image_missing,
                f"no image numbered {n} (e.g. *_image-{n}.png) for {pose_path.name}",
            )
        views.append(View(images[n].stem, images[n], read_visp_pose(pose_path)))
    xmls = sorted(d.glob("*.xml"))
    if not xmls:
        raise DatasetError(ErrorCode.camera_missing, f"no camera xml (vpXmlParserCamera) in {d}")
    camera = read_visp_camera(xmls[0])
    board = read_visp_board(d / "chessboard-data.txt")
    return HandEyeDataset(camera, board, tuple(views), "visp", d)


def _numbered_images(d: Path) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for p in sorted(d.iterdir()):
        m = re.search(r"[-_](\d+)$", p.stem)
        if p.suffix.lower() in IMAGE_SUFFIXES and m:
            out.setdefault(int(m.group(1)), p)
    return out


def read_visp_pose(path: Path) -> NDArray[np.float64]:
    """``T_base_flange`` (mm) from ViSP's vpPoseVector YAML: [tx ty tz (m), theta-u (rad)]."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise DatasetError(ErrorCode.pose_unreadable,
                           f"cannot read robot pose {path}: {err}") from err
    # vpPoseVector::saveYAML writes {rows: 6, cols: 1, data: [[tx], [ty], ...]}.
    values: list[float] = []
    try:
        data = yaml.safe_load(text)
        rows = data["data"] if isinstance(data, dict) else None
        if isinstance(rows, list):
            values = [float(r[0] if isinstance(r, list) else r) for r in rows]
    except (yaml.YAMLError, KeyError, IndexError, TypeError, ValueError):
        values = []
    if len(values) != 6 or not np.all(np.isfinite(values)):
        raise DatasetError(
            ErrorCode.pose_unreadable,
            f"{path} is not a ViSP pose (rows: 6, cols: 1, data: 6 numbers [t m, theta-u rad])",
        )
    return T_from_ur_pose(values)


def read_visp_camera(path: Path) -> CameraModel:
    """Intrinsics from vpXmlParserCamera's file; ViSP's ``kud`` is OpenCV's k1."""
    try:
        root = ET.parse(path).getroot()
        cam = root.find("camera")
        if cam is None:
            raise ValueError("no <camera> element")
        width = int(_xml_text(cam, "image_width"))
        height = int(_xml_text(cam, "image_height"))
        models = {(_xml_text(m, "type")): m for m in cam.findall("model")}
        model = models.get("perspectiveProjWithDistortion") or models.get(
            "perspectiveProjWithoutDistortion"
        )
        if model is None:
            raise ValueError("no perspective <model>")
        kud = float(model.findtext("kud") or 0.0)
        return CameraModel(
            float(_xml_text(model, "px")), float(_xml_text(model, "py")),
            float(_xml_text(model, "u0")), float(_xml_text(model, "v0")),
            (kud, 0.0, 0.0, 0.0, 0.0) if kud != 0.0 else (), width, height,
        )
    except (ET.ParseError, ValueError, OSError) as err:
        raise DatasetError(ErrorCode.camera_unreadable,
                           f"cannot read camera {path}: {err}") from err


def _xml_text(node: ET.Element, tag: str) -> str:
    text = node.findtext(tag)
    if text is None:
        raise ValueError(f"missing <{tag}>")
    return text.strip()


def read_visp_board(path: Path) -> Board:
    """``chessboard-data.txt``: a line ``9 x 6`` (inner corners) and ``square size: 0.0236 m``."""
    try:
        text = path.read_text()
    except OSError as err:
        raise DatasetError(ErrorCode.board_missing,
                           f"cannot read board description {path}") from err
    size = re.search(r"(\d+)\s*x\s*(\d+)", text)
    square = re.search(r"square size:\s*([0-9.eE+-]+)\s*m", text)
    if not size or not square:
        raise DatasetError(
            ErrorCode.board_unreadable, f"{path} should give 'C x R' and 'square size: S m'"
        )
    return Board("chessboard", int(size[1]), int(size[2]), round(float(square[1]) * 1000.0, 9))


# --- the project's format --------------------------------------------------------------------


def load_project_dataset(folder: str | Path) -> HandEyeDataset:
    d = Path(folder)
    path = d / DATASET_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(ErrorCode.dataset_invalid, f"cannot read {path}: {err}") from err
    try:
        if data.get("format") != FORMAT_NAME:
            raise ValueError(f'"format" must be "{FORMAT_NAME}"')
        c = data["camera"]
        camera = CameraModel(float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"]),
                             tuple(c.get("dist", ())), int(c["width"]), int(c["height"]))
        board, target = None, None
        if "board" in data:
            b = data["board"]
            board = Board(b["kind"], int(b["cols"]), int(b["rows"]), float(b["pitch_mm"]))
        elif "target" in data:
            t = data["target"]
            target = Target(np.asarray(t["points_mm"], dtype=float),
                            float(t["dot_diameter_mm"]), t.get("polarity", "dark"))
        else:
            raise ValueError('the dataset names no pattern: give "board" or "target"')
        views = []
        for k, v in enumerate(data["views"]):
            try:
                T = T_from_pose_dict(v["T_base_flange"])
            except (KeyError, TypeError, ValueError) as err:
                raise DatasetError(
                    ErrorCode.pose_unreadable,
                    f"{path}: views[{k}].T_base_flange is not a pose object "
                    f'{{"position_mm": [x, y, z], "rotvec_rad": [rx, ry, rz]}} ({err})'
                ) from err
            image = d / str(v["image"])
            q = None
            if "joints_rad" in v:
                q = np.asarray(v["joints_rad"], dtype=float)
                if q.shape != (6,) or not np.all(np.isfinite(q)):
                    raise ValueError(f"views[{k}].joints_rad must be 6 finite angles")
            views.append(View(Path(v["image"]).stem, image, T, q))
        arm_model = data["arm"]["model"] if "arm" in data else None
        if arm_model is not None and arm_model not in UR_DH:
            raise ValueError(f'"arm.model" must be one of {", ".join(UR_DH)}')
    except DatasetError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise DatasetError(ErrorCode.dataset_invalid, f"{path}: {err!r}") from err
    return HandEyeDataset(camera, board, tuple(views), "project", d, target, arm_model)


def new_dataset_folder(folder: str | Path) -> Path:
    """Create ``folder`` for a dataset about to be recorded, before anything moves.

    Raises DatasetError ``dataset_exists`` when it already holds a dataset (a calibration's
    record is never overwritten) and ``dataset_unwritable`` when it cannot be written.
    """
    d = Path(folder)
    if (d / DATASET_FILE).exists():
        raise DatasetError(ErrorCode.dataset_exists,
                           f"{d} already holds a {DATASET_FILE}: choose a "
                           "new folder (a calibration's record is never overwritten)")
    try:
        d.mkdir(parents=True, exist_ok=True)
        probe = d / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise DatasetError(ErrorCode.dataset_unwritable, f"cannot write to {d}: {err}") from err
    return d


def save_project_dataset(
    folder: str | Path,
    camera: CameraModel,
    pattern: Board | Target,
    views: Sequence[tuple[str, NDArray[np.float64]]],
    images: Sequence[NDArray[np.uint8]] | None = None,
    joints_rad: Sequence[NDArray[np.float64]] | None = None,
    arm_model: str | None = None,
) -> HandEyeDataset:
    """Write ``dataset.json`` (and the images when given, lossless) for ``(image file,
    T_base_flange)`` views of a board or of the dot target, with each view's joints and the
    arm's model when given."""
    d = Path(folder)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise DatasetError(ErrorCode.dataset_unwritable, f"cannot create {d}: {err}") from err
    if images is not None:
        for (name, _), img in zip(views, images, strict=True):
            if not cv2.imwrite(str(d / name), img):
                raise DatasetError(ErrorCode.image_unwritable, f"cannot write {d / name}")
    data: dict[str, Any] = {
        "format": FORMAT_NAME,
        "version": 1,
        "camera": {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                   "width": camera.width, "height": camera.height, "dist": list(camera.dist)},
    }
    if isinstance(pattern, Board):
        data["board"] = {"kind": pattern.kind, "cols": pattern.cols, "rows": pattern.rows,
                         "pitch_mm": pattern.pitch_mm}
    else:
        data["target"] = {"points_mm": pattern.points_mm.tolist(),
                          "dot_diameter_mm": pattern.dot_diameter_mm,
                          "polarity": pattern.polarity}
    data["views"] = [{"image": name, "T_base_flange": pose_dict(T)} for name, T in views]
    if joints_rad is not None and arm_model is not None:
        for view, q in zip(data["views"], joints_rad, strict=True):
            view["joints_rad"] = [float(a) for a in np.asarray(q, dtype=float).reshape(6)]
        data["arm"] = {"model": arm_model}
    try:
        (d / DATASET_FILE).write_text(json.dumps(data, indent=2) + "\n")
    except OSError as err:
        raise DatasetError(ErrorCode.dataset_unwritable, f"cannot write {d / DATASET_FILE}: {err}"
                           ) from err
    return load_project_dataset(d)
