"""A randomised camera family: many OIS cameras, one ``DeviceProfile`` each, for training one
generic (scale-free) network across cameras (models_spec/simulator.md, "Camera family").

Every camera is drawn by a pure function of a seeded generator: an image size from ``SIZES_PX``
(cycled in a seeded random order, so every family of >= len(SIZES_PX) cameras holds every size),
a horizontal field of view, a lens focal length, pixel aspect, principal-point offset, OIS
stroke and hand shake, corner noise; the label noise, border margin and rig distances follow
from the resolution and the field of view. Cameras close to the paper's three profiles are
re-drawn (``near_paper_profile``), so those stay zero-shot tests of a family-trained network.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Optional

import numpy as np

from dimenet.runtime.errors import InputError
from dimenet.runtime.formats.dataset import Dataset
from dimenet.runtime.sim.image_errors import draw_image_errors
from dimenet.runtime.sim.natural import random_natural
from dimenet.runtime.sim.profiles import PROFILES, DeviceProfile
from dimenet.runtime.sim.scenes import FILL, build_errors_mm, extent_mm, framed, random_rig
from dimenet.runtime.sim.simulator import simulate

# Image sizes (width, height) px: 16:9 and 4:3 stream and photo sizes, 1280 to 8000 px wide.
# fmt: off
SIZES_PX = (
    (1280, 720), (1920, 1080), (2560, 1440), (3840, 2160), (7680, 4320),                   # 16:9
    (1280, 960), (1600, 1200), (2048, 1536), (3264, 2448), (4000, 3000), (4608, 3456),     # 4:3
    (6000, 4500), (8000, 6000),
)
# fmt: on
HFOV_DEG = (55.0, 85.0)  # horizontal field of view, uniform
FOCAL_LENGTH_MM = (2.5, 7.0)  # lens focal length at infinity focus, uniform (drives focus breathing)
PIXEL_ASPECT_TOLERANCE = 0.01  # fy / fx uniform in 1 +- this
CENTRE_OFFSET_WIDTH_FRACTION = 0.02  # optical centre offset per axis, uniform in +- this x the width (px)
SHAKE_SIGMA_DEG = (0.4, 1.6)  # hand-shake std per axis, uniform (paper profiles: 0.5 .. 1.4)
STROKE_OVER_SHAKE = (1.05, 1.6)  # OIS stroke / shake std, uniform (paper profiles: 1.07 .. 1.6) ...
OIS_STROKE_DEG = (0.7, 1.8)  # ... then clipped to this range (paper profiles: 0.8 .. 1.5)
CORNER_SIGMA_PX = (0.1, 0.6)  # corner detection noise std per axis, uniform (px of that camera)
FAMILY_FRAMES = (80, 20)  # rig frames (train, test) per camera
SCENES = ("paper", "random")  # what a camera sees: the paper's rig at its distances, or a rig of its own (sim.scenes)
OIS_OFF_SHARE = 0.2  # with random scenes, this share of cameras has no OIS (front cameras, OIS disabled) ...
VIDEO_SHARE = 0.15  # ... and this share of those with OIS is a video camera with a larger stroke ...
VIDEO_STROKE_DEG = (1.8, 3.0)  # ... uniform, its shake std the stroke over STROKE_OVER_SHAKE

# The paper's scale: label noise and border margin were set for a 4032 px wide camera, the rig
# distances for the galaxy-s8's field of view.
REFERENCE_WIDTH_PX = 4032
REFERENCE_HFOV_DEG = 67.2  # galaxy-s8: 2 atan(2016 / 3035.7)
REFERENCE = PROFILES["galaxy-s8"]
MIN_BORDER_MARGIN_PX = 2.0
BORDER_MARGIN_CORNER_SIGMAS = 5.0  # and at least 5 corner-noise std, so noisy corners stay inside the image

# Exclusion of the paper's cameras and their neighbours (near_paper_profile).
NEAR_WIDTH_REL = 0.10  # image width within 10 % of the paper's 4032 px ...
NEAR_ASPECT_REL = 0.01  # ... with a 4:3 aspect (within 1 %) ...
NEAR_HFOV_DEG = 4.0  # ... and a horizontal field of view within 4 deg of a paper profile's
MAX_DRAWS = 1000  # re-draws of one camera before giving up (never reached: the excluded band is narrow)
MAX_FAMILY = 1000  # cameras in one family


def hfov_deg(profile: DeviceProfile) -> float:
    """Nominal horizontal field of view (deg) at infinity focus: 2 atan((w / 2) / f_px)."""
    return math.degrees(2.0 * math.atan(profile.image_size_px[0] / 2.0 / profile.focal_px))


def near_paper_profile(profile: DeviceProfile) -> bool:
    """Whether ``profile`` is one of the paper's cameras or a close neighbour: image width within
    10 % of 4032 px at a 4:3 aspect, and horizontal field of view within 4 deg of a paper profile's."""
    width_px, height_px = profile.image_size_px
    same_size = abs(width_px / REFERENCE_WIDTH_PX - 1.0) <= NEAR_WIDTH_REL
    four_three = abs(width_px / height_px / (4.0 / 3.0) - 1.0) <= NEAR_ASPECT_REL
    same_fov = any(abs(hfov_deg(profile) - hfov_deg(p)) <= NEAR_HFOV_DEG for p in PROFILES.values())
    return bool(same_size and four_three and same_fov)


