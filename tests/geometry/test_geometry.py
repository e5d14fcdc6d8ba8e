import cv2
import numpy as np
import pytest
from helpers import K_TEST, random_frames

from dimenet.runtime import geometry as g
from dimenet.runtime.errors import CalibrationError, InputError


def test_rodrigues_matches_opencv_and_round_trips():
    rng = np.random.default_rng(0)
    rvecs = np.r_[rng.normal(0, 1, (20, 3)), [[0, 0, 0], [1e-10, 0, 0], [np.pi - 1e-3, 0, 0]]]
    R = g.rvec_to_matrix(rvecs)
    for r, Ri in zip(rvecs, R):
        np.testing.assert_allclose(Ri, cv2.Rodrigues(r)[0], atol=1e-12)
    np.testing.assert_allclose(g.rvec_to_matrix(g.matrix_to_rvec(R)), R, atol=1e-9)


@pytest.mark.parametrize("n", [None, 1, 4, 20])  # one rvec (3,), OpenCV pose by pose (<= FEW_POSES), vectorised
def test_rotation_matrices_are_rvec_to_matrix_for_any_number_of_poses(n):
    rng = np.random.default_rng(1)
    rvecs = rng.normal(0, 1, (3,) if n is None else (n, 3))
    if n is not None:
        rvecs[0] = [1e-10, 0, 0]  # the small-angle branch too
    R = g.rotation_matrices(rvecs)
    assert R.shape == rvecs.shape + (3,)
    np.testing.assert_allclose(R, g.rvec_to_matrix(rvecs), atol=1e-14)


def test_project_matches_opencv():
    rng = np.random.default_rng(1)
    x, X, K, rvec, tvec = random_frames(rng, frames=1)
    ref = cv2.projectPoints(X[0], rvec[0], tvec[0], K[0], None)[0][:, 0]
    np.testing.assert_allclose(g.project(X[0], K[0], rvec[0], tvec[0]), ref, atol=1e-9)


def test_frame_normal_equations_match_finite_differences_of_the_updated_pose():
    rng = np.random.default_rng(4)
    x, X, K, rvec, tvec = random_frames(rng, frames=1, points=30, noise_px=0.5)
    x, X, rvec, tvec, k = x[0], X[0], rvec[0], tvec[0], g.k_params(K[0])

    def residuals(p):  # p = (w, tau, dk): the pose updated on the left, K + dk; u's then v's
        R, t = g.left_update(cv2.Rodrigues(rvec)[0], tvec, p[:3], p[3:6])
        return (g.project(X, g.k_matrix(k + p[6:]), cv2.Rodrigues(R)[0].ravel(), t) - x).T.ravel()

    JJ, Jr, rss, r = g.frame_normal_equations(g.camera_xy_inverse_depth(X, cv2.Rodrigues(rvec)[0], tvec), x, k)
    np.testing.assert_allclose(r.ravel(), residuals(np.zeros(10)), atol=1e-9)
    assert rss == pytest.approx(float(residuals(np.zeros(10)) @ residuals(np.zeros(10))), rel=1e-12)
    steps = np.array([1e-7] * 3 + [1e-4] * 3 + [1e-3] * 4)
    J = np.stack(
        [(residuals(np.eye(10)[j] * h) - residuals(-np.eye(10)[j] * h)) / (2 * h) for j, h in enumerate(steps)]
    )
    np.testing.assert_allclose(JJ, J @ J.T, rtol=1e-6, atol=1e-6 * np.abs(J @ J.T).max())
    np.testing.assert_allclose(Jr, J @ r.ravel(), rtol=1e-6, atol=1e-6 * np.abs(J @ r.ravel()).max())


def test_k_params_round_trip_and_skew():
    p = np.array([[3000.0, 3010.0, 2016.0, 1512.0]])
    np.testing.assert_array_equal(g.k_params(g.k_matrix(p)), p)
    a, b = np.array([1.0, 2.0, 3.0]), np.array([-2.0, 0.5, 4.0])
    np.testing.assert_allclose(g.skew(a) @ b, np.cross(a, b))


