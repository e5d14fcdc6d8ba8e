"""OIS camera simulator: hand-held photos of the rig (and of a natural scene) with per-frame K.

Physics (see models_spec/simulator.md for every parameter, value and source):
- pinhole camera at the native 4032x3024 px, lens distortion removed (the paper's assumption);
- focus breathing: the autofocus focuses at the rig distance u (mm, with a small AF error),
  the lens sits at the thin-lens image distance v = f·u / (u - f), so f_px = v / pixel pitch;
- OIS: hand shake is a random 2-axis angle θ (deg, Gaussian per axis); the OIS shifts the lens
  to compensate, moving the principal point by f_px·tan(θ) per axis, clipped at the actuator
  stroke. The OIS state is drawn independently of the camera pose, so K is not predictable
  from the pose; only focus breathing depends (legitimately) on the distance;
- 2D observations are the projection under the true K plus Gaussian corner noise; a board with
  any corner outside the image (less a few px margin) is lost entirely;
- optionally, lens distortion (OpenCV's model, fixed, about the profile's nominal K): the pinhole
  observations are distorted, and the in-image test applies to the distorted pixels;
- optionally, the phone SDK's per-frame K (``sim.platform``), from its own random stream.

``simulate`` returns a ``dimenet-dataset/1`` Dataset: the rig frames in the train/test splits
of the paper's Table 1 and, optionally, natural-scene frames (paper's LEGO test) in test.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict
from typing import Callable, Optional, Union

import numpy as np

from dimenet.runtime import __version__
from dimenet.runtime.errors import InputError, RigError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.formats.rig import Rig, paper_rig, rig_to_dict
from dimenet.runtime.geometry import (
    RIG_VIEW_RATIO,
    camera_centre,
    distort_points,
    facing,
    matrix_to_rvec,
    project,
    spans_3d,
    to_camera,
    undistort_points,
)
from dimenet.runtime.rectify.checks import ImageBounds
from dimenet.runtime.rectify.user_camera import DIST_COEFF_COUNTS, MAX_DIST_COEFF
from dimenet.runtime.sim.image_errors import ImageErrors
from dimenet.runtime.sim.mislabels import MISLABEL_PX, checked_share, mislabel_rng, mislabelled
from dimenet.runtime.sim.platform import platform_matrices, platform_meta, platform_rng
from dimenet.runtime.sim.profiles import DeviceProfile, get_profile
from dimenet.runtime.sim.scene_geometry import NaturalSet, Scene, natural_scene, occluded, rig_scene

GENERATOR = "dimenet.simulator"
# Give up when this many poses in a row fail the visibility rule (the scene cannot fit the view).
MAX_POSE_ATTEMPTS = 1000
# A distorted pixel is the lens's image of a pinhole pixel when undistorting it gives that pixel
# back to this (px): beyond the radius where a distortion polynomial folds back, it does not.
ROUND_TRIP_PX = 1e-3


def focus_breathing_focal_px(profile: DeviceProfile, focus_distance_mm: float) -> float:
    """Focal length (px) when focused at u mm: thin-lens image distance v = f·u/(u - f), over the pitch."""
    f = profile.focal_length_mm
    if not focus_distance_mm > f:
        raise InputError(f"focus distance must exceed the focal length {f} mm, got {focus_distance_mm} mm")
    return profile.focal_px * focus_distance_mm / (focus_distance_mm - f)


def ois_shift_px(theta_deg: np.ndarray, focal_px: float, stroke_deg: float) -> np.ndarray:
    """Principal-point shift (px) of an OIS compensating the shake θ (deg), clipped at the stroke."""
    return focal_px * np.tan(np.radians(np.clip(theta_deg, -stroke_deg, stroke_deg)))


def intrinsics(profile: DeviceProfile, focus_distance_mm: float, theta_deg: np.ndarray) -> np.ndarray:
    """(3, 3) K (px) of one frame: focus breathing sets f, the OIS moves the principal point."""
    f_px = focus_breathing_focal_px(profile, focus_distance_mm)
    cx, cy = profile.centre_px + ois_shift_px(np.asarray(theta_deg), f_px, profile.ois_stroke_deg)
    return np.array([[f_px, 0.0, cx], [0.0, f_px * profile.pixel_aspect, cy], [0.0, 0.0, 1.0]])


def look_at(camera_mm: np.ndarray, target_mm: np.ndarray, roll_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Pose {W}->{C} (rvec rad, tvec mm) of a camera at ``camera_mm`` looking at ``target_mm``.

    Image y points along {W} +y (down) before the roll about the optical axis.
    """
    z = target_mm - camera_mm
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x = x / np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    return matrix_to_rvec(R), -R @ camera_mm