def _check_frames(frames: tuple[int, int]) -> tuple[int, int]:
    ok = len(frames) == 2 and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in frames)
    if not (ok and min(frames) >= 0 and sum(frames) >= 1):
        raise InputError(f"frames must be (train, test) rig frames, integers >= 0, at least 1 in all, got {frames!r}")
    return int(frames[0]), int(frames[1])


def _draw_profile(
    rng: np.random.Generator, name: str, image_size_px: tuple[int, int], frames: tuple[int, int]
) -> DeviceProfile:
    """One camera of the given size, every parameter drawn once (no exclusion)."""
    width_px = image_size_px[0]
    hfov_rad = math.radians(rng.uniform(*HFOV_DEG))
    focal_px = width_px / 2.0 / math.tan(hfov_rad / 2.0)
    focal_length_mm = rng.uniform(*FOCAL_LENGTH_MM)
    shake_sigma_deg = rng.uniform(*SHAKE_SIGMA_DEG)
    stroke_deg = float(np.clip(shake_sigma_deg * rng.uniform(*STROKE_OVER_SHAKE), *OIS_STROKE_DEG))
    distance_scale = math.tan(math.radians(REFERENCE_HFOV_DEG) / 2.0) / math.tan(hfov_rad / 2.0)
    resolution_scale = width_px / REFERENCE_WIDTH_PX
    corner_sigma_px = rng.uniform(*CORNER_SIGMA_PX)
    border_margin_px = max(
        MIN_BORDER_MARGIN_PX,
        REFERENCE.border_margin_px * resolution_scale,
        BORDER_MARGIN_CORNER_SIGMAS * corner_sigma_px,
    )
    return DeviceProfile(
        name=name,
        focal_length_mm=focal_length_mm,
        pixel_pitch_um=focal_length_mm * 1e3 / focal_px,
        shake_sigma_deg=shake_sigma_deg,
        ois_stroke_deg=stroke_deg,
        corner_sigma_px=corner_sigma_px,
        n_train=frames[0],
        n_test=frames[1],
        image_size_px=(int(image_size_px[0]), int(image_size_px[1])),
        pixel_aspect=1.0 + rng.uniform(-PIXEL_ASPECT_TOLERANCE, PIXEL_ASPECT_TOLERANCE),
        centre_offset_px=tuple(float(v) for v in rng.uniform(-1.0, 1.0, 2) * CENTRE_OFFSET_WIDTH_FRACTION * width_px),
        label_sigma_px=REFERENCE.label_sigma_px * resolution_scale,
        distance_mm=(REFERENCE.distance_mm[0] * distance_scale, REFERENCE.distance_mm[1] * distance_scale),
        aim_jitter_mm=REFERENCE.aim_jitter_mm * distance_scale,
        border_margin_px=border_margin_px,
    )


