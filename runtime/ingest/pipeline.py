"""Photos of the rig (and of a natural object with labelled points) -> a ``dimenet-dataset/1`` dataset.

Per photo (``ingest_photo``; in worker processes when ``workers`` > 1): decode it
(``photo.read_photo``), find the boards at native resolution (``board_detection``), tell them
apart and fit the photo's single-frame K (``board_identity``); when that camera shows a board in
view that was not found, the boards are searched again with every fallback detector
(``detect_boards(thorough=True)``). A photo without labels needs
MIN_BOARDS boards; a labelled one (scene ``natural``, as the paper's LEGO test) needs
MIN_BOARDS_NATURAL, its labels giving the rest. A photo that fails gets the reason in the report.

Then, in the photos' order, every accepted photo becomes one frame: the rig's corners (rig order,
NaN where not found), then the object's points (OBJECT.csv order) where labelled. On a rig
frame every valid point is in ``infer_mask``; on a natural frame only the labelled points.
``frame_id`` is the photo's file name. Specified in models_spec/ingest.md.
"""

from __future__ import annotations

import hashlib
import multiprocessing
from collections.abc import Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime import __version__
from dimenet.runtime.errors import DimenetError, IngestError, LabelsError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.natural_labels import ImageLabels, NaturalObject
from dimenet.runtime.formats.rig import Rig, rig_to_dict
from dimenet.runtime.geometry import MIN_POINTS, k_params, project, to_camera
from dimenet.runtime.geometry.camera import camera_centre, facing
from dimenet.runtime.ingest.detection import detect_boards
from dimenet.runtime.ingest.identity import identify, rough_k
from dimenet.runtime.ingest.photo import read_photo

GENERATOR = "dimenet.ingest"
MIN_BOARDS = 2  # boards a rig photo needs: two planes make K observable from the photo alone
MIN_BOARDS_NATURAL = 1  # boards a labelled photo needs (its labelled points add the depth)
SPLITS = ("auto", "train", "test")
AUTO_TRAIN_FRACTION = 0.8  # --split auto: share of rig photos in train, by file-name hash
IN_VIEW_MARGIN_PX = 16.0  # a board is expected in a photo when its corners lie this far inside the image


@dataclass(frozen=True)
class PhotoResult:
    """One photo's outcome: its rig corners and fit, or why it was skipped."""

    name: str  # file name, the frame's frame_id
    labels: Optional[ImageLabels]  # its labelled natural points, if any
    exif_orientation: int = 1
    image_size: Optional[tuple[int, int]] = None  # width, height px
    corners_px: Optional[np.ndarray] = None  # (P_rig, 2) px in rig order, NaN where not found
    boards: tuple[int, ...] = ()  # rig board indices found, ascending
    K: Optional[np.ndarray] = None  # (3, 3) px the photo's best single-frame K (fitted with its pose)
    rms_px: Optional[float] = None  # reprojection RMS under K
    runner_up_rms_px: Optional[float] = None  # the same under the next-best board labelling
    skipped: Optional[str] = None


@dataclass(frozen=True)
class Ingestion:
    """The dataset (None when no photo gave a frame) and the per-photo results, in the photos' order."""

    dataset: Optional[Dataset]
    results: tuple[PhotoResult, ...]
    splits: tuple[Optional[str], ...]  # each photo's split, None when skipped


def ingest_photo(path: Path, rig: Rig, labels: Optional[ImageLabels], object_points_mm: np.ndarray) -> PhotoResult:
    """Decode, detect, identify and fit one photo (pure: reads only ``path``)."""
    result = PhotoResult(name=path.name, labels=labels)
    try:
        photo = read_photo(path)
        h, w = photo.gray.shape
        result = replace(result, exif_orientation=photo.exif_orientation, image_size=(w, h))
        detections = detect_boards(photo.gray, rig)
        need = MIN_BOARDS if labels is None else MIN_BOARDS_NATURAL
        if len(detections) < need:
            kind = "a rig photo" if labels is None else "a labelled photo"
            return replace(result, skipped=f"{len(detections)} board(s) found, {kind} needs {need}")
        fixed_2d = np.empty((0, 2)) if labels is None else labels.points_px
        fixed_3d = np.empty((0, 3)) if labels is None else object_points_mm[labels.index]
        found = identify(detections, rig, rough_k((w, h)), fixed_2d, fixed_3d)
        missing = set(np.flatnonzero(boards_in_view(rig, found.K, found.rvec, found.tvec, (w, h)))) - set(found.boards)
        if missing:  # the rig says a board is in view: search again with every fallback detector
            detections = detect_boards(photo.gray, rig, thorough=True)
            found = identify(detections, rig, rough_k((w, h)), fixed_2d, fixed_3d)
    except DimenetError as exc:
        return replace(result, skipped=str(exc))
    n_points = int(np.isfinite(found.corners_px[:, 0]).sum()) + len(fixed_3d)
    if n_points < MIN_POINTS:
        return replace(result, skipped=f"{n_points} points found, a frame needs {MIN_POINTS}")
    return replace(
        result,
        corners_px=found.corners_px,
        boards=tuple(sorted(found.boards)),
        K=found.K,
        rms_px=found.rms_px,
        runner_up_rms_px=found.runner_up_rms_px,
    )


