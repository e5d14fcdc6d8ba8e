"""Hand-held recordings with a temporal OIS loop: a video of a natural scene (or a rig), frame by frame, with its
true K per frame and the gyroscope's samples (models_spec/simulator.md, "Recordings").

A recording is one camera of the any-scene family (``family.family_profile``, framed on a ``scenes.random_rig``)
looking at a random room, street or table (``natural.random_natural``) or at its rig, for ``seconds`` at ``fps``:

- the hand (``TraceModel``, drawn by ``draw_trace``): sway (three sinusoids under ~2 Hz), tremor (five sinusoids
  at 8-12 Hz), walking (a bob at 1.5-2.2 Hz) and pans (raised-cosine yaw excursions), as small rotations of the
  camera about its own centre (x: pitch, y: yaw, z: roll, OpenCV {C});
- the OIS loop runs at the gyroscope's rate: a first-order high-pass (the centring filter, cutoff ``ois_cutoff_hz``)
  of the rotation, times a gain near 1, clipped at the stroke, moves the principal point against the image's
  motion (cx by +f tan(hp yaw), cy by -f tan(hp pitch)); a camera with OIS off (stroke 0) keeps c;
- focus breathing: f = f_lens u / (u - f_lens) (``simulator.focus_breathing_focal_px``) at the focus distance u,
  which changes only when the camera refocuses (a step in f);
- cuts: the recording jumps to a new hand-held pose (``simulator.sample_pose``) and refocuses; the OIS recentres;
- the gyroscope: the angular rate in {C} (rad/s, small-angle: the angles' derivative) plus a constant bias and
  white noise, at ``gyro_hz``;
- the platform's lens-shift samples (Android's STATISTICS_OIS_SAMPLES) at the gyroscope's times: the optical
  centre's shift f (tan hp yaw, -tan hp pitch) px at the nominal f, times a Hall-sensor gain in LENS_SHIFT_GAIN,
  plus white noise of LENS_SHIFT_NOISE_PX (its own stream).

The frames are a ``dimenet-dataset/1`` Dataset in time order: ``infer_mask`` the points an app would stream (the
natural labels, with their 2D noise and 3D model error; half of a rig's corners), ``valid & ~infer_mask`` held-out
points for scoring (the scene's board corners and the other features, or corners, at their true 3D with corner
noise); a noisy point off the image is not seen; meta ``recording`` holds t_ns, cuts, refocus frames and the
trace. A frame the hand turns the scene out of is dropped (a gap in t_ns). ``K_platform``: the SDK's K as users
report it (``platform.reported_matrices``: f biased, c following the shift in part and a frame late, quantised;
its own stream). ``held_out=True`` draws from the held-out trace model (other spectra, cutoffs, gains, strokes
and frame rates), which training never draws from.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from dimenet.runtime.errors import InputError, RigError
from dimenet.runtime.formats.camera_file import write_camera
from dimenet.runtime.formats.dataset import Dataset, write_dataset
from dimenet.runtime.formats.motion import write_gyro, write_lens_shift
from dimenet.runtime.formats.points import write_points
from dimenet.runtime.geometry import k_params, matrix_to_rvec, rvec_to_matrix, to_camera
from dimenet.runtime.rectify.user_camera import checked_camera
from dimenet.runtime.sim.family import family_profile
from dimenet.runtime.sim.natural import random_natural
from dimenet.runtime.sim.platform import reported_matrices
from dimenet.runtime.sim.scene_geometry import rig_scene
from dimenet.runtime.sim.scenes import extent_mm, framed, random_rig
from dimenet.runtime.sim.simulator import MAX_POSE_ATTEMPTS, focus_breathing_focal_px, rig_view_ok, sample_pose, visible

KINDS = ("natural", "rig")
FORMAT = "dimenet-recording/1"  # meta["recording"]["format"]
MAX_SECONDS = 600.0
# Trace ranges (uniform) per model: (training, held-out). See models_spec/simulator.md, "Recordings".
TRACE_RANGES = {
    "fps": ((30.0,), (60.0, 30.0)),  # choices
    "gyro_hz": ((200.0, 400.0), (100.0, 500.0)),  # choices
    "sway_deg": ((0.3, 1.2), (0.5, 1.8)),
    "sway_hz": ((0.2, 1.5), (0.4, 2.0)),
    "tremor_deg": ((0.02, 0.08), (0.04, 0.12)),
    "tremor_hz": ((8.0, 11.0), (9.0, 12.0)),
    "walk_deg": ((0.2, 0.6), (0.4, 0.9)),
    "pan_deg": ((1.0, 3.0), (2.0, 4.0)),
    "ois_cutoff_hz": ((0.3, 1.0), (0.8, 1.6)),
    "ois_gain": ((0.92, 1.05), (0.85, 0.95)),
    "stroke_deg": ((0.8, 1.5), (1.5, 2.5)),
    "gyro_noise_rad_s": ((0.002, 0.006), (0.004, 0.01)),
    "gyro_bias_rad_s": ((0.0, 0.01), (0.005, 0.02)),
}
WALKING_SHARE = 0.3  # share of recordings walking (else standing still)
PANS_PER_MINUTE = 6.0  # Poisson rate of pans
PAN_SECONDS = (1.0, 2.5)  # one pan's duration, uniform
REFOCUS_PER_MINUTE = 4.0  # Poisson rate of refocus events (besides the one at each cut)
REFOCUS_DISTANCE = (0.5, 1.8)  # a refocus focuses at this factor of the scene distance, uniform
LABEL_SHARE = 0.5  # share of the features (a rig's corners) streamed; the rest are held out for scoring
LENS_SHIFT_GAIN = (0.9, 1.05)  # the lens-shift samples' gain (the Hall sensor's calibration), uniform
LENS_SHIFT_NOISE_PX = (0.05, 0.3)  # their white noise's std per axis (px), uniform


@dataclass(frozen=True)
class TraceModel:
    """How one recording is hand-held and stabilised (units in the names; see the module doc)."""

    fps: float
    gyro_hz: float
    sway_deg: float
    sway_hz: tuple
    tremor_deg: float
    tremor_hz: tuple
    walking: bool
    walk_deg: float
    pan_deg: float
    ois_cutoff_hz: float
    ois_gain: float
    stroke_deg: float
    gyro_noise_rad_s: float
    gyro_bias_rad_s: tuple
    held_out: bool


def draw_trace(rng: np.random.Generator, held_out: bool = False, ois: bool = True) -> TraceModel:
    """A trace from the training ranges (or the held-out ones) of TRACE_RANGES; ``ois=False``: stroke 0."""
    r = {k: v[1 if held_out else 0] for k, v in TRACE_RANGES.items()}
    u = lambda key: float(rng.uniform(*r[key]))  # noqa: E731
    bias = rng.normal(size=3)
    return TraceModel(
        fps=float(rng.choice(r["fps"])),
        gyro_hz=float(rng.choice(r["gyro_hz"])),
        sway_deg=u("sway_deg"),
        sway_hz=tuple(float(v) for v in rng.uniform(*r["sway_hz"], 3)),
        tremor_deg=u("tremor_deg"),
        tremor_hz=tuple(float(v) for v in rng.uniform(*r["tremor_hz"], 5)),
        walking=bool(rng.uniform() < WALKING_SHARE),
        walk_deg=u("walk_deg"),
        pan_deg=u("pan_deg"),
        ois_cutoff_hz=u("ois_cutoff_hz"),
        ois_gain=u("ois_gain"),
        stroke_deg=u("stroke_deg") if ois else 0.0,
        gyro_noise_rad_s=u("gyro_noise_rad_s"),
        gyro_bias_rad_s=tuple(float(v) for v in bias / np.linalg.norm(bias) * u("gyro_bias_rad_s")),
        held_out=held_out,
    )


def hand_angles_rad(trace: TraceModel, t_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(T, 3) rad the camera's rotation (pitch x, yaw y, roll z) off its base pose at times t_s (s)."""
    out = np.zeros((len(t_s), 3))
    for axis, weight in ((0, 1.0), (1, 1.0), (2, 0.5)):
        for hz in trace.sway_hz:
            out[:, axis] += weight * trace.sway_deg / math.sqrt(3) * np.sin(2 * math.pi * hz * t_s + rng.uniform(0, 7))
        for hz in trace.tremor_hz:
            out[:, axis] += trace.tremor_deg / math.sqrt(5) * np.sin(2 * math.pi * hz * t_s + rng.uniform(0, 7))
    if trace.walking:
        step_hz = rng.uniform(1.5, 2.2)
        out[:, 0] += trace.walk_deg * np.sin(2 * math.pi * 2 * step_hz * t_s)  # a bob per step
        out[:, 2] += trace.walk_deg * np.sin(2 * math.pi * step_hz * t_s)  # a sway per stride
    duration = float(t_s[-1]) if len(t_s) else 0.0
    for _ in range(int(rng.poisson(PANS_PER_MINUTE * duration / 60.0))):
        start, length = rng.uniform(0.0, duration), rng.uniform(*PAN_SECONDS)
        phase = np.clip((t_s - start) / length, 0.0, 1.0)
        out[:, 1] += rng.choice((-1.0, 1.0)) * trace.pan_deg * 0.5 * (1.0 - np.cos(2 * math.pi * phase))
    return np.radians(out)


