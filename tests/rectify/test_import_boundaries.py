"""The rectifier's import boundary: an app importing it loads no dataset, simulator, ingest,
evaluation or CLI code, and neither torch, onnx, ray nor the training and export packages."""

from __future__ import annotations

import json
import subprocess
import sys

FORBIDDEN = (
    "dimenet.runtime.formats",
    "dimenet.runtime.sim",
    "dimenet.runtime.ingest",
    "dimenet.runtime.evaluation",
    "dimenet.runtime.cli",
    "dimenet.training",
    "dimenet.export",
    "torch",
    "onnx",
    "ray",
)

CODE = """\
import json, sys

forbidden = tuple(sys.argv[1:])


def loaded():
    return sorted(m for m in sys.modules if any(m == p or m.startswith(p + ".") for p in forbidden))


import dimenet.runtime.rectify.rectifier as rectifier

after_import = loaded()
from dimenet.runtime import BatchRectification, Rectification, Rectifier

same = [Rectifier is rectifier.Rectifier, Rectification is rectifier.Rectification,
        BatchRectification is rectifier.BatchRectification]
print(json.dumps({"after_import": after_import, "after_from_import": loaded(), "same": same}))
"""


def test_rectifier_imports_nothing_beyond_geometry_and_rectify():
    done = subprocess.run(
        [sys.executable, "-c", CODE, *FORBIDDEN], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["after_import"] == [], f"importing the rectifier loaded {report['after_import']}"
    assert report["after_from_import"] == [], f"`from dimenet.runtime import ...` loaded {report['after_from_import']}"
    assert report["same"] == [True, True, True]
