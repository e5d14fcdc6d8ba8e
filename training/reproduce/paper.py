"""The set-up of `dimenet reproduce` (devices, points, eta, grids, feature variants, noise) and
the paper's numbers it is compared with; shared by the tables (tables.py) and the report (report.py)."""

from __future__ import annotations

DEVICES = ("galaxy-s8", "iphone-12-pro", "ipad-mini-6")
NATURAL_FRAMES = 34
PLANAR_FRAMES = 40  # galaxy-s8 test frames whose K is inferred from one board (not in the paper)
POINTS = (320, 256, 192, 128, 64)
ETAS = (0.0, 0.2, 0.4, 0.6, 0.8)
GRIDS = ("16x12", "12x9", "8x6")
VARIANTS = ("A", "B", "C", "D", "E")

# The paper's numbers (Avg errors in px, rho and gamma in %).
PAPER_T2 = {  # grid -> [(gamma, Avg(e)) per eta]
    "16x12": [(64.5, 0.73), (52.1, 0.87), (38.9, 1.29), (26.6, 1.77), (13.4, 2.47)],
    "12x9": [(78.6, 0.75), (62.6, 0.97), (46.0, 1.33), (30.5, 1.88), (14.8, 2.49)],
    "8x6": [(96.4, 0.68), (79.3, 0.92), (57.7, 1.45), (36.6, 2.05), (19.7, 2.52)],
}
PAPER_T3 = {"A": 0.68, "B": 0.78, "C": 0.78, "D": 0.75, "E": 2.58}
# fmt: off
PAPER_T4 = {  # noise -> points -> (Avg(e_c), Avg(e), Avg(e*), rho)
    "clean": {320: (3.44, 0.68, 0.45, 92.2), 256: (3.34, 0.67, 0.45, 92.5), 192: (3.43, 0.69, 0.45, 92.2),
              128: (3.45, 0.85, 0.46, 87.0), 64: (3.40, 1.35, 0.45, 69.8)},
    "noisy": {320: (5.28, 3.90, 3.86, 97.2), 256: (5.27, 3.89, 3.82, 95.0), 192: (5.28, 3.88, 3.83, 96.8),
              128: (5.31, 3.84, 3.81, 97.7), 64: (5.56, 4.01, 3.81, 88.2)},
}
# fmt: on
PAPER_T5 = {
    "galaxy-s8": (3.44, 0.68, 0.45, 91.7),
    "iphone-12-pro": (2.36, 0.61, 0.46, 92.3),
    "ipad-mini-6": (1.61, 0.36, 0.32, 96.8),
    "galaxy-s8 (N)": (4.26, 3.74, 3.45, 64.0),
}
NOISE_2D_PX, NOISE_3D_MM = 3.0, 0.1