def sample_pose(profile: DeviceProfile, centre_mm: np.ndarray, rng: np.random.Generator):
    """A hand-held pose (rvec, tvec) viewing a scene whose front faces -z of {W}, centred at ``centre_mm``."""
    distance = rng.uniform(*profile.distance_mm)
    yaw, pitch = np.radians(rng.uniform(-profile.view_max_deg, profile.view_max_deg, 2))
    direction = np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), -np.cos(yaw) * np.cos(pitch)])
    aim = centre_mm + np.r_[rng.uniform(-profile.aim_jitter_mm, profile.aim_jitter_mm, 2), 0.0]
    roll = np.radians(rng.uniform(-profile.roll_max_deg, profile.roll_max_deg))
    return look_at(centre_mm + distance * direction, aim, roll)


def in_image(points_px: np.ndarray, profile: DeviceProfile) -> np.ndarray:
    """(N,) whether each pixel lies inside the image, at least the border margin from its edges."""
    m = profile.border_margin_px
    w, h = profile.image_size_px
    x, y = points_px[:, 0], points_px[:, 1]
    return (x >= m) & (x <= w - 1 - m) & (y >= m) & (y <= h - 1 - m)


def lens_image(pinhole_px: np.ndarray, profile: DeviceProfile, dist_coeffs: np.ndarray) -> tuple:
    """The distorted pixels (N, 2) of pinhole pixels (N, 2) px through the lens (``dist_coeffs``
    about the profile's nominal K), and (N,) whether the lens images them there: undistorting
    gives them back within ROUND_TRIP_PX (not so beyond the radius where the model folds back)."""
    K_lens = profile.nominal_K
    image_px = distort_points(pinhole_px, K_lens, dist_coeffs)
    back = undistort_points(image_px, K_lens, dist_coeffs)
    with np.errstate(invalid="ignore"):
        faithful = np.linalg.norm(back - pinhole_px, axis=-1) <= ROUND_TRIP_PX
    return image_px, faithful


def visible(
    scene: Scene,
    profile: DeviceProfile,
    K: np.ndarray,
    rvec: np.ndarray,
    tvec: np.ndarray,
    dist_coeffs: Optional[np.ndarray] = None,
    min_board_corners: Optional[int] = None,
):
    """Pinhole pixels (N, 2) of the scene points and which are seen: in front of the camera,
    facing it, not hidden behind a surface, inside the image (through the lens's distortion,
    ``dist_coeffs`` about the nominal K, when given); a board with any corner unseen is lost entirely,
    or with ``min_board_corners`` (a ChArUco board, detected in part) one with fewer seen than that."""
    camera = camera_centre(rvec, tvec)
    px = project(scene.points, K, rvec, tvec)
    if dist_coeffs is None:
        inside = in_image(px, profile)
    else:
        image_px, faithful = lens_image(px, profile, dist_coeffs)
        inside = in_image(image_px, profile) & faithful
    seen = (
        (to_camera(scene.points, rvec, tvec)[:, 2] > 0)
        & inside
        & facing(scene.points, scene.normals, camera)
        & ~occluded(scene.points, camera, scene.surfaces)
    )
    for g in np.unique(scene.group[scene.group >= 0]):
        board = scene.group == g
        if min_board_corners is None:
            seen[board] = seen[board].all()
        elif np.count_nonzero(seen[board]) < min_board_corners:
            seen[board] = False
    return px, seen


def rig_view_ok(scene: Scene, seen: np.ndarray) -> bool:
    """A rig photo is usable when >= 2 boards are seen and their corners span 3D (K* observable)."""
    return len(np.unique(scene.group[seen])) >= 2 and spans_3d(scene.points[seen], RIG_VIEW_RATIO)


def natural_view_ok(scene: Scene, seen: np.ndarray) -> bool:
    """A natural photo is usable when every labelled building feature is seen."""
    return bool(seen[scene.group < 0].all())


