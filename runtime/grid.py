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

from .errors import InputError


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

    @classmethod
    def parse(cls, text: str) -> "Grid":
        """'8x6' -> Grid(cols=8, rows=6)."""
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
        if not m:
            raise InputError(f"grid must look like '8x6' (columns x rows), got {text!r}")
        return cls(int(m.group(1)), int(m.group(2)))

    def cell_index(self, points_2d: np.ndarray, image_size) -> np.ndarray:
        """(..., N, 2) px -> (..., N) cell index; points on or past the border go to the edge cell."""
        width, height = float(image_size[0]), float(image_size[1])
        col = np.clip(np.floor(points_2d[..., 0] * (self.cols / width)), 0, self.cols - 1)
        row = np.clip(np.floor(points_2d[..., 1] * (self.rows / height)), 0, self.rows - 1)
        col = np.nan_to_num(col).astype(np.int64)
        row = np.nan_to_num(row).astype(np.int64)
        return row * self.cols + col
