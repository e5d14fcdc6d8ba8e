"""Photos of the rig (and of a natural object with labelled points) -> a ``dimenet-dataset/1`` dataset.

Per photo (``ingest_photo``; by ``workers`` threads and helper processes when ``workers`` > 1,
``jobs.workers.run_shared``, results in the photos' order):
decode it (``photo.read_photo``), find the boards (``detection.detect_boards``; with a rig of several
boards the first one kept places the others, ``placement.place``), tell them apart and
fit the photo's single-frame K (``identity``); when that camera shows a board in view that was not
found, it is looked for again where the camera puts it (``predicted.search_predicted``). A photo
without labels needs ``min_boards`` boards (``default_min_boards``: MIN_BOARDS, or 1 for a one-board
rig; a photo of one board is a planar frame without K); a labelled one (scene ``natural``, as the
paper's LEGO test) needs MIN_BOARDS_NATURAL, its labels giving the rest. Each board's outcome (kept,
dropped and why, not found) is in the result's ``board_lines`` (``outcome``). A photo that fails,
whatever the stage (a size beyond the caps of ``photo.check_size``, undecodable, a label outside the
image, an OpenCV or numeric error in detection or identification), is skipped with the reason in the
report; the run goes on.

Then, in the photos' order, every accepted photo becomes one frame: the rig's corners (rig order,
NaN where not found), then the object's points (OBJECT.csv order) where labelled. On a rig
frame every valid point is in ``infer_mask``; on a natural frame only the labelled points.
``frame_id`` is the photo's file name. With a ``camera`` (its lens known, e.g. from a camera file), a
photo of another image size is skipped, each photo's single-frame K is the pinhole camera's (its points
undistorted by the lens) and the dataset carries the lens. Specified in models_spec/ingest.md.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Callable, Optional

import cv2
import numpy as np

from dimenet.runtime import __version__
from dimenet.runtime.errors import CalibrationError, DimenetError, IngestError, LabelsError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.natural_labels import MAX_OBJECT_MM, ImageLabels, NaturalObject
from dimenet.runtime.formats.rig import Rig, rig_to_dict
from dimenet.runtime.geometry import MIN_POINTS, k_params, project, undistort_points
from dimenet.runtime.ingest.detection import BoardSearch, detect_boards
from dimenet.runtime.ingest.identity import (
    Identification,
    check_unambiguous,
    label,
    label_planar,
    refit,
    rough_k,
)
from dimenet.runtime.ingest.outcome import BoardLine, board_lines, shortfall
from dimenet.runtime.ingest.photo import MAX_MEGAPIXELS, read_photo
from dimenet.runtime.ingest.placement import boards_in_view, place
from dimenet.runtime.ingest.predicted import search_predicted
from dimenet.runtime.ingest.wider import look_from_one_plane, look_under_close_labellings
from dimenet.runtime.jobs.workers import run_shared
from dimenet.runtime.rectify.user_camera import Camera

GENERATOR = "dimenet.ingest"
MIN_BOARDS = 2  # boards a rig photo needs (a rig of 2 or more boards): two planes make K observable from the photo
MIN_BOARDS_NATURAL = 1  # boards a labelled photo needs (its labelled points add the depth)
SPLITS = ("auto", "train", "test")
AUTO_TRAIN_FRACTION = 0.8  # --split auto: share of rig photos in train, by file-name hash
LABEL_MARGIN = 1.0  # a label may lie this many image sizes beyond the image (a point extrapolated, e.g. hidden)
# What a photo's failure may raise besides DimenetError: OpenCV's errors and numeric ones (a singular or
# non-converging linear algebra step, an overflow). Anything else (a bug, KeyboardInterrupt, MemoryError) propagates.
PHOTO_FAILURES = (DimenetError, cv2.error, np.linalg.LinAlgError, ArithmeticError)


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
    board_lines: tuple[BoardLine, ...] = ()  # what became of each board (outcome.board_lines)


@dataclass(frozen=True)
class Ingestion:
    """The dataset (None when no photo gave a frame) and the per-photo results, in the photos' order."""

    dataset: Optional[Dataset]
    results: tuple[PhotoResult, ...]
    splits: tuple[Optional[str], ...]  # each photo's split, None when skipped


def failure_reason(exc: BaseException, stage: str) -> str:
    """The report's reason for a photo that failed with one of PHOTO_FAILURES while ``stage``."""
    if isinstance(exc, DimenetError):
        return str(exc)
    if isinstance(exc, cv2.error):
        return f"OpenCV failed while {stage} ({exc.func or 'unknown function'}: {exc.err or exc})"
    return f"numeric failure while {stage} ({type(exc).__name__}: {exc})"