def test_mean_reprojection_error_hand_computed():
    # Two points, offsets (3, 4) px and (0, 0) px from their exact projections: mean 2.5 px.
    X = np.array([[0.0, 0.0, 1000.0], [100.0, 50.0, 1000.0]])
    exact = g.project(X, K_TEST, np.zeros(3), np.zeros(3))
    x = exact + np.array([[3.0, 4.0], [0.0, 0.0]])
    pose = np.zeros((1, 3))
    assert g.mean_reprojection_error(x[None], X[None], None, K_TEST, pose, pose) == pytest.approx([2.5])
    # A point outside ``valid`` does not count, whatever its values.
    x_nan = np.where([[True], [False]], np.nan, x)[None]
    valid = np.array([[False, True]])
    assert g.mean_reprojection_error(x_nan, X[None], valid, K_TEST, pose, pose) == pytest.approx([0.0])

    # B frames at once, with and without a mask, and one K per frame.
    x2, X2, poses = np.stack([x, x]), np.stack([X, X]), np.zeros((2, 3))
    np.testing.assert_allclose(g.mean_reprojection_error(x2, X2, None, K_TEST, poses, poses), [2.5, 2.5])
    mask = np.array([[True, True], [False, True]])
    np.testing.assert_allclose(
        g.mean_reprojection_error(x2, X2, mask, np.stack([K_TEST] * 2), poses, poses), [2.5, 0.0], atol=1e-12
    )
    # The per-point errors and the residuals behind them.
    np.testing.assert_allclose(g.reprojection_errors(x, X, K_TEST, np.zeros(3), np.zeros(3)), [5.0, 0.0], atol=1e-9)
    residuals = g.reprojection_residuals(x, X, K_TEST, np.eye(3), np.zeros(3))
    np.testing.assert_allclose(residuals, [[-3.0, 0.0], [-4.0, 0.0]], atol=1e-9)


def test_mean_residual_norms_hand_computed():
    # u, v rows: norms 5, 1 and 0 px.
    residuals = np.array([[[3.0, 0.0, 0.0], [4.0, -1.0, 0.0]]])
    assert g.mean_residual_norms(residuals, None) == pytest.approx([2.0])
    assert g.mean_residual_norms(residuals, np.array([[True, False, True]])) == pytest.approx([2.5])


def test_dlt_recovers_exact_camera_from_noise_free_points():
    rng = np.random.default_rng(2)
    x, X, K, rvec, tvec = random_frames(rng, frames=1)
    K0, r0, t0 = g.dlt_camera(x[0], X[0])
    np.testing.assert_allclose(K0, K[0], atol=1e-6)
    np.testing.assert_allclose(r0, rvec[0], atol=1e-9)
    np.testing.assert_allclose(t0, tvec[0], atol=1e-6)


def test_dlt_refuses_coplanar_points():
    rng = np.random.default_rng(3)
    x, X, *_ = random_frames(rng, frames=1, planar=True)
    with pytest.raises(CalibrationError, match="coplanar"):
        g.dlt_camera(x[0], X[0])


@pytest.mark.parametrize("rvec", [(0.5, -0.2, 0.1), (-0.1, 0.7, 2.0), (0.9, 0.4, -1.2)])
def test_planar_focal_recovers_f_from_one_tilted_plane(rvec):
    # A plane (square units, z = 0) seen by f = 1650 px, centre (799.5, 599.5): H = K [r1 r2 t], any scale.
    K = g.k_matrix([1650.0, 1650.0, 799.5, 599.5])
    R = g.rvec_to_matrix(np.array(rvec))
    H = 3.7 * K @ np.c_[R[:, :2], [20.0, -15.0, 400.0]]
    assert g.planar_focal(H, np.array([799.5, 599.5])) == pytest.approx(1650.0, rel=1e-9)
    # A principal point off by 40 px moves it, but not far (what a rough centre costs).
    assert g.planar_focal(H, np.array([839.5, 599.5])) == pytest.approx(1650.0, rel=0.1)