def boards_in_view(
    rig: Rig, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray, image_size: tuple[int, int]
) -> np.ndarray:
    """(B,) whether each rig board, seen by the camera (K px, pose {W}->{C}), lies in front of it, faces it
    and has every corner at least IN_VIEW_MARGIN_PX inside the (width, height) image."""
    w, h = image_size
    camera = camera_centre(rvec, tvec)
    seen = []
    for board in rig.boards:
        points = board.points()
        px = project(points, K, rvec, tvec)
        inside = np.all((px >= IN_VIEW_MARGIN_PX) & (px <= np.array([w - 1, h - 1]) - IN_VIEW_MARGIN_PX))
        seen.append(
            bool(
                inside
                and np.all(to_camera(points, rvec, tvec)[:, 2] > 0)
                and facing(points[:1], -board.normal()[None], camera)[0]
            )
        )
    return np.array(seen)


def auto_split(name: str) -> str:
    """``train`` for AUTO_TRAIN_FRACTION of file names, else ``test``, by the name's SHA-256: a photo keeps
    its split whatever photos are ingested with it."""
    h = int.from_bytes(hashlib.sha256(name.encode("utf-8")).digest()[:8], "big")
    return "train" if h < AUTO_TRAIN_FRACTION * 2**64 else "test"


def frame_split(result: PhotoResult, split: str) -> str:
    """The split of an accepted photo: ``split``, or under ``auto`` the name hash for rig photos and
    ``test`` for natural ones (as the paper's LEGO test)."""
    if split != "auto":
        return split
    return "test" if result.labels is not None else auto_split(result.name)


def _results(
    paths: list[Path], rig: Rig, labels: dict[str, ImageLabels], object_points_mm: np.ndarray, workers: int
) -> Iterator[PhotoResult]:
    jobs = ([p, rig, labels.get(p.name), object_points_mm] for p in paths)
    if workers == 1:
        yield from (ingest_photo(*job) for job in jobs)
        return
    with ProcessPoolExecutor(
        workers, mp_context=multiprocessing.get_context("spawn"), initializer=cv2.setNumThreads, initargs=(1,)
    ) as pool:
        yield from pool.map(ingest_photo, *zip(*jobs))


def check_inputs(paths: list[Path], labels: dict[str, ImageLabels], split: str, workers: int) -> None:
    """IngestError / LabelsError for what would fail late: no photos, missing files, repeated names,
    labels of photos not given, an unknown split, workers < 1."""
    if not paths:
        raise IngestError("no photos given")
    if split not in SPLITS:
        raise IngestError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    if workers < 1:
        raise IngestError(f"workers must be >= 1, got {workers}")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise IngestError(
            f"{missing[0]}: no such photo" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
        )
    names = [p.name for p in paths]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise IngestError(f"two photos are named {repeated[0]}: file names are the frames' ids and must be unique")
    foreign = sorted(set(labels) - set(names))
    if foreign:
        raise LabelsError(f"labels for {foreign[0]}, which is not among the photos given")