def ois_shift_rad(trace: TraceModel, angles_rad: np.ndarray, dt_s: float, reset: np.ndarray) -> np.ndarray:
    """(T, 2) rad the OIS's compensation (about x, about y) at the gyro's samples: the first-order high-pass of the
    angles (cutoff ois_cutoff_hz, sampled every dt_s), times ois_gain, clipped at the stroke; ``reset`` (T,) bool
    recentres the filter (a cut)."""
    a = 1.0 / (1.0 + 2.0 * math.pi * trace.ois_cutoff_hz * dt_s)
    stroke = math.radians(trace.stroke_deg)
    out = np.zeros((len(angles_rad), 2))
    hp = np.zeros(2)
    for n in range(1, len(angles_rad)):
        hp = 0.0 if reset[n] else a * (hp + angles_rad[n, :2] - angles_rad[n - 1, :2])
        out[n] = np.clip(trace.ois_gain * hp, -stroke, stroke)
    return out


@dataclass(frozen=True)
class Recording:
    """A simulated recording: ``dataset`` (frames in time order, see the module doc), ``t_ns`` (F,) int64 per frame,
    ``gyro`` (G, 4) float64 rows (t_ns, gx, gy, gz rad/s in {C}), ``cuts`` and ``refocus``: frame indices where a
    cut or a refocus (a cut refocuses too) takes effect; ``lens_shift`` (G, 3) float64 rows (t_ns, x_shift_px,
    y_shift_px): the platform's samples of the optical centre's shift."""

    dataset: Dataset
    t_ns: np.ndarray
    gyro: np.ndarray
    cuts: tuple
    refocus: tuple
    lens_shift: np.ndarray


