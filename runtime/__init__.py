"""dimenet.runtime: the torch-free foundation (geometry, dataset I/O, calibration, metrics, CLI core)."""
from .errors import CalibrationError, DatasetError, DimenetError, InputError, ModelError, RigError

__version__ = "0.1.0"
__all__ = ["CalibrationError", "DatasetError", "DimenetError", "InputError", "ModelError", "RigError", "__version__"]
