"""`dimenet reproduce`: the paper's Tables 2-5 on the three simulated device profiles, and
the baselines beyond the paper.

Trains one model per device (8x6, features A, full epochs), plus the ablation models on
galaxy-s8 (features B-E; grids 16x12 and 12x9) with fewer epochs, evaluates every case of
the paper on the test split, then every method (kc, self, dimenet, map, oracle) on every
Table 4/5 case and on planar frames, and writes REPRODUCTION.md (ours beside the paper's
numbers), results.json and three plots into OUT_DIR.

paper.py holds the set-up and the paper's numbers, tables.py the run (`run`), report.py the
markdown report and the plots.
"""

from ..config import ReproduceConfig
from .report import report
from .tables import run

__all__ = ["ReproduceConfig", "report", "run"]