def shoot(
    scene: Scene,
    profile: DeviceProfile,
    rng: np.random.Generator,
    usable: Callable[[Scene, np.ndarray], bool],
    pose: Callable = sample_pose,
    dist_coeffs: Optional[np.ndarray] = None,
    min_board_corners: Optional[int] = None,
):
    """One hand-held photo: OIS and AF state, then poses ``pose(profile, centre, rng)`` until ``usable``
    (seen through the lens distortion ``dist_coeffs`` about the nominal K, when given; boards seen whole,
    or with at least ``min_board_corners`` corners: ``visible``).

    Returns K_true (px), the pose {W}->{C} (rvec, tvec mm), the scene's pinhole pixels (N, 2) and
    which are seen (N,).
    """
    theta_deg = rng.normal(0.0, profile.shake_sigma_deg, 2)
    af_error = rng.normal(0.0, profile.af_error_rel)
    for _ in range(MAX_POSE_ATTEMPTS):
        rvec, tvec = pose(profile, scene.centre, rng)
        focus_mm = to_camera(scene.centre[None], rvec, tvec)[0, 2] * (1.0 + af_error)
        K = intrinsics(profile, focus_mm, theta_deg)
        px, seen = visible(scene, profile, K, rvec, tvec, dist_coeffs, min_board_corners)
        if usable(scene, seen):
            return K, rvec, tvec, px, seen
    raise RigError(
        f"no hand-held pose out of {MAX_POSE_ATTEMPTS} gives a usable view of the scene "
        f"with profile {profile.name!r}: does the rig fit the camera's view?"
    )


def _observed(px, seen, noise, scene: Scene, usable, profile: DeviceProfile, errors, rng) -> tuple:
    """One frame's observations: (seen (N,), points (N, 2) px, NaN where unseen) from the pinhole pixels px (N, 2)
    px of the scene's points, which are seen, and the noise (S, 2) px of the S seen ones. With ``errors``
    (``ImageErrors``, drawn from ``rng``) through the residual lens, with the boards' detection errors, and
    without the corners a ChArUco camera misses (unless the view would no longer be ``usable``)."""
    out = np.full(px.shape, np.nan)
    if errors is None:
        out[seen] = px[seen] + noise
        return seen, out
    out[seen] = errors.detection(errors.lens(px, profile)[seen] + noise, scene.group[seen], rng)
    kept = seen & ~errors.missed(seen, scene.group, rng)
    return (kept, np.where(kept[:, None], out, np.nan)) if usable(scene, kept) else (seen, out)


def label_noise_px(points_camera_mm: np.ndarray, K: np.ndarray, label_sigma_px: float, model_sigma_mm: float) -> float:
    """The std per image axis (px) of labels of 2D noise ``label_sigma_px`` on 3D points (N, 3) mm in {C} that
    are off by ``model_sigma_mm`` per axis, RMS over the points: a point's 3D error moves its pixel by f / Z (dX - x
    dZ) per axis (x = X / Z), of variance (f sigma / Z)^2 (1 + x^2)."""
    x = points_camera_mm[:, :2] / points_camera_mm[:, 2:]
    f = np.array([K[0, 0], K[1, 1]])
    moved = (f * model_sigma_mm / points_camera_mm[:, 2:]) ** 2 * (1.0 + x**2)
    return float(np.sqrt(label_sigma_px**2 + moved.mean())) if len(x) else float(label_sigma_px)


def checked_dist_coeffs(dist_coeffs: Optional[Sequence[float]]) -> Optional[np.ndarray]:
    """OpenCV distortion coefficients -> (n,) float64, n in DIST_COEFF_COUNTS, finite, of magnitude
    <= MAX_DIST_COEFF; None stays None. InputError otherwise."""
    if dist_coeffs is None:
        return None
    counts = "/".join(str(n) for n in DIST_COEFF_COUNTS)
    try:
        coeffs = np.asarray(dist_coeffs, dtype=np.float64)
    except (TypeError, ValueError):
        coeffs = np.full(0, np.nan)
    if coeffs.ndim != 1 or coeffs.size not in DIST_COEFF_COUNTS:
        raise InputError(f"dist_coeffs must be {counts} numbers (OpenCV's k1, k2, p1, p2, ...), got {dist_coeffs!r}")
    if not (np.all(np.isfinite(coeffs)) and np.all(np.abs(coeffs) <= MAX_DIST_COEFF)):
        raise InputError(f"dist_coeffs must be finite, of magnitude <= {MAX_DIST_COEFF:g}, got {coeffs.tolist()}")
    return coeffs


