"""The camera a ``Rectifier`` serves, in the model's pixels (``ModelCamera``): built once per rectifier,
read by every stage (``rectify.stages``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from dimenet.runtime.geometry import k_params, mean_distorted_error, undistort_points
from dimenet.runtime.rectify.checks import STRUCTURE_PX, ImageBounds, check_undistorted
from dimenet.runtime.rectify.spec import ModelSpec, ServedCamera
from dimenet.runtime.rectify.user_camera import Camera, PixelMap


@dataclass(frozen=True, eq=False)
class ModelCamera:
    """The camera a ``Rectifier`` serves, built once: ``spec`` the model's spec in model px (its
    K_c, image size and K_bounds those of the camera mapped onto the model's pixels); K_c (3, 3),
    k_c (4,) and fx_c model px, with ``k_c_list`` and ``K_bounds_list`` as floats for the frame
    path; ``image`` the user's image (the input rule's bounds); ``pixels`` the map from the user's
    pixels onto the model's (None: the same) and ``user_px`` user px per model px; the lens
    (``lens_K`` (3, 3) px, ``dist_coeffs``; None without one); ``K_c_user`` (3, 3) the prior in the
    user's pixels (read-only); ``structure_px`` the structure rule's limit (model px);
    ``population_cov`` (4, 4) model px^2 and ``population_cov_user`` user px^2 the K_cov of a frame
    that keeps K_c (None: the model has none)."""

    spec: ModelSpec
    K_c: np.ndarray
    k_c: np.ndarray
    k_c_list: list
    fx_c: float
    K_bounds_list: list
    image: ImageBounds
    pixels: Optional[PixelMap]
    user_px: float
    lens_K: Optional[np.ndarray]
    dist_coeffs: Optional[np.ndarray]
    K_c_user: np.ndarray
    structure_px: float
    population_cov: Optional[np.ndarray]
    population_cov_user: Optional[np.ndarray]

    @classmethod
    def build(cls, served: ServedCamera, camera: Optional[Camera]) -> ModelCamera:
        spec = served.model
        k_c = k_params(spec.K_c)
        K_c_user = served.K_c.copy()
        K_c_user.setflags(write=False)
        population = None if spec.uncertainty is None else spec.uncertainty.population_covariance()
        population_user = population
        if population is not None and served.pixels is not None:
            population_user = served.pixels.covariance_to_user(population)
        structure_px = spec.residual_structure_px
        return cls(
            spec=spec,
            K_c=np.ascontiguousarray(spec.K_c, dtype=np.float64),
            k_c=k_c,
            k_c_list=k_c.tolist(),
            fx_c=float(k_c[0]),
            K_bounds_list=spec.K_bounds.tolist(),
            image=ImageBounds(served.image_size),
            pixels=served.pixels,
            user_px=1.0 if served.pixels is None else 1.0 / served.pixels.scale,
            lens_K=None if camera is None else camera.lens_K,
            dist_coeffs=None if camera is None else camera.dist_coeffs,
            K_c_user=K_c_user,
            structure_px=STRUCTURE_PX if structure_px is None else structure_px,
            population_cov=population,
            population_cov_user=population_user,
        )

    def to_model(self, points_2d: np.ndarray, valid=True) -> np.ndarray:
        """(N, 2) or (B, N, 2) points in the user's pixels (distorted by the lens) -> the model's pinhole
        pixels; InputError naming a ``valid`` point whose undistortion is not finite."""
        pinhole = points_2d
        if self.dist_coeffs is not None:
            pinhole = undistort_points(points_2d, self.lens_K, self.dist_coeffs)
            check_undistorted(pinhole, points_2d, valid)
        return pinhole if self.pixels is None else self.pixels.points_to_model(pinhole)

    def user_k(self, k) -> np.ndarray:
        """(4,) (fx, fy, cx, cy) model px -> the user's px (for the reasons)."""
        return np.asarray(k) if self.pixels is None else self.pixels.k_to_user(k)

    def image_errors(self, p2_image, p3, valid, K, rvecs, tvecs) -> np.ndarray:
        """Mean errors (px) in the lens's distorted image of (B, N) points (the user's) for each of
        the candidate (K, pose) pairs: K (M, 3, 3) px, rvecs and tvecs M arrays (B, 3) or (3,) -> (M, B)."""
        return np.stack(
            [
                mean_distorted_error(
                    p2_image,
                    p3,
                    valid,
                    K[m],
                    np.reshape(rvecs[m], (-1, 3)),
                    np.reshape(tvecs[m], (-1, 3)),
                    self.lens_K,
                    self.dist_coeffs,
                )
                for m in range(len(K))
            ]
        )
