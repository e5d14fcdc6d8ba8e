"""The rectifier over the frames of a points file (`dimenet rectify --points`, `dimenet bench --stream`):
one record of ``formats.rectified_points`` per frame, frame by frame; with ``--temporal`` through a
``rectify.stream.Stream``."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from dimenet.runtime.errors import InputError, PointsError
from dimenet.runtime.formats.points import PointsFrame
from dimenet.runtime.formats.rectified_points import error_record, frame_record
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.stream import Stream


def rectified_records(rectifier: Rectifier, frames: Iterable[PointsFrame], *, refine: bool) -> Iterator[dict]:
    """``frame_record`` of each frame (``Rectifier.rectify``, the single-frame path), or its
    ``error_record`` when the rectifier refuses it (InputError); the run goes on. A frame with its own K_c
    (points format 2) is rectified about it."""
    for frame in frames:
        try:
            res = rectifier.rectify(frame.points_2d, frame.points_3d, refine=refine, K_c=frame.K_c)
        except InputError as exc:
            yield error_record(frame, exc)
        else:
            yield frame_record(frame, res)


def streamed_records(stream: Stream, frames: Iterable[PointsFrame]) -> Iterator[dict]:
    """``frame_record`` of each frame's fused result (``Stream.update``, with the frame's own K_c where points
    format 2 gives one) with its ``event`` and whether K is the filter's (``fused``), or its ``error_record`` when
    the rectifier refuses the frame; the run goes on. In a stream with motion, a frame with its own K_c or without
    t_ns is a PointsError: the motion (the gyroscope's loop, the lens shift) predicts c about the camera's one K_c,
    at each frame's time on its clock."""
    for frame in frames:
        if frame.K_c is not None and stream.gyro is not None:
            raise PointsError(
                f"frame {frame.frame_id!r} (line {frame.line}) gives its own K_c (fx_px..cy_px): with --motion the "
                "motion predicts c about the camera's one K_c; track the file without --motion"
            )
        if frame.t_ns is None and stream.gyro is not None:
            raise PointsError(
                f"frame {frame.frame_id!r} (line {frame.line}) has no t_ns: with --motion every frame needs its time "
                "on the motion's clock (a t_ns column)"
            )
        try:
            out = stream.update(frame.points_2d, frame.points_3d, frame.t_ns, K_c=frame.K_c)
        except InputError as exc:
            yield error_record(frame, exc)
        else:
            yield {**frame_record(frame, out.result), "event": out.event, "fused": out.fused}