def assemble(results: list[PhotoResult], rig: Rig, obj: Optional[NaturalObject], split: str) -> Ingestion:
    """The dataset of the accepted photos, in order. A photo whose image size differs from the first
    accepted photo's is skipped (one dataset, one image size)."""
    size = next((r.image_size for r in results if r.skipped is None), None)
    results = [
        replace(
            r,
            skipped=f"image size {r.image_size[0]}x{r.image_size[1]} px differs from the "
            f"dataset's {size[0]}x{size[1]} px",
        )
        if r.skipped is None and r.image_size != size
        else r
        for r in results
    ]
    accepted = [r for r in results if r.skipped is None]
    splits = tuple(frame_split(r, split) if r.skipped is None else None for r in results)
    if not accepted:
        return Ingestion(dataset=None, results=tuple(results), splits=splits)
    object_points = np.empty((0, 3)) if obj is None else obj.points_mm
    n_rig = rig.n_points
    F, P = len(accepted), n_rig + len(object_points)
    p2, p3 = np.full((F, P, 2), np.nan), np.full((F, P, 3), np.nan)
    rig_points = rig.points()
    for k, r in enumerate(accepted):
        found = np.isfinite(r.corners_px[:, 0])
        p2[k, :n_rig][found], p3[k, :n_rig][found] = r.corners_px[found], rig_points[found]
        if r.labels is not None:
            p2[k, n_rig + r.labels.index] = r.labels.points_px
            p3[k, n_rig + r.labels.index] = object_points[r.labels.index]
    valid = np.isfinite(p2[..., 0])
    natural = np.array([r.labels is not None for r in accepted])
    infer = valid & np.where(natural[:, None], np.arange(P) >= n_rig, True)
    meta = {
        "generator": GENERATOR,
        "version": __version__,
        "units": {"2d": "px", "3d": "mm"},
        "rig": rig_to_dict(rig),
        "object_points": [] if obj is None else list(obj.point_ids),
        "split": split,
    }
    dataset = Dataset(
        image_size=np.array(size, np.int64),
        points_2d=p2,
        points_3d=p3,
        valid=valid,
        infer_mask=infer,
        split=np.array([s for s in splits if s is not None]),
        scene=np.where(natural, "natural", "rig"),
        meta=meta,
        frame_id=np.array([r.name for r in accepted]),
    )
    return Ingestion(dataset=dataset, results=tuple(results), splits=splits)


def ingest(
    paths: Iterable[str | Path],
    rig: Rig,
    *,
    split: str = "auto",
    obj: Optional[NaturalObject] = None,
    labels: Optional[dict[str, ImageLabels]] = None,
    workers: int = 1,
    progress: Callable[[Iterator[PhotoResult]], Iterable[PhotoResult]] = iter,
) -> Ingestion:
    """Ingest photos of ``rig`` (see the module doc); ``labels`` by photo file name need ``obj``.

    ``progress`` wraps the iterator of per-photo results (e.g. ``dimenet.runtime.cli.progress.progress``).
    Raises IngestError / LabelsError for bad input; a photo that cannot be used is skipped with a reason.
    """
    paths = [Path(p) for p in paths]
    labels = labels or {}
    if labels and obj is None:
        raise LabelsError("labels need the object's points (OBJECT.csv)")
    check_inputs(paths, labels, split, workers)
    object_points = np.empty((0, 3)) if obj is None else obj.points_mm
    results = list(progress(_results(paths, rig, labels, object_points, workers)))
    return assemble(results, rig, obj, split)


def report(ingestion: Ingestion, rig: Rig) -> dict:
    """The JSON report: one entry per photo (boards, corners, labels, K as fx, fy, cx, cy, RMS, split or why
    skipped) and totals."""

    def finite(x: Optional[float]) -> Optional[float]:
        return None if x is None or not np.isfinite(x) else round(float(x), 4)

    photos = []
    for r, s in zip(ingestion.results, ingestion.splits):
        photos.append(
            {
                "photo": r.name,
                "scene": "natural" if r.labels is not None else "rig",
                "split": s,
                "boards": [rig.boards[b].name for b in r.boards],
                "corners": 0 if r.corners_px is None else int(np.isfinite(r.corners_px[:, 0]).sum()),
                "labels": 0 if r.labels is None else len(r.labels.index),
                "K_px": None if r.K is None else [round(float(v), 2) for v in k_params(r.K)],
                "rms_px": finite(r.rms_px),
                "runner_up_rms_px": finite(r.runner_up_rms_px),
                "exif_orientation": r.exif_orientation,
                "skipped": r.skipped,
            }
        )
    ds = ingestion.dataset
    totals = {
        "photos": len(photos),
        "frames": 0 if ds is None else ds.n_frames,
        "skipped": sum(p["skipped"] is not None for p in photos),
        "boards": sum(len(p["boards"]) for p in photos),
        "corners": sum(p["corners"] for p in photos),
        "splits": {s: sum(p["split"] == s for p in photos) for s in ("train", "test")},
        "image_size": None if ds is None else ds.image_size.tolist(),
    }
    return {"generator": GENERATOR, "version": __version__, "totals": totals, "photos": photos}