def check_labels(labels: ImageLabels, image_size: tuple[int, int], point_ids: tuple[str, ...] = ()) -> None:
    """LabelsError unless every labelled point of a photo lies within LABEL_MARGIN image sizes of its
    (width, height) px image."""
    w, h = image_size
    x, y = labels.points_px[:, 0], labels.points_px[:, 1]
    mx, my = LABEL_MARGIN * w, LABEL_MARGIN * h
    outside = np.flatnonzero(~((x >= -mx) & (x <= w + mx) & (y >= -my) & (y <= h + my)))
    if outside.size:
        k = int(outside[0])
        index = int(labels.index[k])
        name = repr(point_ids[index]) if index < len(point_ids) else f"#{index}"
        more = f" (and {outside.size - 1} more)" if outside.size > 1 else ""
        raise LabelsError(
            f"labels: point {name} at ({x[k]:.6g}, {y[k]:.6g}) px lies far outside the {w}x{h} px image{more} "
            f"(a label may lie at most {LABEL_MARGIN:g} image size(s) beyond its edges)"
        )


def points_shortfall(n_points: int) -> str:
    """A skipped photo's reason when it has fewer than MIN_POINTS points."""
    return f"{n_points} points found, a frame needs {MIN_POINTS}"


def default_min_boards(rig: Rig) -> int:
    """Boards a rig photo needs unless told: 1 for a one-board rig (planar frames), else MIN_BOARDS."""
    return min(MIN_BOARDS, len(rig.boards))


def find_and_label(gray: np.ndarray, rig: Rig, fixed_2d: np.ndarray, fixed_3d: np.ndarray, search: BoardSearch):
    """The labelling of the boards found (``identity.label``), after looking again, where its camera puts them,
    for the boards it shows in view but that were not found (``predicted.search_predicted``; the camera of
    the best labelling is good enough to say where, even before it is known to be unambiguous), labelled again
    when any is found. Returns the final labelling, the search with the boards found again (and those hidden
    where the camera puts them, unless the new labelling tells the boards apart otherwise), and which rig
    boards are in view (B,)."""
    h, w = gray.shape
    found = label(list(search.detections), rig, rough_k((w, h)), fixed_2d, fixed_3d)
    in_view = boards_in_view(rig, found.K, found.rvec, found.tvec, (w, h))
    missing = sorted(set(np.flatnonzero(in_view)) - set(found.boards))
    if not missing:
        return found, search, in_view
    predicted = {int(b): project(rig.boards[b].points(), found.K, found.rvec, found.tvec) for b in missing}
    again = search_predicted(gray, rig, search.detections, predicted)
    search = BoardSearch(search.detections + again.detections, search.dropped + again.dropped, again.hidden)
    if not again.detections:
        return found, search, in_view
    before = found.boards
    found = label(list(search.detections), rig, rough_k((w, h)), fixed_2d, fixed_3d)
    if found.boards[: len(before)] != before:  # told apart otherwise: what was hidden was another board
        search = replace(search, hidden=())
    return found, search, boards_in_view(rig, found.K, found.rvec, found.tvec, (w, h))


def under_lens(found: Identification, rig: Rig, fixed_2d: np.ndarray, fixed_3d: np.ndarray, camera: Camera):
    """The photo's single-frame K, pose and RMS of the pinhole camera: its points undistorted by the lens."""
    seen = np.isfinite(found.corners_px[:, 0])
    points_2d = undistort_points(np.vstack([found.corners_px[seen], fixed_2d]), camera.lens_K, camera.dist_coeffs)
    points_3d = np.vstack([rig.points()[seen], fixed_3d])
    rms, fit = refit([points_2d], [points_3d], found.K, found.rvec[None], found.tvec[None])
    return replace(found, K=fit.K[0], rvec=fit.rvec[0], tvec=fit.tvec[0], rms_px=float(rms[0]))


