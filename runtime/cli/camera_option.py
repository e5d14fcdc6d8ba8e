"""The camera a command serves (`--camera FILE`, or the dataset's own), shared by rectify and evaluate."""

from __future__ import annotations

import argparse
from typing import Optional

from dimenet.runtime.cli.arguments import nonempty_path
from dimenet.runtime.cli.main import CliError
from dimenet.runtime.errors import CameraError
from dimenet.runtime.evaluation.calibration import dataset_camera
from dimenet.runtime.formats.camera_file import read_camera
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.rectify.spec import ModelSpec
from dimenet.runtime.rectify.user_camera import Camera, checked_camera


def add_camera_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--camera",
        type=nonempty_path,
        metavar="FILE",
        help="the camera file: K_c, image size and distortion as OpenCV YAML/XML, ROS camera_info, COLMAP "
        "cameras.txt, Kalibr camchain, mrcal .cameramodel or camera.json; FILE#NAME picks one of several cameras "
        "(default: a device model's own camera when the dataset's image size is its, else K_c calibrated on the "
        "dataset's train split as `dimenet calibrate` does)",
    )


def require_dataset_size(image_size: tuple, frames: Dataset, source: str) -> None:
    """CameraError naming ``source`` unless a camera's image size (width, height) px is the dataset's."""
    size = tuple(int(v) for v in frames.image_size)
    if tuple(image_size) != size:
        raise CameraError(
            f"{source}: the camera is {image_size[0]}x{image_size[1]} px, the dataset's images {size[0]}x{size[1]}"
        )


def dataset_camera_file(camera_file: str, frames: Dataset) -> Camera:
    """The camera file's camera, CameraError unless its image size is the dataset's."""
    camera = read_camera(camera_file)
    require_dataset_size(camera.image_size, frames, camera_file)
    return camera


def served_camera(spec: ModelSpec, frames: Dataset, camera_file: Optional[str], source: str) -> Optional[Camera]:
    """The camera for ``frames``: the file's; None (the model's own) for a device model whose image
    size the dataset has (with the dataset's lens, if it carries one); else K_c from the
    dataset's train split (and its lens). CliError when that is needed
    and the dataset has no train split; CameraError when the file's image size is not the dataset's."""
    if camera_file is not None:
        return dataset_camera_file(camera_file, frames)
    size = tuple(int(v) for v in frames.image_size)
    if spec.generic is None and size == tuple(spec.image_size):  # the model's own camera, through the dataset's lens
        if frames.dist_coeffs is None:
            return None
        return checked_camera(spec.K_c, size, "the dataset's lens", frames.dist_coeffs, frames.dist_K)
    if not frames.frames_in("train").any():
        kind = "a generic model" if spec.generic is not None else f"a {size[0]}x{size[1]} px dataset"
        raise CliError(f"{source}: {kind} needs the camera's K_c: give --camera FILE (the dataset has no train split)")
    return dataset_camera(frames)
