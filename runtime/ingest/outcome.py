"""What became of each board in one photo: the report's per-board lines and a skipped photo's message.

Every board a detector found is a line: ``identified`` (kept and labelled with its rig board), ``found``
(kept, the photo skipped before or while its boards were told apart) or ``dropped`` (the refinement
refused it: why, with its largest corner residual and the tolerance, px). Every rig board not found is a
line ``not found``: by name once the photo's camera is known (in view or not; in view and hidden where that
camera puts it, how many corners are no checker corner there), else by pattern.
Specified in models_spec/ingest.md ("Report").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dimenet.runtime.formats.rig import Rig
from dimenet.runtime.ingest.detection import BoardSearch

IDENTIFIED, FOUND, DROPPED, NOT_FOUND = "identified", "found", "dropped", "not found"


@dataclass(frozen=True)
class BoardLine:
    """One board's outcome in a photo; ``board`` its rig index when known, ``residual_px``/``tolerance_px``
    its largest corner residual under its board model and what it may be (px), ``why`` for the others."""

    status: str
    pattern: tuple[int, int]
    board: Optional[int] = None
    found_by: Optional[str] = None
    residual_px: Optional[float] = None
    tolerance_px: Optional[float] = None
    why: Optional[str] = None


def board_lines(
    rig: Rig, search: BoardSearch, boards: Optional[tuple[int, ...]] = None, in_view: Optional[np.ndarray] = None
) -> tuple[BoardLine, ...]:
    """The lines of a photo's boards: ``search`` what was found and dropped; ``boards`` the rig board of each
    detection once identified (None: not identified); ``in_view`` (B,) which rig boards the photo's camera
    shows in view (None: unknown)."""
    lines = [
        BoardLine(
            FOUND if boards is None else IDENTIFIED,
            d.pattern if boards is None else rig.boards[boards[k]].inner_corners,
            d.board if boards is None else boards[k],
            d.found_by,
            d.residual_px,
            d.tolerance_px,
        )
        for k, d in enumerate(search.detections)
    ]
    lines += [
        BoardLine(DROPPED, x.pattern, None, x.found_by, x.residual_px, x.tolerance_px, x.reason) for x in search.dropped
    ]
    if boards is not None:
        hidden = dict(search.hidden)
        for b, board in enumerate(rig.boards):
            if b not in boards:
                seen = in_view is not None and bool(in_view[b])
                why = f"in view of the photo's camera, {hidden.get(b, 'found by no detector step')}"
                lines.append(BoardLine(NOT_FOUND, board.inner_corners, b, why=why if seen else "not in view"))
        return tuple(lines)
    known = {d.board for d in search.detections if d.board is not None}
    plain = [d.pattern for d in search.detections if d.board is None]
    for b, board in enumerate(rig.boards):
        if board.aruco is not None:
            if b not in known:
                lines.append(BoardLine(NOT_FOUND, board.inner_corners, b))
        elif board.inner_corners in plain:
            plain.remove(board.inner_corners)  # a plain detection of this pattern may be this board
        else:
            lines.append(BoardLine(NOT_FOUND, board.inner_corners))
    return tuple(lines)


def shortfall(search: BoardSearch, need: int, kind: str) -> str:
    """A skipped photo's reason when too few boards are kept: how many were found, how many dropped and why."""
    text = f"{len(search.detections)} board(s) found"
    if search.dropped:
        reasons = "; ".join(dict.fromkeys(x.reason for x in search.dropped))
        text += f", {len(search.dropped)} more found by a detector but dropped ({reasons})"
    return f"{text}, {kind} needs {need}"