def ingest_photo(
    path: Path,
    rig: Rig,
    labels: Optional[ImageLabels],
    object_points_mm: np.ndarray,
    max_megapixels: float = MAX_MEGAPIXELS,
    point_ids: tuple[str, ...] = (),
    min_boards: Optional[int] = None,
    camera: Optional[Camera] = None,
) -> PhotoResult:
    """Decode, detect, identify and fit one photo (pure: reads only ``path``). A rig photo needs ``min_boards``
    boards (``default_min_boards`` when None), a labelled one MIN_BOARDS_NATURAL; a rig photo of one board is
    a planar frame (no K). With a ``camera``, a photo of another image size is skipped and K is fitted under
    its lens. Never raises for a bad photo: any of PHOTO_FAILURES becomes the result's ``skipped`` reason."""
    result = PhotoResult(name=path.name, labels=labels)
    stage = "decoding"
    search = BoardSearch(())
    try:
        photo = read_photo(path, max_megapixels)
        h, w = photo.gray.shape
        result = replace(result, exif_orientation=photo.exif_orientation, image_size=(w, h))
        if camera is not None and tuple(camera.image_size) != (w, h):
            cw, ch = camera.image_size
            return replace(result, skipped=f"{w}x{h} px, the camera's image is {cw}x{ch} px")
        if labels is not None:
            check_labels(labels, (w, h), point_ids)
        stage = "finding the boards"
        placer = partial(place, photo.gray, rig) if len(rig.boards) > 1 else None
        search = detect_boards(photo.gray, rig, placer)
        need = (default_min_boards(rig) if min_boards is None else min_boards) if labels is None else MIN_BOARDS_NATURAL
        if 0 < len(search.detections) < need and len(rig.boards) > 1:  # one board's camera says where the others are
            search = look_from_one_plane(photo.gray, rig, search)
        if len(search.detections) < need:
            kind = "a rig photo" if labels is None else "a labelled photo"
            return replace(result, skipped=shortfall(search, need, kind), board_lines=board_lines(rig, search))
        stage = "identifying the boards"
        if labels is None and len(search.detections) == 1:
            board, corners = label_planar(search.detections[0], rig)
            lines = board_lines(rig, search, (board,))
            n_points = int(np.isfinite(corners[:, 0]).sum())
            if n_points < MIN_POINTS:
                return replace(result, skipped=points_shortfall(n_points), board_lines=lines)
            return replace(result, corners_px=corners, boards=(board,), board_lines=lines)
        fixed_2d = np.empty((0, 2)) if labels is None else labels.points_px
        fixed_3d = np.empty((0, 3)) if labels is None else object_points_mm[labels.index]
        try:
            found, search, in_view = find_and_label(photo.gray, rig, fixed_2d, fixed_3d, search)
        except CalibrationError:  # the boards found lie in one plane: no camera yet to say where the others are
            wider = look_from_one_plane(photo.gray, rig, search)
            if len(wider.detections) == len(search.detections):
                raise
            found, search, in_view = find_and_label(photo.gray, rig, fixed_2d, fixed_3d, wider)
        wider = look_under_close_labellings(photo.gray, rig, found, search)
        if len(wider.detections) > len(search.detections):
            found, search, in_view = find_and_label(photo.gray, rig, fixed_2d, fixed_3d, wider)
        check_unambiguous(found)
        if camera is not None and camera.dist_coeffs is not None:
            found = under_lens(found, rig, fixed_2d, fixed_3d, camera)
        n_points = int(np.isfinite(found.corners_px[:, 0]).sum()) + len(fixed_3d)
    except PHOTO_FAILURES as exc:
        return replace(result, skipped=failure_reason(exc, stage), board_lines=board_lines(rig, search))
    lines = board_lines(rig, search, found.boards, in_view)
    if n_points < MIN_POINTS:
        return replace(result, skipped=points_shortfall(n_points), board_lines=lines)
    return replace(
        result,
        corners_px=found.corners_px,
        boards=tuple(sorted(found.boards)),
        K=found.K,
        rms_px=found.rms_px,
        runner_up_rms_px=found.runner_up_rms_px,
        board_lines=lines,
    )


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
    paths: list[Path],
    rig: Rig,
    labels: dict[str, ImageLabels],
    obj: Optional[NaturalObject],
    workers: int,
    max_megapixels: float,
    min_boards: int,
    camera: Optional[Camera],
) -> Iterator[PhotoResult]:
    object_points = np.empty((0, 3)) if obj is None else obj.points_mm
    point_ids = () if obj is None else obj.point_ids
    jobs = [[p, rig, labels.get(p.name), object_points, max_megapixels, point_ids, min_boards, camera] for p in paths]
    if workers == 1:
        yield from (ingest_photo(*job) for job in jobs)
        return
    yield from run_shared(_ingest_job, jobs, workers)


def _ingest_job(job: list) -> PhotoResult:
    """``ingest_photo`` of one job, its arguments in order (the function ``run_shared`` runs over the jobs)."""
    return ingest_photo(*job)