def _events(rng: np.random.Generator, seconds: float, cuts: int) -> tuple[np.ndarray, np.ndarray]:
    """Cut times (s, evenly spread, jittered) and refocus times (s, Poisson) of a recording."""
    cut_s = (np.arange(1, cuts + 1) + rng.uniform(-0.2, 0.2, cuts)) * seconds / (cuts + 1)
    refocus_s = np.sort(rng.uniform(0.0, seconds, rng.poisson(REFOCUS_PER_MINUTE * seconds / 60.0)))
    return np.sort(cut_s), refocus_s


def _kept_events(kept: np.ndarray, events) -> tuple:
    """The kept frames' indices where events at frame indices ``events`` take effect (none at the first frame)."""
    at = {int(np.searchsorted(kept, e)) for e in events}
    return tuple(sorted(i for i in at if 0 < i < len(kept)))


def _base_pose(profile, scene, usable, rng: np.random.Generator) -> tuple:
    """A hand-held pose (``simulator.sample_pose``) from which the scene is usable with the lens at rest."""
    for _ in range(MAX_POSE_ATTEMPTS):
        rvec, tvec = sample_pose(profile, scene.centre, rng)
        if usable(scene, visible(scene, profile, profile.nominal_K, rvec, tvec)[1]):
            return rvec, tvec
    raise RigError(f"recording: no hand-held pose out of {MAX_POSE_ATTEMPTS} sees the scene")


