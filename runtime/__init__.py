"""dimenet.runtime: the torch-free foundation of DIME-Net.

``from dimenet.runtime import Rectifier`` is all an app needs (see README). The rectifier and
its results load on first use, so ``import dimenet.runtime`` (the CLI, the errors) stays light;
``__version__`` too: it is the installed distribution's (pyproject.toml holds the one version).
"""

from dimenet.runtime.errors import (
    CalibrationError,
    CameraError,
    DatasetError,
    DimenetError,
    IdentificationError,
    IngestError,
    InputError,
    LabelsError,
    ModelError,
    PhotoError,
    PointsError,
    RigError,
)

_RECTIFY = ("Rectifier", "Rectification", "BatchRectification")
__all__ = [
    "CalibrationError",
    "CameraError",
    "DatasetError",
    "DimenetError",
    "IdentificationError",
    "IngestError",
    "InputError",
    "LabelsError",
    "ModelError",
    "PhotoError",
    "PointsError",
    "RigError",
    *_RECTIFY,
    "__version__",
]


def __getattr__(name: str):
    if name in _RECTIFY:
        from dimenet.runtime.rectify import rectifier

        return getattr(rectifier, name)
    if name == "__version__":
        from importlib.metadata import version

        return version("dimenet-runtime")
    raise AttributeError(f"module 'dimenet.runtime' has no attribute {name!r}")
