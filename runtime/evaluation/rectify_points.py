"""The rectifier over the frames of a points file (`dimenet rectify --points`, `dimenet bench --stream`):
one record of ``formats.rectified_points`` per frame, frame by frame; with ``--temporal`` through a
``rectify.stream.Stream``."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.points import PointsFrame
from dimenet.runtime.formats.rectified_points import error_record, frame_record
from dimenet.runtime.rectify.rectifier import Rectifier
from dimenet.runtime.rectify.stream import Stream


def rectified_records(rectifier: Rectifier, frames: Iterable[PointsFrame], *, refine: bool) -> Iterator[dict]:
    """``frame_record`` of each frame (``Rectifier.rectify``, the single-frame path), or its
    ``error_record`` when the rectifier refuses it (InputError); the run goes on."""
    for frame in frames:
        try:
            res = rectifier.rectify(frame.points_2d, frame.points_3d, refine=refine)
        except InputError as exc:
            yield error_record(frame, exc)
        else:
            yield frame_record(frame, res)


def streamed_records(stream: Stream, frames: Iterable[PointsFrame]) -> Iterator[dict]:
    """``frame_record`` of each frame's fused result (``Stream.update``) with its ``event`` and whether K is the
    filter's (``fused``), or its ``error_record`` when the rectifier refuses the frame; the run goes on."""
    for frame in frames:
        try:
            out = stream.update(frame.points_2d, frame.points_3d, frame.t_ns)
        except InputError as exc:
            yield error_record(frame, exc)
        else:
            yield {**frame_record(frame, out.result), "event": out.event, "fused": out.fused}