def simulate_recording(
    seed: int,
    *,
    seconds: float = 10.0,
    kind: str = "natural",
    held_out: bool = False,
    ois: bool = True,
    cuts: int = 1,
    image_size_px=None,
) -> Recording:
    """One recording of camera ``seed`` (see the module doc); deterministic per arguments."""
    if kind not in KINDS:
        raise InputError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if not (0.0 < seconds <= MAX_SECONDS) or not (0 <= cuts <= 100):
        raise InputError(f"seconds must be in (0, {MAX_SECONDS:g}] and cuts in [0, 100], got {seconds!r}, {cuts!r}")
    root = np.random.SeedSequence(int(seed), spawn_key=(51,))
    g_cam, g_rig, g_nat, g_trace, g_hand, g_run, g_sdk, g_ois = (np.random.default_rng(s) for s in root.spawn(8))
    rig = random_rig(g_rig)
    trace = draw_trace(g_trace, held_out, ois)
    profile = framed(family_profile(g_cam, f"recording-s{seed}", image_size_px, (1, 0)), rig)
    profile = replace(profile, ois_stroke_deg=trace.stroke_deg)
    if kind == "natural":
        natural = random_natural(rig.boards[0], extent_mm(rig), g_nat)
        scene, usable = natural.scene, natural.view_ok
        label_px, model_mm = natural.label_sigma_px, natural.model_sigma_mm
        features = scene.group < 0
        labels = features & (g_nat.uniform(size=len(features)) < LABEL_SHARE)
        model_points = scene.points + labels[:, None] * g_nat.normal(0.0, model_mm, scene.points.shape)
    else:
        scene, usable, label_px = rig_scene(rig), rig_view_ok, profile.corner_sigma_px
        labels, model_points = g_nat.uniform(size=len(scene.points)) < LABEL_SHARE, scene.points
    dt_s = 1.0 / trace.gyro_hz
    t_gyro = np.arange(0.0, seconds + dt_s, dt_s)
    angles = hand_angles_rad(trace, t_gyro, g_hand)
    cut_s, refocus_s = _events(g_run, seconds, cuts)
    reset = np.zeros(len(t_gyro), bool)
    reset[np.searchsorted(t_gyro, cut_s)] = True
    reset[0] = True
    ois_rad = ois_shift_rad(trace, angles, dt_s, reset)
    rate = np.gradient(angles, dt_s, axis=0)
    rate[reset] = rate[np.minimum(np.flatnonzero(reset) + 1, len(rate) - 1)]
    gyro_noise = g_run.normal(0.0, trace.gyro_noise_rad_s, rate.shape)
    t0_ns = int(g_run.integers(10**9, 10**12))
    gyro = np.column_stack([t0_ns + np.round(t_gyro * 1e9), rate + np.asarray(trace.gyro_bias_rad_s) + gyro_noise])
    shift_px = profile.nominal_K[0, 0] * np.column_stack([np.tan(ois_rad[:, 1]), -np.tan(ois_rad[:, 0])])
    shift_px = g_ois.uniform(*LENS_SHIFT_GAIN) * shift_px
    shift_px += g_ois.normal(0.0, g_ois.uniform(*LENS_SHIFT_NOISE_PX), shift_px.shape)
    lens_shift = np.column_stack([gyro[:, 0], shift_px])

    frames_t = np.arange(0.0, seconds, 1.0 / trace.fps)
    segment = np.searchsorted(cut_s, frames_t, side="right")
    focus_epoch = np.searchsorted(refocus_s, frames_t, side="right") + segment * 1000
    poses = {}
    focus = {}
    F_max, P = len(frames_t), len(scene.points)
    p2, p3 = np.full((F_max, P, 2), np.nan), np.full((F_max, P, 3), np.nan)
    valid, infer, K_true, kept, t_ns = (
        np.zeros((F_max, P), bool),
        np.zeros((F_max, P), bool),
        np.zeros((F_max, 3, 3)),
        [],
        [],
    )
    for k, t in enumerate(frames_t):
        s = int(segment[k])
        if s not in poses:
            poses[s] = _base_pose(profile, scene, usable, g_run)
        R0, t0 = rvec_to_matrix(poses[s][0]), np.asarray(poses[s][1])
        if focus_epoch[k] not in focus:
            distance = to_camera(scene.centre[None], *poses[s])[0, 2]
            factor = 1.0 if focus_epoch[k] == s * 1000 else g_run.uniform(*REFOCUS_DISTANCE)
            focus[focus_epoch[k]] = distance * factor * (1.0 + g_run.normal(0.0, profile.af_error_rel))
        n = min(int(round(t / dt_s)), len(t_gyro) - 1)
        D = rvec_to_matrix(angles[n])
        rvec, tvec = matrix_to_rvec(D.T @ R0), D.T @ t0
        f_px = focus_breathing_focal_px(profile, focus[focus_epoch[k]])
        cx, cy = profile.centre_px + f_px * np.array([math.tan(ois_rad[n, 1]), -math.tan(ois_rad[n, 0])])
        K = np.array([[f_px, 0.0, cx], [0.0, f_px * profile.pixel_aspect, cy], [0.0, 0.0, 1.0]])
        px, seen = visible(scene, profile, K, rvec, tvec)
        if not usable(scene, seen):
            continue
        i = len(kept)
        sigma = np.where(labels, label_px, profile.corner_sigma_px)[:, None]
        noisy = px + g_run.normal(0.0, 1.0, px.shape) * sigma
        w, h = profile.image_size_px
        seen &= np.all((noisy >= 0.0) & (noisy <= (w - 1, h - 1)), 1)  # no detector reports a point off the image
        p2[i][seen] = noisy[seen]
        p3[i][seen] = model_points[seen]
        valid[i], infer[i], K_true[i] = seen, seen & labels, K
        kept.append(k)
        t_ns.append(t0_ns + int(round(t * 1e9)))
    F = len(kept)
    if F == 0:
        raise InputError(f"recording seed {seed}: the hand turned the scene out of every frame")
    kept = np.asarray(kept)
    cut_frames = _kept_events(kept, np.searchsorted(frames_t, cut_s))
    refocus_frames = _kept_events(kept, np.flatnonzero(np.diff(focus_epoch) != 0) + 1)
    meta = {
        "generator": "dimenet.simulator.recording",
        "recording": {
            "format": FORMAT,
            "seed": int(seed),
            "kind": kind,
            "seconds": float(seconds),
            "t_ns": [int(v) for v in t_ns],
            "cuts": list(cut_frames),
            "refocus": list(refocus_frames),
            "trace": asdict(trace),
            "label_sigma_px": float(label_px),
        },
        "device": asdict(profile),
        "units": {"2d": "px", "3d": "mm"},
    }
    K_platform, platform = reported_matrices(K_true[:F], profile.nominal_K, g_sdk)
    meta["platform_k"] = {"simulated": True, **platform}
    dataset = Dataset(
        image_size=np.array(profile.image_size_px, np.int64),
        points_2d=p2[:F],
        points_3d=p3[:F],
        valid=valid[:F],
        infer_mask=infer[:F],
        split=np.array(["test"] * F),
        scene=np.array([kind] * F),
        meta=meta,
        K_true=K_true[:F],
        frame_id=np.array([f"f{k:05d}" for k in kept]),
        K_platform=K_platform,
    )
    return Recording(dataset, np.asarray(t_ns, np.int64), gyro, cut_frames, refocus_frames, lens_shift)