def family_profile(
    rng: np.random.Generator,
    name: str,
    image_size_px: Optional[tuple[int, int]] = None,
    frames: tuple[int, int] = FAMILY_FRAMES,
) -> DeviceProfile:
    """One random camera named ``name``: of ``image_size_px`` (width, height px; default a size of
    ``SIZES_PX`` drawn from ``rng``) with ``frames`` = (train, test) rig frames. Draws again while
    the camera is near a paper profile (``near_paper_profile``). Deterministic given ``rng``'s state."""
    frames = _check_frames(frames)
    if image_size_px is None:
        image_size_px = SIZES_PX[int(rng.integers(len(SIZES_PX)))]
    for _ in range(MAX_DRAWS):
        profile = _draw_profile(rng, name, image_size_px, frames)
        if not near_paper_profile(profile):
            return profile
    raise InputError(f"no camera of size {image_size_px} away from the paper profiles in {MAX_DRAWS} draws")


def _check_family(n: int, seed: int) -> None:
    for label, value, low, high in (("n", n, 1, MAX_FAMILY), ("seed", seed, 0, None)):
        integer = isinstance(value, (int, np.integer)) and not isinstance(value, bool)
        if not (integer and value >= low and (high is None or value <= high)):
            bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
            raise InputError(f"{label} must be an integer {bound}, got {value!r}")


def _stream(seed: int, *key: int) -> np.random.Generator:
    """An independent generator for one part of the family (sizes, camera i, ...), by key."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=key))


def family_sizes(n: int, seed: int) -> list[tuple[int, int]]:
    """Image sizes (width, height px) of the family's ``n`` cameras: ``SIZES_PX`` block after block,
    each block in a fresh seeded random order (so any ``len(SIZES_PX)`` cameras in a row hold each
    size once per block). The first m sizes do not depend on ``n``."""
    _check_family(n, seed)
    rng = _stream(seed, 0)
    blocks = -(-n // len(SIZES_PX))
    order = np.concatenate([rng.permutation(len(SIZES_PX)) for _ in range(blocks)])[:n]
    return [SIZES_PX[i] for i in order]


def camera_name(seed: int, index: int) -> str:
    """The name of camera ``index`` of the family of ``seed``: ``family-s<seed>-<index:03d>``."""
    return f"family-s{seed}-{index:03d}"


def camera_seed(seed: int, index: int) -> int:
    """The simulator seed (0 .. 2**32 - 1) of camera ``index``'s frames: independent draws per camera."""
    return int(np.random.SeedSequence(int(seed), spawn_key=(2, index)).generate_state(1)[0])


def has_ois(seed: int, index: int) -> bool:
    """Whether camera ``index`` of a random-scene family of ``seed`` keeps its OIS (OIS_OFF_SHARE of them do not)."""
    return bool(_stream(seed, 4, index).uniform() >= OIS_OFF_SHARE)


def ois_camera(profile: DeviceProfile, seed: int, index: int) -> DeviceProfile:
    """Camera ``index`` of a random-scene family of ``seed`` as its OIS makes it: no OIS (stroke 0) on
    OIS_OFF_SHARE of the cameras (``has_ois``); on VIDEO_SHARE of the others (their own stream) a video camera,
    stroke U(VIDEO_STROKE_DEG) and hand shake the stroke over U(STROKE_OVER_SHAKE); else ``profile``."""
    if not has_ois(seed, index):
        return replace(profile, ois_stroke_deg=0.0)
    rng = _stream(seed, 8, index)
    if rng.uniform() >= VIDEO_SHARE:
        return profile
    stroke_deg = rng.uniform(*VIDEO_STROKE_DEG)
    return replace(profile, ois_stroke_deg=stroke_deg, shake_sigma_deg=stroke_deg / rng.uniform(*STROKE_OVER_SHAKE))