def test_planar_focal_is_nan_for_a_plane_seen_face_on():
    K = g.k_matrix([1650.0, 1650.0, 799.5, 599.5])
    H = K @ np.c_[np.eye(3)[:, :2], [20.0, -15.0, 400.0]]
    assert np.isnan(g.planar_focal(H, np.array([799.5, 599.5])))


@pytest.mark.parametrize("kind", ["coincide", "collinear"])
def test_degenerate_configurations_are_named(kind):
    X = np.zeros((8, 3)) if kind == "coincide" else np.c_[np.arange(8.0), np.arange(8.0), 500 + np.arange(8.0)]
    x = np.c_[np.arange(8.0), np.arange(8.0) * 2]
    with pytest.raises(InputError, match=kind):
        g.check_not_degenerate(x, X)


def test_covariance_invariants_match_numpy():
    rng = np.random.default_rng(5)
    for D in (2, 3):
        points = rng.normal(size=(50, D)) @ rng.normal(size=(D, D)) + 1000.0
        C = np.cov(points.T, bias=True)
        minors = sum(np.linalg.det(C[np.ix_([i, j], [i, j])]) for i in range(D) for j in range(i + 1, D))
        np.testing.assert_allclose(g.covariance_invariants(points), (np.trace(C), minors, np.linalg.det(C)), rtol=1e-9)
        # The batch version over masked frames (NaN where masked out) agrees frame by frame.
        frames = np.stack([points, points[::-1] * 2.0])
        mask = np.ones((2, 50), bool)
        mask[1, :7] = False
        frames[1, :7] = np.nan
        batch = np.array(g.covariance_invariants_batch(frames, mask))
        for b in range(2):
            np.testing.assert_allclose(
                batch[:, b], g.covariance_invariants(np.ascontiguousarray(frames[b][mask[b]])), rtol=1e-9
            )


def test_covariance_invariants_sum_in_point_order():
    # The order the compiled core follows: the mean, then each centred product, summed point after point.
    rng = np.random.default_rng(6)
    for D in (2, 3):
        points = rng.normal(0.0, 1.0, (97, D)) * 10.0 ** rng.uniform(-3, 6, (97, 1)) + 1e4
        mean = [0.0] * D
        for p in points.tolist():
            mean = [m + v for m, v in zip(mean, p)]
        mean = [m / len(points) for m in mean]
        pairs = [(0, 0), (0, 1), (1, 1)] if D == 2 else [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        sums = [0.0] * len(pairs)
        for p in points.tolist():
            d = [v - m for v, m in zip(p, mean)]
            sums = [s + d[i] * d[j] for s, (i, j) in zip(sums, pairs)]
        c = [s / len(points) for s in sums]
        if D == 2:
            a, b, d = c
            assert g.covariance_invariants(points) == (a + d, a * d - b * b, a * d - b * b)
        else:
            a, b, c_, d, e, f = c
            det = (a * (d * f - e * e) - b * (b * f - e * c_)) + c_ * (b * e - d * c_)
            minors = ((a * d - b * b) + (a * f - c_ * c_)) + (d * f - e * e)
            assert g.covariance_invariants(points) == ((a + d) + f, minors, det)


def test_the_pixel_rescale_by_hand():
    """Half resolution (scale 0.5): a half-resolution pixel covers 2x2 full ones, so the full image's
    top-left corner (-0.5, -0.5) stays, the far corner (1.5, 1.5) of its first 2x2 block is the first half
    pixel's far corner (0.5, 0.5), and full pixel 0's centre lies at -0.25. K's focal lengths halve and its
    principal point moves as a point; scale 2 undoes 0.5 exactly."""
    np.testing.assert_array_equal(
        g.rescaled_px([[-0.5, -0.5], [1.5, 1.5], [0.0, 3.0]], 0.5), [[-0.5, -0.5], [0.5, 0.5], [-0.25, 1.25]]
    )
    k = np.array([3000.0, 3010.0, 2015.5, 1511.5])
    np.testing.assert_array_equal(g.rescaled_k(k, 0.5), [1500.0, 1505.0, 1007.5, 755.5])
    np.testing.assert_array_equal(g.rescaled_k(g.rescaled_k(k[None], 0.5), 2.0), k[None])