def points_rows(recording: Recording, platform: bool = False):
    """The points CSV rows of the recording (frame_id, t_ns, x_px, y_px, X_mm, Y_mm, Z_mm): each frame's streamed
    points (``infer_mask``); with ``platform`` each row ends in the frame's platform K (fx, fy, cx, cy px)."""
    ds = recording.dataset
    for i in range(ds.n_frames):
        m = ds.infer_mask[i]
        k = tuple(k_params(ds.K_platform[i])) if platform else ()
        for (x, y), (X, Y, Z) in zip(ds.points_2d[i, m], ds.points_3d[i, m]):
            yield (str(ds.frame_id[i]), int(recording.t_ns[i]), x, y, X, Y, Z, *k)


def nominal_camera(recording: Recording):
    """The recording camera's factory calibration as a rectify ``Camera``: its nominal K (infinity focus, OIS at
    rest) and image size, what an app would give as K_c."""
    device = recording.dataset.meta["device"]
    w, h = device["image_size_px"]
    f = device["focal_length_mm"] / (device["pixel_pitch_um"] * 1e-3)
    cx, cy = (w - 1) / 2.0 + device["centre_offset_px"][0], (h - 1) / 2.0 + device["centre_offset_px"][1]
    K = np.array([[f, 0.0, cx], [0.0, f * device["pixel_aspect"], cy], [0.0, 0.0, 1.0]])
    return checked_camera(K, (w, h), "recording camera")


def write_recording(recording: Recording, out_dir) -> dict:
    """The recording's files in ``out_dir``: points.csv (the streamed points, format 1), points-platform.csv (the
    same points in format 2 with the platform's per-frame K as each frame's K_c), gyro.csv and ois.csv (the lens
    shift's samples; ``formats.motion``),
    camera.json (``nominal_camera``) and truth.npz (the dataset: K_true per frame, held-out points
    ``valid & ~infer_mask``); -> {name: path}."""
    out = Path(out_dir)
    return {
        "points": write_points(out / "points.csv", points_rows(recording)),
        "points_platform": write_points(
            out / "points-platform.csv", points_rows(recording, platform=True), frame_k_c=True
        ),
        "gyro": write_gyro(out / "gyro.csv", recording.gyro),
        "ois": write_lens_shift(out / "ois.csv", recording.lens_shift),
        "camera": write_camera(out / "camera.json", nominal_camera(recording), "json"),
        "truth": write_dataset(recording.dataset, out / "truth.npz"),
    }