def family_profiles(n: int, seed: int, frames: tuple[int, int] = FAMILY_FRAMES) -> list[DeviceProfile]:
    """The ``n`` cameras (1 .. 1000) of the family of ``seed``, each with ``frames`` = (train, test)
    rig frames. Deterministic per seed; camera i does not depend on ``n`` (a family's first m
    cameras are the family of m)."""
    frames = _check_frames(frames)
    return [
        family_profile(_stream(seed, 1, i), camera_name(seed, i), size, frames)
        for i, size in enumerate(family_sizes(n, seed))
    ]


def simulate_family(
    n: int,
    seed: int,
    *,
    natural_frames: int = 0,
    planar_frames: int = 0,
    frames: tuple[int, int] = FAMILY_FRAMES,
    dist_coeffs: Optional[Sequence[float]] = None,
    platform_k: bool = False,
    scenes: str = "paper",
    fill: tuple = FILL,
) -> Iterator[tuple[DeviceProfile, Dataset]]:
    """(camera, dataset) for each camera of ``family_profiles(n, seed, frames)``, lazily: ``family_member``'s."""
    for i, profile in enumerate(family_profiles(n, seed, frames)):
        yield (
            profile,
            family_member(
                profile,
                i,
                seed,
                n,
                natural_frames=natural_frames,
                planar_frames=planar_frames,
                dist_coeffs=dist_coeffs,
                platform_k=platform_k,
                scenes=scenes,
                fill=fill,
            ),
        )


def family_member(
    profile: DeviceProfile,
    index: int,
    seed: int,
    n: int,
    *,
    natural_frames: int = 0,
    planar_frames: int = 0,
    dist_coeffs: Optional[Sequence[float]] = None,
    platform_k: bool = False,
    scenes: str = "paper",
    fill: tuple = FILL,
    mislabel_share: float = 0.0,
) -> Dataset:
    """The dataset of camera ``index`` (``profile``) of the family of ``seed`` and ``n`` cameras:
    ``simulate(profile, seed=camera_seed(seed, index), ...)`` with ``family`` = {"seed", "index", "cameras",
    "scenes"} added to its meta. It depends on nothing else, so cameras can be simulated apart (``dimenet
    simulate --family N --address``). ``dist_coeffs`` (scale-free) apply to each camera about its own nominal K.
    ``scenes``: ``paper``, the paper's rig at the camera's distances; ``random``, a rig of the camera's own
    (``scenes.random_rig``, its own stream) framed so it spans ``fill`` (low, high) of the image width from the
    camera's far distance to its near one (``scenes.framed``; held-out families draw other framings than the
    training's: ``training/reproduce``), with its OIS as ``ois_camera`` draws it (none, or a video camera's larger
    stroke); the rig as built departs from its points (``scenes.build_errors_mm``, a third stream): sagging sheets,
    boards placed slightly off; its image has a residual lens, corner bias and JPEG noise, and a share of cameras
    photographs ChArUco boards (``image_errors.draw_image_errors``, a fourth stream); its natural frames see a random
    room, street or table of the rig's size around the rig's first board (``natural.random_natural``, a fifth
    stream); ``mislabel_share`` of their labels are gross mislabels (``simulate``'s)."""
    if scenes not in SCENES:
        raise InputError(f"scenes must be one of {', '.join(SCENES)}, got {scenes!r}")
    rig, offsets, natural, errors = None, None, None, None
    if scenes == "random":
        rig = random_rig(_stream(seed, 3, index))
        profile = framed(ois_camera(profile, seed, index), rig, fill)
        offsets = build_errors_mm(rig, _stream(seed, 5, index))
        errors = draw_image_errors(profile, _stream(seed, 7, index))
        if natural_frames:
            natural = random_natural(rig.boards[0], extent_mm(rig), _stream(seed, 6, index))
    ds = simulate(
        profile,
        seed=camera_seed(seed, index),
        natural_frames=natural_frames,
        planar_frames=planar_frames,
        dist_coeffs=dist_coeffs,
        platform_k=platform_k,
        rig=rig,
        rig_offsets_mm=offsets,
        natural=natural,
        image_errors=errors,
        mislabel_share=mislabel_share,
    )
    family = {"seed": int(seed), "index": index, "cameras": int(n), "scenes": scenes}
    return replace(ds, meta={**ds.meta, "family": family})
