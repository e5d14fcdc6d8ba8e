"""The whole feature in one ONNX graph (`dimenet export --graph full`): a generic model's frame in,
Delta K and K in the user's pixels out, in standard ONNX operators only, so an app in any language
runs it with ONNX Runtime and keeps only the two PnP solves and the fallback rules
(models_spec/model-v1.md, "The algorithm, for an app in another language").

Inputs (one frame of N points; double unless said):
- ``points_2d`` [N, 2] px, the user's image (OpenCV: the centre of the top-left pixel at (0, 0));
- ``points_3d`` [N, 3] in {W}, any unit;
- ``mask`` bool [N], the inference points; the others may hold anything (NaN, inf, the camera centre) and
  change nothing;
- ``K_c`` [3, 3] px and ``image_size`` [2] (width, height) px, the user's camera;
- ``rvec``, ``tvec`` [3], the pose {W}->{C0} from the app's own SQPnP under K_c.
Outputs: ``delta_k`` [4] (fx, fy, cx, cy) px and ``K`` [3, 3] px in the user's pixels (K = K_c +
Delta K, before the fallback rules), ``features`` float [1, D], what the network read, and (for a
model with an uncertainty model) ``sigma`` [4] px, the standard deviations of Delta K
(``Uncertainty.frame_covariance``; K_cov = sigma sigma^T * the spec's correlation). Without an inference
point (N = 0, or no mask set): Delta K = 0, K = K_c and sigma the population's (``population_sigma_px``),
as for a frame that keeps K_c. Parity with the runtime: ``export.golden.parity_px`` (models_spec/model-v1.md,
"The full graph's contract").

The graph computes what ``rectify.features.grid_features`` and the pixel map compute, in double:
the canonical camera (scale s = focal_px / fx_c, ``rectify.user_camera.generic_pixel_map``), the
C0 transform (Rodrigues), the PMD and {C0} point rows, the cell of each point (clamped, floored),
the per-cell means by a one-hot product, the scale-free depth factor, the channel scales, and for a
model with ``features.data_step`` the frame's Gauss-Newton step (``_data_step``); then the model's own
MLP nodes (float32, the gated step head's included) and the map back (Delta K / s).
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from dimenet.runtime.errors import ModelError
from dimenet.runtime.geometry.normal_equations import JACOBIAN_BASIS
from dimenet.runtime.rectify.encoders import grid, spans
from dimenet.runtime.rectify.encoders.data_step import (
    STEP_CLIP_REL,
    STEP_NOISE_FLOOR_PX,
    STEP_PRIOR_REL,
    STEP_VARIANCE_FLOOR,
)
from dimenet.runtime.rectify.encoders.grid import CHANNELS
from dimenet.runtime.rectify.encoders.moments import MOMENT_INDEX
from dimenet.runtime.rectify.model import INPUT_NAME, OUTPUT_NAME, onnx_model_from_bytes
from dimenet.runtime.rectify.spec import METADATA_KEY
from dimenet.runtime.rectify.uncertainty import D_FLOOR_PX, T_FLOOR

FULL_GRAPH_OPSET = 17
INPUTS = ("points_2d", "points_3d", "mask", "K_c", "image_size", "rvec", "tvec")
OUTPUTS = ("delta_k", "K", "features", "sigma")
# Below this rotation angle (rad) Rodrigues' sin(t)/t and (1 - cos t)/t^2 take their limits 1 and 1/2.
SMALL_ANGLE = 1e-12


class _Builder:
    """Nodes and constants of one graph, each name unique; a constant of a value already held is that one."""

    def __init__(self) -> None:
        self.nodes: list = []
        self.initializers: list = []
        self._count = 0
        self._constants: dict = {}

    def name(self, stem: str) -> str:
        self._count += 1
        return f"{stem}_{self._count}"

    def const(self, value, stem: str = "c", dtype=np.float64) -> str:
        array = np.asarray(value, dtype=dtype)
        key = (array.dtype.str, array.shape, array.tobytes())
        if key not in self._constants:
            self._constants[key] = self.name(stem)
            self.initializers.append(numpy_helper.from_array(array, self._constants[key]))
        return self._constants[key]

    def op(self, op_type: str, *inputs: str, stem: str = "", **attrs) -> str:
        out = self.name(stem or op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], **attrs))
        return out

    def column(self, x: str, k: int) -> str:
        """x[:, k] of a 2-D tensor, [N]."""
        return self.op("Gather", x, self.const(k, "col", np.int64), axis=1)


def _rotation(g: _Builder, rvec: str) -> str:
    """R [3, 3] from rvec [3] (Rodrigues): I + a [r]x + b [r]x^2, a = sin t / t, b = (1 - cos t) / t^2."""
    cross = np.zeros((3, 9))  # [r]x flattened row by row, as r @ cross
    for i, j, k, sign in ((2, 0, 1, -1), (1, 0, 2, 1), (2, 1, 0, 1), (0, 1, 2, -1), (1, 2, 0, -1), (0, 2, 1, 1)):
        cross[i, 3 * j + k] = sign
    rx = g.op(
        "Reshape",
        g.op("MatMul", g.op("Unsqueeze", rvec, g.const([0], "ax", np.int64)), g.const(cross)),
        g.const([3, 3], "shape", np.int64),
    )
    theta2 = g.op("ReduceSum", g.op("Mul", rvec, rvec), g.const([0], "ax", np.int64), keepdims=0)
    theta = g.op("Sqrt", theta2)
    small = g.op("Less", theta, g.const(SMALL_ANGLE))
    safe = g.op("Where", small, g.const(1.0), theta)
    a = g.op("Where", small, g.const(1.0), g.op("Div", g.op("Sin", safe), safe))
    b = g.op(
        "Where", small, g.const(0.5), g.op("Div", g.op("Sub", g.const(1.0), g.op("Cos", safe)), g.op("Mul", safe, safe))
    )
    rx2 = g.op("MatMul", rx, rx)
    return g.op("Add", g.op("Add", g.const(np.eye(3)), g.op("Mul", a, rx)), g.op("Mul", b, rx2))


def _thickness(g: _Builder, points_3d: str, weight: str, n: str) -> str:
    """``rectify.uncertainty.thickness`` of the masked 3D points (``n`` of them): det(C) tr(C) / e2(C)^2
    of their covariance C, clipped to [0, 1/3], 0 when e2 = 0."""
    ax0 = g.const([0], "ax", np.int64)
    w = g.op("Unsqueeze", weight, g.const([1], "ax", np.int64))
    mean = g.op("Div", g.op("ReduceSum", g.op("Mul", points_3d, w), ax0, keepdims=1), n)
    centred = g.op("Sub", points_3d, mean)
    cov = g.op("Div", g.op("MatMul", g.op("Transpose", g.op("Mul", centred, w), perm=[1, 0]), centred), n)
    a, b, c, d, e, f = (
        g.op("Gather", g.op("Reshape", cov, g.const([9], "shape", np.int64)), g.const(k, "i", np.int64))
        for k in (0, 1, 2, 4, 5, 8)
    )
    mul, sub, add = (lambda x, y, op=op: g.op(op, x, y) for op in ("Mul", "Sub", "Add"))
    trace = add(add(a, d), f)
    minors = add(add(sub(mul(a, d), mul(b, b)), sub(mul(a, f), mul(c, c))), sub(mul(d, f), mul(e, e)))
    det = add(
        sub(mul(a, sub(mul(d, f), mul(e, e))), mul(b, sub(mul(b, f), mul(e, c)))), mul(c, sub(mul(b, e), mul(d, c)))
    )
    positive = g.op("Greater", minors, g.const(0.0))
    safe = g.op("Where", positive, minors, g.const(1.0))
    ratio = g.op("Div", mul(g.op("Max", det, g.const(0.0)), trace), mul(safe, safe))
    return g.op("Where", positive, g.op("Min", ratio, g.const(1 / 3)), g.const(0.0))


def _sigma(g: _Builder, spec, points_3d: str, weight: str, n: str, dx: str, dy: str, counts: str) -> str:
    """sigma [4] model px of ``Uncertainty.frame_covariance``: exp(coef . z), z = [1, then the spec's
    statistics among log n, log occupied cells, log max(mean PMD, D_FLOOR_PX), log max(thickness, T_FLOOR)]."""
    ax0 = g.const([0], "ax", np.int64)
    occupied = g.op(
        "ReduceSum",
        g.op("Cast", g.op("Greater", counts, g.const(0.0)), to=TensorProto.DOUBLE),
        g.const([0, 1], "ax", np.int64),
        keepdims=0,
    )
    norms = g.op("Sqrt", g.op("Add", g.op("Mul", dx, dx), g.op("Mul", dy, dy)))
    pmd = g.op("Div", g.op("ReduceSum", g.op("Mul", norms, weight), ax0, keepdims=0), n)
    logs = {
        "log_points": g.op("Log", n),
        "log_cells": g.op("Log", occupied),
        "log_pmd": g.op("Log", g.op("Max", pmd, g.const(D_FLOOR_PX))),
        "log_thickness": g.op("Log", g.op("Max", _thickness(g, points_3d, weight, n), g.const(T_FLOOR))),
    }
    z = g.op(
        "Concat", g.const([1.0]), *(g.op("Unsqueeze", logs[name], ax0) for name in spec.uncertainty.statistics), axis=0
    )
    return g.op("Exp", g.op("MatMul", g.const(spec.uncertainty.coef), z))


def _inverse(g: _Builder, h: str, n: int) -> str:
    """The inverse of a symmetric positive definite [n, n] matrix h as ``geometry.prior_posterior``
    takes it: its diagonal scaled to 1 (D h D, D = diag(h)^-1/2), inverted by Gauss-Jordan elimination
    without pivoting on [D h D | I], unrolled (OpenCV's Cholesky in Python), then D (D h D)^-1 D."""
    ax0, ax1 = g.const([0], "ax", np.int64), g.const([1], "ax", np.int64)
    diagonal = g.op("ReduceSum", g.op("Mul", h, g.const(np.eye(n))), ax1, keepdims=0)
    d = g.op("Div", g.const(1.0), g.op("Sqrt", diagonal))
    scale = g.op("Mul", g.op("Unsqueeze", d, ax1), g.op("Unsqueeze", d, ax0))  # D_ii D_jj
    aug = g.op("Concat", g.op("Mul", h, scale), g.const(np.eye(n)), axis=1)
    for k in range(n):
        k_index = g.const(k, "i", np.int64)
        row = g.op("Gather", aug, k_index, axis=0)
        row = g.op("Div", row, g.op("Gather", row, k_index))
        column = g.op("Unsqueeze", g.op("Gather", aug, k_index, axis=1), ax1)
        unit = np.zeros((n, 1))
        unit[k] = 1.0
        aug = g.op("Sub", aug, g.op("Mul", g.op("Sub", column, g.const(unit)), g.op("Unsqueeze", row, ax0)))
    return g.op("Mul", g.op("Slice", aug, g.const([n], "s", np.int64), g.const([2 * n], "e", np.int64), ax1), scale)


def _gram(g: _Builder, weight: str, ab_inv_z: tuple, residuals: tuple) -> str:
    """``geometry.monomial_gram`` over the inference points [11, 11]: Q^T Q of the points' monomials
    q = [1, a, b, ab, a^2, b^2, 1/Z, a/Z, b/Z] and residuals (PMD) r_u, r_v, the masked points' rows zero."""
    a, b, inv_z = ab_inv_z
    ax1 = g.const([1], "ax", np.int64)
    one = g.op("Add", g.op("Mul", a, g.const(0.0)), g.const(1.0))
    ab = (a, b)
    columns = (one, a, b, g.op("Mul", a, b), *(g.op("Mul", c, c) for c in ab), inv_z)
    columns += (*(g.op("Mul", c, inv_z) for c in ab), *residuals)
    Q = g.op("Concat", *(g.op("Unsqueeze", c, ax1) for c in columns), axis=1)
    Q = g.op("Mul", Q, g.op("Unsqueeze", weight, ax1))
    return g.op("MatMul", g.op("Transpose", Q, perm=[1, 0]), Q)


def _block(g: _Builder, G: str, rows: tuple, cols: tuple) -> str:
    """G[rows[0]:rows[1], cols[0]:cols[1]]."""
    starts, ends = g.const([rows[0], cols[0]], "s", np.int64), g.const([rows[1], cols[1]], "e", np.int64)
    return g.op("Slice", G, starts, ends, g.const([0, 1], "ax", np.int64))


def _data_step(g: _Builder, G: str, n: str, focal: tuple, pmd_scale: float) -> str:
    """The data step's 8 inputs (``rectify.encoders.data_step``, ``geometry.prior_step``) [8]: the
    Gauss-Newton step over (pose, fx, fy, cx, cy) at the C0 pose and K_c with a prior of
    STEP_PRIOR_REL fx on K, its data weighted by 1 / s^2 twice (the pose's residuals, then the step's),
    the step's Delta K clipped to STEP_CLIP_REL fx times the PMD scale, then 1/2 ln(posterior / prior
    variance). The normal equations are ``geometry.gram_normal_equations``'s, from the points' Gram G
    [11, 11] (``_gram``): J J^T = C G C^T summed over u and v, C = fx B0 + fy B1 + B2 (JACOBIAN_BASIS)."""
    fx, fy = focal
    mul, add, sub = (lambda x, y, op=op: g.op(op, x, y) for op in ("Mul", "Add", "Sub"))
    ax0, ax1 = g.const([0], "ax", np.int64), g.const([1], "ax", np.int64)
    shape = lambda *dims: g.const(list(dims), "shape", np.int64)  # noqa: E731
    f1 = g.op("Concat", g.op("Unsqueeze", fx, ax0), g.op("Unsqueeze", fy, ax0), g.const([1.0]), axis=0)
    C = g.op("Reshape", g.op("MatMul", g.op("Unsqueeze", f1, ax0), g.const(JACOBIAN_BASIS)), shape(20, 9))
    CG = g.op("Reshape", g.op("MatMul", C, _block(g, G, (0, 9), (0, 9))), shape(10, 18))
    JJ = g.op("MatMul", CG, g.op("Transpose", g.op("Reshape", C, shape(10, 18)), perm=[1, 0]))
    Cr = g.op("Reshape", g.op("MatMul", C, _block(g, G, (0, 9), (9, 11))), shape(10, 4))  # [u r_u, u r_v, v r_u, v r_v]
    Jr = g.op("ReduceSum", mul(Cr, g.const([1.0, 0.0, 0.0, 1.0])), ax1, keepdims=0)
    residual_diagonal = g.const(np.diag([0.0] * 9 + [1.0, 1.0]))
    rss = g.op("ReduceSum", mul(G, residual_diagonal), g.const([0, 1], "ax", np.int64), keepdims=0)
    n_res = g.op("Mul", n, g.const(2.0))
    floor2 = g.const(STEP_NOISE_FLOOR_PX**2)

    def noise_weight(residual_ss: str, params: float) -> str:
        dof = g.op("Max", g.op("Sub", n_res, g.const(params)), g.const(1.0))
        return g.op("Div", g.const(1.0), g.op("Max", g.op("Div", residual_ss, dof), floor2))

    prior_var = g.op("Mul", g.op("Mul", fx, g.const(STEP_PRIOR_REL)), g.op("Mul", fx, g.const(STEP_PRIOR_REL)))
    k_block = np.zeros((10, 10))
    k_block[6:, 6:] = np.eye(4)
    prior = g.op("Div", g.const(k_block), prior_var)
    weight_1 = noise_weight(rss, 6.0)
    step_1 = g.op("Mul", g.op("MatMul", _inverse(g, add(mul(JJ, weight_1), prior), 10), Jr), weight_1)
    rss_step = add(
        sub(rss, mul(g.const(2.0), g.op("ReduceSum", mul(step_1, Jr), ax0, keepdims=0))),
        g.op("ReduceSum", mul(step_1, g.op("MatMul", JJ, step_1)), ax0, keepdims=0),
    )
    weight_2 = noise_weight(rss_step, 10.0)
    cov = _inverse(g, add(mul(JJ, weight_2), prior), 10)
    step = g.op("Neg", g.op("Mul", g.op("MatMul", cov, Jr), weight_2))
    k_part = g.op("Slice", step, g.const([6], "s", np.int64), g.const([10], "e", np.int64), ax0)
    clip = g.op("Mul", fx, g.const(STEP_CLIP_REL))
    clipped = g.op("Min", g.op("Max", k_part, g.op("Neg", clip)), clip)
    variance = g.op(
        "Slice",
        g.op("ReduceSum", g.op("Mul", cov, g.const(np.eye(10))), ax1, keepdims=0),
        g.const([6], "s", np.int64),
        g.const([10], "e", np.int64),
        ax0,
    )
    log_ratio = g.op(
        "Mul", g.const(0.5), g.op("Log", g.op("Max", g.op("Div", variance, prior_var), g.const(STEP_VARIANCE_FLOOR)))
    )
    return g.op("Concat", g.op("Mul", clipped, g.const(pmd_scale)), log_ratio, axis=0)


def _moments(g: _Builder, G: str, n: str, focal: tuple, pmd_scale: float) -> str:
    """The moments (``rectify.encoders.moments``) [MOMENT_SIZE] from the points' Gram G [11, 11]
    (``_gram``): s_i s_j G_ij / n with s each monomial's scale (1; z's n / sum(1/Z), sum(1/Z) = G[0, 6];
    the PMD's scale), gathered from the raveled matrix."""
    inv_z_sum = g.op("Reshape", _block(g, G, (0, 1), (6, 7)), g.const([], "shape", np.int64))
    positive = g.op("Greater", inv_z_sum, g.const(0.0))
    z_scale = g.op("Where", positive, g.op("Div", n, g.op("Where", positive, inv_z_sum, g.const(1.0))), g.const(1.0))
    is_z = np.zeros(11)
    is_z[6:9] = 1.0
    fixed = np.r_[np.ones(6), np.zeros(3), pmd_scale, pmd_scale]
    s = g.op("Add", g.const(fixed), g.op("Mul", g.const(is_z), z_scale))  # [11]
    ax0, ax1 = g.const([0], "ax", np.int64), g.const([1], "ax", np.int64)
    outer = g.op("Mul", g.op("Unsqueeze", s, ax1), g.op("Unsqueeze", s, ax0))
    scaled = g.op("Div", g.op("Mul", G, outer), n)
    flat = g.op("Reshape", scaled, g.const([121], "shape", np.int64))
    return g.op("Gather", flat, g.const(MOMENT_INDEX, "moments", np.int64), axis=0)


# The subgraph of each encoder after the grid (``rectify.encoders.ENCODERS``), by its name: (g, the points'
# Gram G [11, 11], their count n, K_c's (fx, fy), the PMD's scale) -> its inputs [size].
GRAM_BUILDERS = {"data_step": _data_step, "moments": _moments}


def full_graph(blob: bytes, source: str = "model") -> bytes:
    """The full graph of a generic ``dimenet-model/1`` file's bytes, with its spec in the metadata.
    ModelError for a model the graph does not hold yet (a device model)."""
    model = onnx_model_from_bytes(blob, source)
    spec = model.spec
    if spec.generic is None:
        raise ModelError(f"{source}: the full graph holds generic models (as the bundled default), not device models")
    mlp = onnx.load_from_string(blob)
    g = _Builder()
    features = spec.features
    cols, rows = features.grid.cols, features.grid.rows
    # The canonical camera: s = focal_px / fx_c; x_model = s (x + 0.5) - 0.5; K_c likewise.
    fx_c = g.op("Gather", g.op("Reshape", "K_c", g.const([9], "shape", np.int64)), g.const([0, 4, 2, 5], "k", np.int64))
    s = g.op("Div", g.const(spec.generic.focal_px), g.op("Gather", fx_c, g.const(0, "i", np.int64)))
    # Masked points may hold anything (NaN, inf, the camera centre) and change nothing: their values are
    # replaced (Where, no arithmetic) before any arithmetic, and their {C0} points by (0, 0, 1).
    keep = g.op("Unsqueeze", "mask", g.const([1], "ax", np.int64))
    points_2d = g.op("Where", keep, "points_2d", g.const(0.0))
    points_3d = g.op("Where", keep, "points_3d", g.const(0.0))
    half = g.const(0.5)
    p2 = g.op("Sub", g.op("Mul", s, g.op("Add", points_2d, half)), half)
    k_model = g.op(
        "Sub", g.op("Mul", s, g.op("Add", fx_c, g.const([0.0, 0.0, 0.5, 0.5]))), g.const([0.0, 0.0, 0.5, 0.5])
    )
    size = g.op("Mul", s, "image_size")
    # Points in {C0} and their projection under K_c (model px).
    R = _rotation(g, "rvec")
    xc = g.op("Add", g.op("MatMul", points_3d, g.op("Transpose", R, perm=[1, 0])), "tvec")
    xc = g.op("Where", keep, xc, g.const([0.0, 0.0, 1.0]))
    X, Y, Z = (g.column(xc, k) for k in range(3))
    inv_z = g.op("Div", g.const(1.0), Z)
    fx, fy, cx, cy = (g.op("Gather", k_model, g.const(k, "i", np.int64)) for k in range(4))
    u = g.op("Add", g.op("Mul", g.op("Mul", fx, X), inv_z), cx)
    v = g.op("Add", g.op("Mul", g.op("Mul", fy, Y), inv_z), cy)
    dx = g.op("Sub", u, g.column(p2, 0))
    dy = g.op("Sub", v, g.column(p2, 1))
    ax1 = g.const([1], "ax", np.int64)
    point_rows = g.op("Concat", *(g.op("Unsqueeze", c, ax1) for c in (dx, dy, X, Y, inv_z)), axis=1)
    # Cells: (x cols / width, y rows / height) clamped to [0, cols - 1] x [0, rows - 1], floored.
    per_cell = g.op("Div", g.const([cols, rows]), size)
    clamped = g.op("Min", g.op("Max", g.op("Mul", p2, per_cell), g.const(0.0)), g.const([cols - 1.0, rows - 1.0]))
    cell_xy = g.op("Floor", clamped)
    cell = g.op("Add", g.column(cell_xy, 0), g.op("Mul", g.column(cell_xy, 1), g.const(float(cols))))
    n_cells = cols * rows
    weight = g.op("Cast", "mask", to=TensorProto.DOUBLE)
    n = g.op("ReduceSum", weight, g.const([0], "ax", np.int64), keepdims=0)  # the inference points
    # No inference point (N = 0 or an all-false mask): Delta K = 0, sigma the population's, features 0.
    some = g.op("Greater", n, g.const(0.0))
    one_hot = g.op(
        "Mul",
        g.op(
            "Cast",
            g.op("Equal", g.op("Unsqueeze", cell, ax1), g.const(np.arange(n_cells, dtype=np.float64))),
            to=TensorProto.DOUBLE,
        ),
        g.op("Unsqueeze", weight, ax1),
    )
    one_hot_t = g.op("Transpose", one_hot, perm=[1, 0])
    sums = g.op("MatMul", one_hot_t, point_rows)  # [cells, 5]
    counts = g.op("ReduceSum", one_hot_t, ax1, keepdims=1)  # [cells, 1]
    means = g.op("Div", sums, g.op("Max", counts, g.const(1.0)))
    # Channel scales; scale-free depth: X, Y times depth_mm / Z_mean, 1/Z over it (1 when Z_mean <= 0).
    channel_index = [CHANNELS.index(c) for c in features.channels]
    scale = g.const(features.channel_scale)
    chosen = g.op("Gather", means, g.const(channel_index, "ch", np.int64), axis=1)
    if features.depth_mm is not None:
        ax0 = g.const([0], "ax", np.int64)
        z_sum = g.op("ReduceSum", g.op("Mul", Z, weight), ax0, keepdims=0)
        positive = g.op("Greater", z_sum, g.const(0.0))
        safe_sum = g.op("Where", positive, z_sum, g.const(1.0))
        factor = g.op(
            "Where", positive, g.op("Div", g.op("Mul", g.const(features.depth_mm), n), safe_sum), g.const(1.0)
        )
        scale = g.op("Mul", scale, g.op("Pow", factor, g.const(features.depth_exponents)))
    flat = g.op("Reshape", g.op("Mul", chosen, scale), g.const([1, features.grid_size], "shape", np.int64))
    used = [name for name, span in spans(features).items() if name != grid.NAME and span.stop > span.start]
    if used:
        G = _gram(g, weight, (g.op("Mul", X, inv_z), g.op("Mul", Y, inv_z), inv_z), (dx, dy))
    for name in used:
        inputs = GRAM_BUILDERS[name](g, G, n, (fx, fy), features.scale["dx"])
        flat = g.op("Concat", flat, g.op("Unsqueeze", inputs, g.const([0], "ax", np.int64)), axis=1)
    feats32 = g.op("Cast", g.op("Where", some, flat, g.const(0.0)), to=TensorProto.FLOAT)
    g.nodes.append(helper.make_node("Identity", [feats32], ["features"]))
    # The model's MLP, its names prefixed, reading the feature.
    rename = {INPUT_NAME: "features", OUTPUT_NAME: "mlp/delta_k"}
    for init in mlp.graph.initializer:
        copy = onnx.TensorProto()
        copy.CopyFrom(init)
        copy.name = rename.setdefault(init.name, f"mlp/{init.name}")
        g.initializers.append(copy)
    for node in mlp.graph.node:
        copy = onnx.NodeProto()
        copy.CopyFrom(node)
        copy.name = f"mlp/{node.name}"
        copy.input[:] = [rename.setdefault(i, f"mlp/{i}") for i in node.input]
        copy.output[:] = [rename.setdefault(o, f"mlp/{o}") for o in node.output]
        g.nodes.append(copy)
    sigma = None
    if spec.uncertainty is not None:
        population = spec.uncertainty.population_sigma_px  # None (spec < 1.6): NaN, as the runtime's K_cov
        population = np.full(4, np.nan) if population is None else population
        sigma = g.op("Where", some, _sigma(g, spec, points_3d, weight, n, dx, dy, counts), g.const(population))
    # Back to the user's pixels: Delta K / s, K = K_c + Delta K.
    delta = g.op("Reshape", g.op("Cast", "mlp/delta_k", to=TensorProto.DOUBLE), g.const([4], "shape", np.int64))
    delta = g.op("Div", g.op("Where", some, delta, g.const(0.0)), s)
    g.nodes.append(helper.make_node("Identity", [delta], ["delta_k"]))
    place = np.zeros((4, 9))
    place[0, 0] = place[1, 4] = place[2, 2] = place[3, 5] = 1.0
    k_delta = g.op(
        "Reshape",
        g.op("MatMul", g.op("Unsqueeze", delta, g.const([0], "ax", np.int64)), g.const(place)),
        g.const([3, 3], "shape", np.int64),
    )
    g.nodes.append(helper.make_node("Add", ["K_c", k_delta], ["K"]))
    if sigma is not None:
        g.nodes.append(helper.make_node("Div", [sigma, s], ["sigma"]))
    double = TensorProto.DOUBLE
    inputs = [
        helper.make_tensor_value_info("points_2d", double, ["N", 2]),
        helper.make_tensor_value_info("points_3d", double, ["N", 3]),
        helper.make_tensor_value_info("mask", TensorProto.BOOL, ["N"]),
        helper.make_tensor_value_info("K_c", double, [3, 3]),
        helper.make_tensor_value_info("image_size", double, [2]),
        helper.make_tensor_value_info("rvec", double, [3]),
        helper.make_tensor_value_info("tvec", double, [3]),
    ]
    outputs = [
        helper.make_tensor_value_info("delta_k", double, [4]),
        helper.make_tensor_value_info("K", double, [3, 3]),
        helper.make_tensor_value_info("features", TensorProto.FLOAT, [1, features.size]),
    ]
    if sigma is not None:
        outputs.append(helper.make_tensor_value_info("sigma", double, [4]))
    graph = helper.make_graph(g.nodes, "dimenet_full", inputs, outputs, g.initializers)
    opset = max([FULL_GRAPH_OPSET] + [o.version for o in mlp.opset_import if o.domain in ("", "ai.onnx")])
    full = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="dimenet")
    full.ir_version = min(full.ir_version, 8)
    entry = full.metadata_props.add()  # the spec without the MLP file's weights_sha256, which hashes that file
    entry.key, entry.value = METADATA_KEY, spec.to_json()
    full.doc_string = (
        "DIME-Net full graph: a frame's points, K_c and C0 pose -> Delta K, K (px); spec in metadata_props"
    )
    onnx.checker.check_model(full, full_check=True)
    return full.SerializeToString()
