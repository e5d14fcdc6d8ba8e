"""dimenet.runtime: the torch-free foundation of DIME-Net.

``from dimenet.runtime import Rectifier`` is all an app needs (see README). The rectifier and
its results load on first use, so ``import dimenet.runtime`` (the CLI, the errors) stays light.
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
    RigError,
)

__version__ = "0.1.0"
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
    "RigError",
    *_RECTIFY,
    "__version__",
]


def __getattr__(name: str):
    if name in _RECTIFY:
        from dimenet.runtime.rectify import rectifier

        return getattr(rectifier, name)
    raise AttributeError(f"module 'dimenet.runtime' has no attribute {name!r}")