def check_object(obj: NaturalObject, source: str = "OBJECT.csv") -> None:
    """LabelsError naming ``source`` and the point when a coordinate of the object is beyond MAX_OBJECT_MM
    (finite but absurd, e.g. 1e300: its squares would overflow the fits)."""
    far = ~(np.abs(obj.points_mm) <= MAX_OBJECT_MM)  # NaN too
    if far.any():
        k, axis = (int(v) for v in np.argwhere(far)[0])
        raise LabelsError(
            f"{source}: point {obj.point_ids[k]!r}: {('X_mm', 'Y_mm', 'Z_mm')[axis]} = {obj.points_mm[k, axis]:g} "
            f"lies beyond ±{MAX_OBJECT_MM:g} mm of the rig"
        )


def check_inputs(
    paths: list[Path], labels: dict[str, ImageLabels], split: str, workers: int, max_megapixels: float = MAX_MEGAPIXELS
) -> None:
    """IngestError / LabelsError for what would fail late: no photos, missing files, repeated names,
    labels of photos not given, an unknown split, workers < 1, a pixel cap that is not a positive number."""
    if not paths:
        raise IngestError("no photos given")
    if not (isinstance(max_megapixels, (int, float)) and 0 < max_megapixels < float("inf")):
        raise IngestError(f"max_megapixels must be a positive number, got {max_megapixels!r}")
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


def assemble(
    results: list[PhotoResult], rig: Rig, obj: Optional[NaturalObject], split: str, camera: Optional[Camera] = None
) -> Ingestion:
    """The dataset of the accepted photos, in order, with the ``camera``'s lens if it has one. A photo whose
    image size differs from the first accepted photo's is skipped (one dataset, one image size)."""
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
    if camera is not None and camera.dist_coeffs is not None:
        dataset = replace(dataset, dist_coeffs=np.array(camera.dist_coeffs), dist_K=np.array(camera.lens_K))
    return Ingestion(dataset=dataset, results=tuple(results), splits=splits)


def check_min_boards(min_boards: int, rig: Rig) -> None:
    """IngestError unless 1 <= ``min_boards`` <= the rig's number of boards."""
    if isinstance(min_boards, bool) or not isinstance(min_boards, int) or not 1 <= min_boards <= len(rig.boards):
        raise IngestError(
            f"min_boards must be an integer from 1 to the rig's {len(rig.boards)} boards, got {min_boards!r}"
        )


def ingest(
    paths: Iterable[str | Path],
    rig: Rig,
    *,
    split: str = "auto",
    obj: Optional[NaturalObject] = None,
    labels: Optional[dict[str, ImageLabels]] = None,
    workers: int = 1,
    progress: Callable[[Iterator[PhotoResult]], Iterable[PhotoResult]] = iter,
    max_megapixels: float = MAX_MEGAPIXELS,
    min_boards: Optional[int] = None,
    camera: Optional[Camera] = None,
) -> Ingestion:
    """Ingest photos of ``rig`` (see the module doc); ``labels`` by photo file name need ``obj``. A rig photo
    needs ``min_boards`` boards (``default_min_boards(rig)`` when None: 1 for a one-board rig, else 2).
    ``camera``: the photos' camera with its lens (see the module doc), or None.

    ``progress`` wraps the iterator of per-photo results (e.g. ``dimenet.runtime.jobs.progress.progress``).
    Raises IngestError / LabelsError for bad input (before any photo is read); a photo that cannot be used
    (including one over ``max_megapixels``, see ``photo.check_size``) is skipped with a reason.
    """
    paths = [Path(p) for p in paths]
    labels = labels or {}
    if labels and obj is None:
        raise LabelsError("labels need the object's points (OBJECT.csv)")
    if obj is not None:
        check_object(obj)
    check_inputs(paths, labels, split, workers, max_megapixels)
    min_boards = default_min_boards(rig) if min_boards is None else min_boards
    check_min_boards(min_boards, rig)
    results = list(progress(_results(paths, rig, labels, obj, workers, max_megapixels, min_boards, camera)))
    return assemble(results, rig, obj, split, camera)


def board_line_entry(line: BoardLine, rig: Rig, finite: Callable[[Optional[float]], Optional[float]]) -> dict:
    """One board's line of the JSON report."""
    return {
        "board": None if line.board is None else rig.boards[line.board].name,
        "pattern": list(line.pattern),
        "status": line.status,
        "found_by": line.found_by,
        "residual_px": finite(line.residual_px),
        "tolerance_px": finite(line.tolerance_px),
        "why": line.why,
    }


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
                "board_lines": [board_line_entry(line, rig, finite) for line in r.board_lines],
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
