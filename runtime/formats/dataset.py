"""Dataset format ``dimenet-dataset/1``: the one reader, validator and writer.

The format is specified in ``models_spec/dataset-v1.md``. A dataset is one ``.npz``
file, read by ``formats.npz.read_npz`` (never unpickles; refuses a corrupt archive or one
declaring more than ``MAX_NPZ_BYTES`` before decoding it). Frames are F images, each with up to P
correspondences (NaN-padded); 2D points are pixels (x right, y down), 3D points are
millimetres in that frame's world frame {W}. A dataset may state its lens distortion
(``dist_coeffs`` about ``dist_K``; its points are then as the distorted image holds them, and
``Dataset.undistorted`` gives the pinhole points) and what the phone's SDK reported as each
frame's K (``K_platform``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Optional

import numpy as np

from dimenet.runtime.errors import DatasetError
from dimenet.runtime.formats.atomic import atomic_write
from dimenet.runtime.formats.npz import read_npz
from dimenet.runtime.geometry import MAX_COORDINATE, MIN_POINTS, undistort_points
from dimenet.runtime.json_text import JsonProblem, parse_json
from dimenet.runtime.rectify.user_camera import DIST_COEFF_COUNTS, MAX_DIST_COEFF

FORMAT = "dimenet-dataset/1"
SPLITS = ("train", "val", "test")
REQUIRED_KEYS = ("format", "image_size", "points_2d", "points_3d", "valid", "infer_mask", "split", "scene", "meta")
LENS_KEYS = ("dist_coeffs", "dist_K")  # a lens in a dataset, calibration or render truth file: both or neither
OPTIONAL_KEYS = ("K_true", "frame_id", "K_platform", "label_noise_px", *LENS_KEYS)
MAX_IMAGE_SIDE_PX = 1_000_000  # image_size: no camera image is wider (it also keeps int64 maths exact)
MAX_META_CHARS = 4 << 20  # meta: 4 Mi characters of JSON (the simulator's is ~5 k, ingest's grows with OBJECT.csv)


@dataclass(frozen=True)
class Dataset:
    """A validated dataset held in memory (see models_spec/dataset-v1.md)."""

    image_size: np.ndarray  # (2,) int64: width, height in px
    points_2d: np.ndarray  # (F, P, 2) float64 px, NaN where absent
    points_3d: np.ndarray  # (F, P, 3) float64 mm in {W}
    valid: np.ndarray  # (F, P) bool
    infer_mask: np.ndarray  # (F, P) bool, subset of valid
    split: np.ndarray  # (F,) str
    scene: np.ndarray  # (F,) str
    meta: dict = field(default_factory=dict)
    K_true: Optional[np.ndarray] = None  # (F, 3, 3) float64 px
    frame_id: Optional[np.ndarray] = None  # (F,) str
    K_platform: Optional[np.ndarray] = None  # (F, 3, 3) float64 px: the K the phone's SDK reported per frame
    dist_coeffs: Optional[np.ndarray] = None  # (n,) float64: OpenCV's lens distortion (n in DIST_COEFF_COUNTS) ...
    dist_K: Optional[np.ndarray] = None  # (3, 3) float64 px: ... stated about this fixed pinhole K
    # (F,) float64 px: the std per image axis of each frame's inference points' errors (the simulator's truth)
    label_noise_px: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        validate_arrays(self.to_arrays())

    @property
    def n_frames(self) -> int:
        return int(self.points_2d.shape[0])

    @property
    def n_points(self) -> int:
        return int(self.points_2d.shape[1])

    def select(self, frames: np.ndarray) -> Dataset:
        """The dataset restricted to ``frames`` (a boolean mask or index array over F)."""
        idx = np.arange(self.n_frames)[frames]
        if len(idx) == 0:  # say so, rather than "the dataset has no frames" about a dataset that has some
            raise DatasetError(f"select: none of the dataset's {self.n_frames} frames is selected (a dataset needs 1)")
        take = lambda a: None if a is None else a[idx]  # noqa: E731
        return replace(
            self,
            points_2d=self.points_2d[idx],
            points_3d=self.points_3d[idx],
            valid=self.valid[idx],
            infer_mask=self.infer_mask[idx],
            split=self.split[idx],
            scene=self.scene[idx],
            K_true=take(self.K_true),
            frame_id=take(self.frame_id),
            K_platform=take(self.K_platform),
            label_noise_px=take(self.label_noise_px),
        )

    def undistorted(self) -> Dataset:
        """The dataset with its points_2d undistorted to the pinhole camera of ``dist_K`` (px, in
        that camera's frame: a frame whose K differs from dist_K, as under OIS, keeps its own K)
        and without the distortion keys; itself when it states no distortion. DatasetError
        when an undistorted valid point lies far outside the image (a lens model that does not
        fit the points)."""
        if self.dist_coeffs is None:
            return self
        points = undistort_points(self.points_2d, self.dist_K, self.dist_coeffs)
        try:
            return replace(self, points_2d=points, dist_coeffs=None, dist_K=None)
        except DatasetError as exc:
            raise DatasetError(f"undistorted: {exc}") from None

    def frames_in(self, split: str) -> np.ndarray:
        """Boolean mask of the frames in ``split``."""
        return self.split == split

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {
            "format": np.array(FORMAT),
            "image_size": np.asarray(self.image_size),
            "points_2d": self.points_2d,
            "points_3d": self.points_3d,
            "valid": self.valid,
            "infer_mask": self.infer_mask,
            "split": np.asarray(self.split),
            "scene": np.asarray(self.scene),
            "meta": np.array(json.dumps(self.meta, sort_keys=True)),
        }
        if self.K_true is not None:
            arrays["K_true"] = self.K_true
        if self.frame_id is not None:
            arrays["frame_id"] = np.asarray(self.frame_id)
        for key in ("K_platform", "label_noise_px", "dist_coeffs", "dist_K"):
            if getattr(self, key) is not None:
                arrays[key] = getattr(self, key)
        return arrays


def _require(cond: bool, key: str, problem: str) -> None:
    if not cond:
        raise DatasetError(f"{key}: {problem}")


def _string_array(arrays: Mapping[str, Any], key: str, shape: tuple) -> np.ndarray:
    a = np.asarray(arrays[key])
    _require(a.dtype.kind == "U", key, f"must be a string array, got dtype {a.dtype}")
    _require(a.shape == shape, key, f"must have shape {shape}, got {a.shape}")
    return a


def _float_array(arrays: Mapping[str, Any], key: str, shape: tuple) -> np.ndarray:
    a = np.asarray(arrays[key])
    _require(a.dtype.kind == "f", key, f"must be a float array, got dtype {a.dtype}")
    _require(a.shape == shape, key, f"must have shape {shape}, got {a.shape}")
    return a.astype(np.float64, copy=False)


def _pinhole_matrices(arrays: Mapping[str, Any], key: str, shape: tuple) -> np.ndarray:
    """``arrays[key]`` as float64 (..., 3, 3) pinhole matrices [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] px:
    finite, fx, fy > 0, zero skew."""
    K = _float_array(arrays, key, shape)
    _require(bool(np.all(np.isfinite(K))), key, "has non-finite entries")
    zeros = K[..., [0, 1, 2, 2], [1, 0, 0, 1]]
    _require(
        bool(np.all(K[..., 0, 0] > 0) and np.all(K[..., 1, 1] > 0))
        and np.allclose(zeros, 0.0)
        and np.allclose(K[..., 2, 2], 1.0),
        key,
        "must be pinhole matrices [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] px (positive focal lengths, no skew)",
    )
    return K


def _distortion(arrays: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The lens distortion keys, both or neither: ``dist_coeffs`` (n,) OpenCV coefficients of
    magnitude <= MAX_DIST_COEFF, ``dist_K`` (3, 3) px the pinhole K they are stated about."""
    present = [k for k in ("dist_coeffs", "dist_K") if k in arrays]
    if not present:
        return {}
    other = "dist_K" if present == ["dist_coeffs"] else "dist_coeffs"
    _require(len(present) == 2, present[0], f"needs {other} with it (the distortion is stated about dist_K)")
    counts = "/".join(str(n) for n in DIST_COEFF_COUNTS)
    raw = np.asarray(arrays["dist_coeffs"])
    _require(
        raw.ndim == 1 and raw.shape[0] in DIST_COEFF_COUNTS,
        "dist_coeffs",
        f"must have shape (n,), n one of {counts} (OpenCV's models), got {raw.shape}",
    )
    coeffs = _float_array(arrays, "dist_coeffs", raw.shape)
    _require(
        bool(np.all(np.isfinite(coeffs)) and np.all(np.abs(coeffs) <= MAX_DIST_COEFF)),
        "dist_coeffs",
        f"must be finite with magnitude <= {MAX_DIST_COEFF:g}, got {coeffs.tolist()}",
    )
    return {"dist_coeffs": coeffs, "dist_K": _pinhole_matrices(arrays, "dist_K", (3, 3))}


def validate_arrays(arrays: Mapping[str, Any]) -> dict[str, Any]:
    """Check a mapping of arrays against ``dimenet-dataset/1``; return normalised fields.

    Raises DatasetError naming the key and the problem.
    """
    keys = set(arrays)
    missing = [k for k in REQUIRED_KEYS if k not in keys]
    _require(not missing, missing[0] if missing else "", "missing required key")
    unknown = sorted(keys - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
    _require(not unknown, unknown[0] if unknown else "", "unknown key (format dimenet-dataset/1 does not define it)")
    fmt = np.asarray(arrays["format"])
    _require(
        fmt.shape == () and fmt.dtype.kind == "U" and str(fmt) == FORMAT,
        "format",
        f"must be exactly {FORMAT!r}, got {fmt!r}",
    )
    size = np.asarray(arrays["image_size"])
    _require(size.dtype.kind in "iu" and size.shape == (2,), "image_size", "must be 2 integers (width, height) px")
    _require(bool(np.all(size > 0)), "image_size", f"must be positive, got {size.tolist()}")
    _require(
        bool(np.all(size <= MAX_IMAGE_SIDE_PX)), "image_size", f"must be <= {MAX_IMAGE_SIDE_PX} px, got {size.tolist()}"
    )
    p2 = np.asarray(arrays["points_2d"])
    _require(p2.ndim == 3 and p2.shape[2] == 2, "points_2d", f"must have shape (F, P, 2), got {p2.shape}")
    F, P = p2.shape[:2]
    _require(F > 0, "points_2d", "the dataset has no frames")
    p2 = _float_array(arrays, "points_2d", (F, P, 2))
    p3 = _float_array(arrays, "points_3d", (F, P, 3))
    valid = np.asarray(arrays["valid"])
    _require(
        valid.dtype == bool and valid.shape == (F, P),
        "valid",
        f"must be bool of shape {(F, P)}, got {valid.dtype} {valid.shape}",
    )
    infer = np.asarray(arrays["infer_mask"])
    _require(
        infer.dtype == bool and infer.shape == (F, P),
        "infer_mask",
        f"must be bool of shape {(F, P)}, got {infer.dtype} {infer.shape}",
    )
    _require(not np.any(infer & ~valid), "infer_mask", "must be a subset of valid (a point to infer from is not valid)")
    bad = valid & ~(np.isfinite(p2).all(-1) & np.isfinite(p3).all(-1))
    if bad.any():
        f, p = np.argwhere(bad)[0]
        raise DatasetError(f"points_2d/points_3d: valid point has a non-finite coordinate (frame {f}, point {p})")
    w, h = (int(v) for v in size)
    far_2d = np.any((p2 < [-w, -h]) | (p2 > [2 * w, 2 * h]), -1)
    far = valid & (far_2d | np.any(np.abs(p3) >= MAX_COORDINATE, -1))
    if far.any():
        f, p = np.argwhere(far)[0]
        raise DatasetError(
            f"points_2d/points_3d: valid point {p} of frame {f} at {p2[f, p].tolist()} px, {p3[f, p].tolist()} "
            f"lies far outside the {w}x{h} px image (more than its size beyond an edge) or beyond "
            f"+-{MAX_COORDINATE:g} in 3D"
        )
    counts = valid.sum(1)
    _require(
        bool(np.all(counts >= MIN_POINTS)),
        "valid",
        f"frame {int(np.argmin(counts))} has {int(counts.min())} valid points, needs >= {MIN_POINTS}",
    )
    split = _string_array(arrays, "split", (F,))
    unknown_split = sorted(set(split.tolist()) - set(SPLITS))
    _require(
        not unknown_split,
        "split",
        f"unknown split {unknown_split[0] if unknown_split else ''!r}; allowed: {', '.join(SPLITS)}",
    )
    scene = _string_array(arrays, "scene", (F,))
    _require(bool(np.all(np.char.str_len(scene) > 0)), "scene", "empty scene name")
    meta_raw = np.asarray(arrays["meta"])
    _require(meta_raw.shape == () and meta_raw.dtype.kind == "U", "meta", "must be a JSON string")
    try:
        meta = parse_json(str(meta_raw), max_chars=MAX_META_CHARS)
    except JsonProblem as exc:
        raise DatasetError(f"meta: not valid JSON ({exc.problem})" if exc.line else f"meta: {exc.problem}") from None
    _require(isinstance(meta, dict), "meta", "must be a JSON object")
    out: dict[str, Any] = {
        "image_size": size.astype(np.int64),
        "points_2d": p2,
        "points_3d": p3,
        "valid": valid,
        "infer_mask": infer,
        "split": split,
        "scene": scene,
        "meta": meta,
    }
    if "K_true" in arrays:
        K = _float_array(arrays, "K_true", (F, 3, 3))
        _require(bool(np.all(np.isfinite(K))), "K_true", "has non-finite entries")
        _require(
            bool(np.all(K[:, 0, 0] > 0) and np.all(K[:, 1, 1] > 0) and np.allclose(K[:, 2], [0, 0, 1])),
            "K_true",
            "must be intrinsic matrices (positive focal lengths, last row 0 0 1)",
        )
        out["K_true"] = K
    if "frame_id" in arrays:
        out["frame_id"] = _string_array(arrays, "frame_id", (F,))
    if "K_platform" in arrays:
        out["K_platform"] = _pinhole_matrices(arrays, "K_platform", (F, 3, 3))
    if "label_noise_px" in arrays:
        noise = _float_array(arrays, "label_noise_px", (F,))
        _require(bool(np.all(np.isfinite(noise) & (noise >= 0))), "label_noise_px", "must be finite and >= 0 px")
        out["label_noise_px"] = noise
    out.update(_distortion(arrays))
    return out


def read_dataset(path: str | Path) -> Dataset:
    """Read and validate a ``dimenet-dataset/1`` file. Raises DatasetError naming the file (never pickle-loads).

    A corrupt, truncated or foreign file, or one declaring more than ``npz.MAX_NPZ_BYTES`` of arrays,
    is refused before its arrays are decoded (see ``formats.npz``).
    """
    path = Path(path)
    arrays = read_npz(path, DatasetError, "dataset file")
    try:
        return Dataset(**validate_arrays(arrays))
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None


def write_dataset(dataset: Dataset, path: str | Path) -> Path:
    """Write atomically (temp file + rename): a failure leaves any previous file intact."""
    arrays = dataset.to_arrays()
    return atomic_write(path, lambda f: np.savez_compressed(f, **arrays))
