"""Typed errors. Every one is a ``ValueError`` so callers can catch bad input broadly."""

from __future__ import annotations


class DimenetError(ValueError):
    """Base class of every error dimenet raises for bad input or bad data."""


class DatasetError(DimenetError):
    """A dataset file does not conform to ``dimenet-dataset/1`` (the message names the key)."""


class InputError(DimenetError):
    """Correspondences handed to the runtime are unusable (shape, count, NaN, degenerate, ...)."""


class ModelError(DimenetError):
    """A model file is missing, corrupt, foreign or of an unsupported spec version."""


class CalibrationError(DimenetError):
    """A calibration problem is ill-posed (too few or coplanar points) or did not converge."""


class RigError(DimenetError):
    """A rig description does not conform to ``dimenet-rig/1``."""


class CameraError(DimenetError):
    """A camera (K_c and image size) file or value does not conform; the message names the file and the field."""


class PhotoError(DimenetError):
    """A photo cannot be read or decoded, or its format is not supported (the message names the file)."""


class IdentificationError(DimenetError):
    """The boards found in a photo cannot be told apart with confidence."""


class LabelsError(DimenetError):
    """A natural-object CSV (OBJECT.csv or LABELS.csv) does not conform (the message names file and line)."""


class IngestError(DimenetError):
    """Photos cannot become a dataset (duplicate names, no usable photo, ...)."""


class PointsError(DimenetError):
    """A points file (CSV or JSON Lines) does not conform; the message names the file and line."""