def simulate(
    profile: Union[str, DeviceProfile],
    *,
    seed: int = 0,
    natural_frames: int = 0,
    planar_frames: int = 0,
    rig: Optional[Rig] = None,
    dist_coeffs: Optional[Sequence[float]] = None,
    platform_k: bool = False,
    rig_offsets_mm: Optional[np.ndarray] = None,
    natural: Optional[NaturalSet] = None,
    image_errors: Optional[ImageErrors] = None,
    mislabel_share: float = 0.0,
) -> Dataset:
    """A simulated dataset: the profile's train/test rig frames, then ``natural_frames`` natural
    test frames, then ``planar_frames`` planar test frames.

    A planar frame is a rig photo (>= 2 boards seen, so K* stays observable from all its valid
    points) whose inference points are the corners of one of its boards, drawn at random: from
    one planar view K is not fully observable. Deterministic per seed; rig frames depend on
    neither count, natural frames not on ``planar_frames``. 2D points in px, 3D points in mm
    in the frame's {W} (the rig frame, or the natural scene's frame).

    ``dist_coeffs`` (OpenCV's 4/5/8/12/14 coefficients about the profile's nominal K): the noisy
    pinhole observations are distorted (``distort_points(x, nominal K, dist_coeffs)``) and a point
    is in the image when its distorted pixel is; the dataset carries ``dist_coeffs`` and ``dist_K``.
    ``platform_k``: add the SDK's K per frame (``sim.platform``, its own random stream; meta
    ``platform_k`` states the model). Without either, the dataset is as before, array for array.
    ``rig_offsets_mm`` (P, 3) mm in {W}: the built rig's corners lie there off the rig's points (``scenes.
    build_errors_mm``); the camera images the built rig (seen where the rig is), the dataset's 3D points stay the rig's.
    ``natural``: the natural frames' scene, noise and 3D error (``sim.natural.random_natural``; None: the paper's
    LEGO buildings beside the rig's first board, with the profile's label and model noise).
    ``image_errors``: the camera's residual lens, corner bias, JPEG noise and ChArUco detection (``sim.image_errors``,
    its own generator); the border margin grows by their reach, and meta ``image_errors`` records them.
    ``mislabel_share``: that share of the natural frames' labels is grossly mislabelled (``sim.mislabels``, its own
    generator; meta ``mislabels``); 0 changes nothing.
    """
    profile = get_profile(profile) if isinstance(profile, str) else profile
    for name, value in (("seed", seed), ("natural_frames", natural_frames), ("planar_frames", planar_frames)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
            raise InputError(f"{name} must be an integer >= 0, got {value!r}")
    dist = checked_dist_coeffs(dist_coeffs)
    mislabel_share = checked_share(mislabel_share)
    mrng = mislabel_rng(seed) if mislabel_share else None
    rig = paper_rig() if rig is None else rig
    rng = np.random.default_rng(seed)
    errors = image_errors
    if errors is not None:
        profile = errors.margined(profile)
    erng = None if errors is None else np.random.default_rng(errors.seed)
    lens_and_boards = {"dist_coeffs": dist, "min_board_corners": None if errors is None else errors.min_board_corners}
    rig_set = rig_scene(rig)
    built = None  # the built rig's corners (P, 3) mm, imaged where the rig is seen (a few mm change no visibility)
    if rig_offsets_mm is not None:
        offsets = np.asarray(rig_offsets_mm, dtype=np.float64)
        if offsets.shape != rig_set.points.shape or not np.all(np.isfinite(offsets)):
            raise InputError(f"rig_offsets_mm must be finite, one (x, y, z) per rig point {rig_set.points.shape}")
        built = rig_set.points + offsets
    if natural is None:
        nature, usable = natural_scene(rig.boards[0]), natural_view_ok
        label_sigma_px, model_sigma_mm = profile.label_sigma_px, profile.model_sigma_mm
    else:
        nature, usable = natural.scene, natural.view_ok
        label_sigma_px, model_sigma_mm = natural.label_sigma_px, natural.model_sigma_mm
    n_rig = profile.n_train + profile.n_test
    n_shot = n_rig + natural_frames
    F, P = n_shot + planar_frames, max(len(rig_set.points), len(nature.points))
    p2, p3 = np.full((F, P, 2), np.nan), np.full((F, P, 3), np.nan)
    valid, infer = np.zeros((F, P), bool), np.zeros((F, P), bool)
    K_true = np.zeros((F, 3, 3))
    label_noise = np.full(F, float(profile.corner_sigma_px))  # rig and planar frames: the corners' noise
    for k in range(n_rig):
        K_true[k], rvec, tvec, px, seen = shoot(rig_set, profile, rng, rig_view_ok, **lens_and_boards)
        px = px if built is None else project(built, K_true[k], rvec, tvec)
        n = len(px)
        noise = rng.normal(0.0, profile.corner_sigma_px, (int(seen.sum()), 2))
        seen, p2[k, :n] = _observed(px, seen, noise, rig_set, rig_view_ok, profile, errors, erng)
        p3[k, :n][seen] = rig_set.points[seen]
        valid[k, :n], infer[k, :n] = seen, seen
    building = nature.group < 0
    model_points = nature.points + building[:, None] * rng.normal(0.0, model_sigma_mm, nature.points.shape)
    noise_px = np.where(building, label_sigma_px, profile.corner_sigma_px)[:, None]
    for k in range(n_rig, n_shot):
        K_true[k], rvec, tvec, px, seen = shoot(nature, profile, rng, usable, **lens_and_boards)
        n = len(px)
        noise = (rng.normal(0.0, 1.0, px.shape) * noise_px)[seen]
        seen, p2[k, :n] = _observed(px, seen, noise, nature, usable, profile, errors, erng)
        if mrng is not None:
            p2[k, :n] = mislabelled(p2[k, :n], seen & building, mislabel_share, profile.image_size_px, mrng)[0]
        p3[k, :n][seen] = model_points[seen]
        valid[k, :n], infer[k, :n] = seen, seen & building
        labelled = to_camera(nature.points[seen & building], rvec, tvec)
        label_noise[k] = label_noise_px(labelled, K_true[k], label_sigma_px, model_sigma_mm)
    for k in range(n_shot, F):
        K_true[k], rvec, tvec, px, seen = shoot(rig_set, profile, rng, rig_view_ok, **lens_and_boards)
        px = px if built is None else project(built, K_true[k], rvec, tvec)
        n = len(px)
        noise = rng.normal(0.0, profile.corner_sigma_px, (int(seen.sum()), 2))
        seen, p2[k, :n] = _observed(px, seen, noise, rig_set, rig_view_ok, profile, errors, erng)
        p3[k, :n][seen] = rig_set.points[seen]
        board = rng.choice(np.unique(rig_set.group[seen]))
        valid[k, :n], infer[k, :n] = seen, seen & (rig_set.group == board)
    meta = {
        "generator": GENERATOR,
        "version": __version__,
        "profile": profile.name,
        "seed": int(seed),
        "natural_frames": int(natural_frames),
        "planar_frames": int(planar_frames),
        "units": {"2d": "px", "3d": "mm"},
        "device": asdict(profile),
        "rig": rig_to_dict(rig),
        "natural_board": rig.boards[0].name,
    }
    if natural is not None:
        meta["natural_scene"] = {
            "kind": natural.kind,
            "features": int(np.count_nonzero(building)),
            "label_sigma_px": label_sigma_px,
            "model_sigma_mm": model_sigma_mm,
        }
    if errors is not None:
        meta["image_errors"] = asdict(errors)
    if mislabel_share:
        meta["mislabels"] = {"share": mislabel_share, "px": list(MISLABEL_PX)}
    if dist is not None:
        p2 = distort_points(p2, profile.nominal_K, dist)
    # A label or corner the noise carries off the image is on its border, as a click or a detection is.
    image = ImageBounds(profile.image_size_px)
    p2 = np.clip(p2, image.low, image.high)
    if platform_k:
        meta["platform_k"] = platform_meta(profile)
    return Dataset(
        image_size=np.array(profile.image_size_px, np.int64),
        points_2d=p2,
        points_3d=p3,
        valid=valid,
        infer_mask=infer,
        split=np.array(["train"] * profile.n_train + ["test"] * (profile.n_test + natural_frames + planar_frames)),
        scene=np.array(["rig"] * n_rig + ["natural"] * natural_frames + ["planar"] * planar_frames),
        meta=meta,
        K_true=K_true,
        frame_id=np.array([f"{profile.name}-{k:04d}" for k in range(F)]),
        K_platform=platform_matrices(K_true, profile, platform_rng(seed)) if platform_k else None,
        label_noise_px=label_noise,
        dist_coeffs=dist,
        dist_K=None if dist is None else profile.nominal_K,
    )
