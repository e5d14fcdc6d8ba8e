"""The u x v image grid of DIME-Net (paper Sec. IV-A): cell geometry shared by the grid
feature and the cell-emptying test condition.

u is the number of columns (along x), v the number of rows (along y); the cells split the
image into u x v equal rectangles (square for the paper's 8x6 on 4032x3024: 504 px).
Cells are numbered in lexicographic (row, column) order: index = row * u + column.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from dimenet.runtime.errors import InputError


@dataclass(frozen=True)
class Grid:
    cols: int  # u, cells along x
    rows: int  # v, cells along y

    def __post_init__(self) -> None:
        if self.cols < 1 or self.rows < 1:
            raise InputError(f"grid must have at least 1x1 cells, got {self.cols}x{self.rows}")

    @property
    def n_cells(self) -> int:
        return self.cols * self.rows

    def __str__(self) -> str:
        return f"{self.cols}x{self.rows}"

    def fits(self, image_size) -> bool:
        """Whether every cell of an image of ``image_size`` (width, height) px holds a pixel."""
        return self.cols <= image_size[0] and self.rows <= image_size[1]

    @classmethod
    def parse(cls, text: str) -> Grid:
        """'8x6' -> Grid(cols=8, rows=6)."""
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
        if not m:
            raise InputError(f"grid must look like '8x6' (columns x rows), got {text!r}")
        return cls(int(m.group(1)), int(m.group(2)))

    def cell_index(self, points_2d: np.ndarray, image_size) -> np.ndarray:
        """(..., N, 2) px -> (..., N) cell index; points on or past the border go to the edge cell
        (a NaN coordinate to the first cell)."""
        points_2d = np.asarray(points_2d)
        scale, last, axes, dtype = self._cell_constants(
            float(image_size[0]), float(image_size[1]), points_2d.dtype, points_2d.ndim
        )
        # Cell coordinates (x u / width, y v / height) in the points' float type, stored
        # coordinate-major, clamped to [0, u - 1] x [0, v - 1] (fmax sends NaN to 0), then
        # floored by the cast to integers (exact: they are >= 0).
        xy = np.multiply(
            points_2d.transpose(axes), scale, out=np.empty(points_2d.shape[-1:] + points_2d.shape[:-1], dtype)
        )
        np.fmax(xy, 0.0, out=xy)
        np.fmin(xy, last, out=xy)
        col, row = xy.astype(np.int64)
        row *= self.cols
        row += col
        return row

    def _cell_constants(self, width: float, height: float, dtype: np.dtype, ndim: int) -> tuple:
        """cell_index's (2, 1, ...) scale and last cell, its transpose axes and float type, cached."""
        key = (self.cols, self.rows, width, height, dtype, ndim)
        constants = _CELL_CONSTANTS.get(key)
        if constants is None:
            dtype = dtype if dtype.kind == "f" else np.dtype(np.float64)
            shape = (2,) + (1,) * (ndim - 1)
            constants = _CELL_CONSTANTS[key] = (
                np.array([self.cols / width, self.rows / height], dtype).reshape(shape),
                np.array([self.cols - 1, self.rows - 1], dtype).reshape(shape),
                (ndim - 1,) + tuple(range(ndim - 1)),
                dtype,
            )
        return constants


_CELL_CONSTANTS: dict = {}
