"""The free-space term (tracking/free_space.py, tracking/terms/free_space.py): model points where the camera saw through them."""
import cv2
import numpy as np

from surfelwarp.deform.warp_field import WarpField, WarpFieldParams, apply_update, skin, warp
from surfelwarp.geometry.camera import Intrinsics
from surfelwarp.geometry.se3 import se3_exp
from surfelwarp.tracking.blend_jacobian import data_jacobian
from surfelwarp.tracking.free_space import FreeSpace, SilhouetteParams, _ball_widths, _holes
from surfelwarp.tracking.free_space_kernels import chamfer, nearest_by_rows, nearest_depth, within_reach
from surfelwarp.tracking.gauss_newton import NonRigidParams, solve_nonrigid

INTR = Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240)
P = SilhouetteParams()


def square_depth(z=1.0, half_px=60, hole_px=0, behind=None):
    """A square of depth z in the middle of an empty image, with an optional square hole of
    hole_px pixels a side in its middle; `behind`: the rest of the image sees a wall that far."""
    depth = np.zeros((INTR.height, INTR.width), np.float32)
    if behind is not None:
        depth[:] = behind
    r, c = int(INTR.cy), int(INTR.cx)
    depth[r - half_px:r + half_px, c - half_px:c + half_px] = z
    if hole_px:
        h = hole_px // 2
        depth[r - h:r - h + hole_px, c - h:c - h + hole_px] = 0
    return depth


def at_pixel(u, v, z=1.0):
    """World points (3, N) projecting to pixels (u, v) at depth z (identity camera)."""
    u, v = np.atleast_1d(u).astype(float), np.atleast_1d(v).astype(float)
    return np.stack([(u - INTR.cx) / INTR.fx * z, (v - INTR.cy) / INTR.fy * z, np.full(len(u), z)])


def test_points_past_the_silhouette_are_pulled_back_by_their_distance():
    space = FreeSpace(square_depth(), INTR, np.eye(4))
    last = int(INTR.cx) + 59                       # the square's last column
    u = np.array([last - 20, last, last + 11, last + 31])
    r, grad = space.residuals(at_pixel(u, np.full(4, INTR.cy)))
    assert r[0] == 0 and r[1] == 0                 # on the observed surface
    # Outside: (distance in pixels - margin) at 1 m, f = 300 (the distance transform is exact
    # along a row to within its 5x5 mask's error).
    np.testing.assert_allclose(r[2:], (np.array([11.0, 31.0]) - P.margin_px) / INTR.fx, rtol=0.03)
    # The gradient points away from the square (+x), with the length of the pixel scale.
    assert grad[0, 2] > 0 and grad[0, 3] > 0
    np.testing.assert_allclose(np.abs(grad[0, 2:]), 1.0, rtol=0.05)


def test_holes_and_the_image_border_are_not_free_space():
    space = FreeSpace(square_depth(hole_px=2 * P.hole_px - 2), INTR, np.eye(4))
    r, _ = space.residuals(at_pixel(np.array([INTR.cx]), np.array([INTR.cy])))
    assert r[0] == 0                               # a dropout inside the surface pulls nothing
    big = FreeSpace(square_depth(hole_px=4 * P.hole_px + 10), INTR, np.eye(4))
    assert big.residuals(at_pixel(np.array([INTR.cx]), np.array([INTR.cy])))[0][0] > 0
    # Near the image edge nothing is judged, though the camera saw nothing there.
    r, _ = space.residuals(at_pixel(np.array([5.0, 40.0]), np.array([INTR.cy, INTR.cy])))
    assert r[0] == 0 and r[1] > 0


def test_a_surface_in_front_hides_its_unmeasured_rim_and_the_far_clip_is_free_space():
    """No depth right beside a nearer surface may be that surface seen edge-on: not free
    space for points behind it. Depth dropped by the far clip is free space in front of it."""
    depth = square_depth(z=1.0, half_px=60)
    r, c = int(INTR.cy), int(INTR.cx)
    depth[r - 30:r + 30, c + 60:c + 70] = 0.8      # a nearer strip along the square's right edge
    space = FreeSpace(depth, INTR, np.eye(4))
    beside = at_pixel(np.array([c + 70 + P.occluder_px // 2]), np.array([r]), z=1.0)
    assert space.residuals(beside)[0][0] == 0
    far_out = at_pixel(np.array([c + 70 + 2 * P.occluder_px]), np.array([r]), z=1.0)
    assert space.residuals(far_out)[0][0] > 0
    # A wall behind, too far for the clip, seen through a 10-pixel slit in a nearer wall: a
    # hole while its depth is merely missing, free space once known to lie beyond the clip.
    walls = np.full(depth.shape, 1.0, np.float32)
    slit = np.zeros(depth.shape, bool)
    slit[:, c - 5:c + 5] = True
    walls[slit] = 0
    in_slit = at_pixel(np.array([c]), np.array([r]), z=0.99)     # on the wall, were it there
    assert FreeSpace(walls, INTR, np.eye(4)).residuals(in_slit)[0][0] == 0
    assert FreeSpace(walls, INTR, np.eye(4), beyond=slit).residuals(in_slit)[0][0] > 0


def test_a_wall_far_behind_a_point_is_seen_through_and_one_near_is_not():
    far = FreeSpace(square_depth(behind=1.5), INTR, np.eye(4))
    near = FreeSpace(square_depth(behind=1.0 + 0.5 * P.depth_margin_m), INTR, np.eye(4))
    outside = at_pixel(np.array([INTR.cx + 90]), np.array([INTR.cy]))
    assert far.residuals(outside)[0][0] > 0
    assert near.residuals(outside)[0][0] == 0
    # A point behind the observed surface is occluded, not seen through.
    assert far.residuals(at_pixel(np.array([INTR.cx + 90]), np.array([INTR.cy]), z=1.6))[0][0] == 0


def test_residual_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    T = se3_exp(np.array([0.05, -0.03, 0.02, 0.04, -0.02, 0.03]))      # camera off the world origin
    space = FreeSpace(square_depth(), INTR, T)
    q = at_pixel(rng.uniform(INTR.cx + 70, INTR.cx + 120, 30), rng.uniform(INTR.cy - 50, INTR.cy + 50, 30),
                 z=rng.uniform(0.95, 1.0, 30))
    x = T[:3, :3] @ q + T[:3, 3:]                   # world points the camera sees outside the square
    r, grad = space.residuals(x)
    assert (r > 0).all()
    h = 1e-6
    numeric = np.stack([(space.residuals(x + h * e[:, None])[0] - space.residuals(x - h * e[:, None])[0]) / (2 * h)
                        for e in np.eye(3)])
    rel = np.linalg.norm(grad - numeric) / np.linalg.norm(numeric)
    print(f"free-space gradient vs central differences: relative error {rel:.1e}")
    assert rel < 1e-6


def test_the_terms_node_jacobian_matches_finite_differences():
    """The solve uses the data term's Jacobian with the residual's gradient as the normal:
    d r(W(x)) / d xi_j, checked against the residual of the warped points."""
    rng = np.random.default_rng(1)
    points = np.stack(np.meshgrid(np.linspace(0.2, 0.4, 12), np.linspace(-0.1, 0.1, 12)), -1).reshape(-1, 2)
    points = np.column_stack([points, np.full(len(points), 0.97)])
    field = WarpField.from_points(points, WarpFieldParams(node_radius_m=0.05))
    field = apply_update(field, rng.normal(size=(field.num_nodes, 6)) * [0.02, 0.02, 0.02, 0.003, 0.003, 0.003])
    knn, w = skin(points, field.nodes, 4, field.sigma_m)
    space = FreeSpace(square_depth(), INTR, np.eye(4))

    def residuals(f):
        live, _ = warp(points, None, knn, w, f)
        return space.residuals(live.T)

    r, grad = residuals(field)
    assert (r > 0).all()
    J = data_jacobian(field, points, knn, w.astype(np.float64), grad.T)     # (C, k, 6) per slot
    node, h = int(knn[0, 0]), 1e-6
    for m in range(6):
        xi = np.zeros((field.num_nodes, 6))
        xi[node, m] = h
        numeric = (residuals(apply_update(field, xi))[0] - residuals(apply_update(field, -xi))[0]) / (2 * h)
        analytic = np.sum(np.where((knn == node)[..., None], J, 0.0), axis=1)[:, m]
        assert np.abs(analytic - numeric).max() < 1e-6 * max(np.abs(numeric).max(), 1e-3)


def test_the_solve_pulls_a_sheet_back_under_its_silhouette():
    """A flat patch observed where it is, its template shifted 2 cm to the right along itself:
    depth alone does not see the slide; the free-space term brings it back."""
    u, v = np.meshgrid(np.arange(INTR.cx - 50, INTR.cx + 50), np.arange(INTR.cy - 50, INTR.cy + 50))
    points = at_pixel(u.ravel(), v.ravel()).T
    depth = square_depth(half_px=50)
    vertex = INTR.backproject(depth)
    normal = np.where(depth[..., None] > 0, np.array([0.0, 0.0, -1.0], np.float32), 0.0)
    valid = depth > 0
    field = WarpField.from_points(points, WarpFieldParams())
    knn, w = skin(points, field.nodes, 4, field.sigma_m)
    shifted = field.with_transforms(np.tile(se3_exp(np.array([0, 0, 0, 0.02, 0, 0])), (field.num_nodes, 1, 1)))
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    for weight, expected in ((0.0, "stays"), (1.0, "back")):
        params = NonRigidParams(silhouette=SilhouetteParams(weight=weight), max_iterations=20)
        solved, res = solve_nonrigid(shifted, points, normals, knn, w, vertex, normal, valid, INTR, np.eye(4), params)
        live, _ = warp(points, None, knn, w, solved)
        slide = float(np.mean(live[:, 0] - points[:, 0]))
        if expected == "stays":
            assert slide > 0.019 and res.silhouette_points == 0
        else:
            assert abs(slide) < 0.004, slide
            assert res.alignment.unsupported_fraction < 0.05


def steps_scene_and_points():
    """A scene of steps, holes and a far wall, and clusters of points in it, one cluster far
    from any surface: (depth, (3, N) points)."""
    rng = np.random.default_rng(5)
    depth = np.full((INTR.height, INTR.width), 2.5, np.float32)
    for _ in range(12):
        r, c = rng.integers(0, INTR.height - 40), rng.integers(0, INTR.width - 40)
        depth[r:r + rng.integers(10, 40), c:c + rng.integers(10, 40)] = rng.uniform(0.6, 2.0)
    depth[rng.random(depth.shape) < 0.02] = 0
    depth[100:160, 40:120] = 0
    depth[:, 190:] = 0      # a wide empty region: its points are farther from the surface than a window reaches
    # Clusters of points, each at one depth (so one layer): a seen-through region is local.
    clusters = []
    for _ in range(80):
        cu, cv, z = rng.uniform(15, INTR.width - 16), rng.uniform(15, INTR.height - 16), rng.uniform(0.5, 2.6)
        clusters.append(at_pixel(cu + rng.uniform(-15, 15, 40), cv + rng.uniform(-15, 15, 40), z))
    clusters.append(at_pixel(rng.uniform(270, 290, 40), rng.uniform(110, 130, 40), 1.01))  # far from any surface
    return depth, np.concatenate(clusters, axis=1)


def whole_image_transforms(depth):
    """The reference: a FreeSpace whose every layer's transform covers the whole image."""
    whole = FreeSpace(depth, INTR, np.eye(4), SilhouetteParams(search_px=0))
    h, w = depth.shape
    for layer in range(200):
        whole._layers[layer] = (0, h, 0, w, whole._transform(layer, 0, h, 0, w))
    return whole


def test_windowed_distance_transforms_equal_the_whole_images():
    """Each layer's transform runs on a window around its points; the residuals and gradients
    must be those of transforms over the whole image."""
    depth, points = steps_scene_and_points()
    windowed = FreeSpace(depth, INTR, np.eye(4), SilhouetteParams(search_px=0))
    r1, g1 = windowed.residuals(points)
    r2, g2 = whole_image_transforms(depth).residuals(points)
    assert (r2 > 0).sum() > 300 and r2.max() > 0.1
    # Equal but for float32 rounding of chamfer sums taken along other paths of the same length.
    np.testing.assert_allclose(r1, r2, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(g1, g2, rtol=1e-6, atol=1e-5)
    h, w = depth.shape
    assert any(box[:4] != (0, h, 0, w) for box in windowed._layers.values())   # windows were used


def test_the_search_about_each_point_equals_the_whole_images_transforms():
    """Distances up to search_px are searched for about each point; the residuals and gradients
    must be the transforms', and farther points must fall back to the transforms."""
    depth, points = steps_scene_and_points()
    searched = FreeSpace(depth, INTR, np.eye(4))
    r1, g1 = searched.residuals(points)
    r2, g2 = whole_image_transforms(depth).residuals(points)
    assert (r2 > 0).sum() > 300 and r2.max() > 0.1
    # The closed-form chamfer distance differs from cv2's sums by float32 rounding (5e-5 px).
    np.testing.assert_allclose(r1, r2, rtol=0, atol=2e-7)
    np.testing.assert_allclose(g1, g2, rtol=0, atol=2e-5)
    far = r2 > 2 * P.search_px * 1.01 / INTR.fx      # beyond the search at the far cluster's depth
    assert far.sum() > 10 and len(searched._layers) > 0 and len(searched._layers) < 40
    # Every layer searched alone: the nearest-depth memo fills the same whichever layer asked first.
    again = FreeSpace(depth, INTR, np.eye(4))
    np.testing.assert_allclose(again.residuals(points[:, ::-1])[0][::-1], r1, rtol=0, atol=1e-12)
    # Each pixel's answer is kept for its layer: asked again, the same bits; the same pixels at
    # the next layer (2 cm farther) are searched afresh, then the first layer's again.
    assert searched.residuals(points)[0].tobytes() == r1.tobytes() and (searched._found_layer >= 0).sum() > 1000
    farther = points * (1 + P.layer_m / points[2])
    r4, g4 = searched.residuals(farther)
    r5, g5 = whole_image_transforms(depth).residuals(farther)
    assert np.abs(r4 - r1).max() > 0.01
    np.testing.assert_allclose(r4, r5, rtol=0, atol=2e-7)
    np.testing.assert_allclose(g4, g5, rtol=0, atol=2e-5)
    assert searched.residuals(points)[0].tobytes() == r1.tobytes()
    # shared with the same observation at another pose (the answers do not depend on it)
    assert searched.moved_to(np.eye(4))._found is searched._found


def test_the_chamfer_distance_in_closed_form_is_cv2s():
    image = np.ones((101, 101), np.uint8)
    image[50, 50] = 0
    reference = cv2.distanceTransform(image, cv2.DIST_L2, cv2.DIST_MASK_5)
    dy, dx = np.mgrid[-50:51, -50:51]
    closed_form = np.vectorize(chamfer)(dy, dx)
    np.testing.assert_allclose(closed_form, reference, rtol=0, atol=1e-4)
    # A knight's move, five steps, five diagonals, and (3, 4) as a knight's move and two diagonals.
    np.testing.assert_allclose([chamfer(1, 2), chamfer(0, 5), chamfer(-5, 5), chamfer(3, -4)],
                               [2.1969, 5, 7, 2.1969 + 2 * 1.4], rtol=1e-6)
    # The occluder test's ball: its rows' half-widths reach exactly the pixels within radius.
    widths = _ball_widths(24)
    assert len(widths) == 49 and widths[24] == 24 and widths[0] == 0
    assert chamfer(8, widths[24 + 8]) <= 24 < chamfer(8, widths[24 + 8] + 1)


def test_the_term_reuses_its_answer_for_the_same_live_points_only():
    """A candidate's answer is kept for the next linearisation on the same live arrays; points
    moved in a new array (as every warp gives) are judged afresh."""
    from types import SimpleNamespace
    from surfelwarp.tracking.terms.free_space import FreeSpaceTerm
    term = FreeSpaceTerm(FreeSpace(square_depth(), INTR, np.eye(4)), P, np.zeros((3, 4)))
    u = np.array([INTR.cx, INTR.cx + 59 + 11, INTR.cx + 59 + 31, INTR.cx - 20])
    live = at_pixel(u, np.full(4, INTR.cy))
    normals = np.tile([[0.0], [0.0], [-1.0]], (1, 4))
    first = term.seen_through(SimpleNamespace(live=live, live_normals=normals))
    assert list(first[1]) == [1, 2] and first[0] > 0
    assert term.seen_through(SimpleNamespace(live=live, live_normals=normals)) is first
    back = live.copy()
    back[0] -= 0.12                                 # 36 px left: all inside the square
    again = term.seen_through(SimpleNamespace(live=back, live_normals=normals))
    assert list(again[1]) == [] and again[0] == 0
    assert term.seen_through(SimpleNamespace(live=live.copy(), live_normals=normals))[0] == first[0]


def test_holes_opened_about_the_valid_pixels_equal_the_whole_images_opening():
    """The opening is made only over the box of valid pixels and 2 hole_px + 2 around it: the
    same mask as cv2's over the whole image, with valid pixels at the edges and corners (the
    replicated border), none, all, and hole_px 0."""
    def whole(invalid, hole_px):
        k = 2 * hole_px + 1
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        return cv2.morphologyEx(invalid.astype(np.uint8), cv2.MORPH_OPEN, disc, borderType=cv2.BORDER_REPLICATE) > 0
    rng = np.random.default_rng(4)
    cases = [np.ones((30, 40), bool), np.zeros((30, 40), bool), square_depth(hole_px=3) <= 0]
    for _ in range(150):
        h, w = rng.integers(1, 70, 2)
        invalid = np.ones((h, w), bool)
        for _ in range(rng.integers(1, 4)):
            y0, x0 = rng.integers(0, h), rng.integers(0, w)
            y1, x1 = y0 + rng.integers(1, 9), x0 + rng.integers(1, 9)
            invalid[max(y0 - rng.integers(0, 9), 0):y1, max(x0 - rng.integers(0, 9), 0):x1] = False
        cases.append(invalid ^ (rng.random((h, w)) < 0.03))
    for i, invalid in enumerate(cases):
        hole_px = int(rng.integers(0, 10))
        assert np.array_equal(_holes(invalid, hole_px), whole(invalid, hole_px)), (i, hole_px)
    small = np.ones((200, 200), bool)
    small[90:110, 90:110] = False
    small[100, 100] = True          # a hole too small for the disc: not free space
    assert _holes(small, 8).sum() == small.sum() - 1


def test_the_points_within_reach_are_numpys():
    """The compiled first pass of `residuals` (points in front, inside the image, nearer than
    their pixel's reach) gives numpy's points, pixels and camera points, bit for bit, with
    points behind the camera, outside the image and NaN among them."""
    T = se3_exp(np.array([0.05, -0.03, 0.02, 0.1, -0.05, 0.2]))
    space = FreeSpace(square_depth(behind=2.0), INTR, T)
    rng = np.random.default_rng(5)
    x = (T[:3, :3] @ at_pixel(rng.uniform(-40, INTR.width + 40, 4000), rng.uniform(-40, INTR.height + 40, 4000),
                              rng.uniform(-0.5, 3.0, 4000)) + T[:3, 3:])
    x[:, :5] = np.nan
    R, t = space.R_wc, space.t_wc
    q = np.stack([x[0] * R[i, 0] + x[1] * R[i, 1] + x[2] * R[i, 2] + t[i] for i in range(3)])
    h, w = INTR.height, INTR.width
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / q[2]
        u, v = INTR.fx * q[0] * inv + INTR.cx, INTR.fy * q[1] * inv + INTR.cy
        inside = (q[2] > 1e-3) & (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
    sel = np.flatnonzero(inside)
    sel = sel[q[2, sel] + P.depth_margin_m < space._reach[v[sel].astype(np.int64) * w + u[sel].astype(np.int64)]]
    n = x.shape[1]
    got, uv, cam = np.empty(n, np.int64), np.empty((2, n)), np.empty((3, n))
    k = within_reach(x, R, t, INTR.fx, INTR.fy, INTR.cx, INTR.cy, h, w, space._reach, P.depth_margin_m, got, uv, cam)
    assert 100 < k < n - 1000
    assert np.array_equal(got[:k], sel)
    assert np.array_equal(uv[:, :k], np.stack([u[sel], v[sel]])) and np.array_equal(cam[:, :k], q[:, sel])


def test_nearest_depths_from_the_rows_minima_are_the_balls():
    """The rows' minima give every pixel's nearest depth within the occluder test's ball as the
    ball itself does: objects on an empty background (the minima made), beside the image's
    edges and with pixels measured beyond the far clip (inf), a mostly measured image, and an
    image with nothing measured."""
    rng = np.random.default_rng(7)
    depth = np.zeros((INTR.height, INTR.width), np.float32)
    depth[30:90, 0:50] = rng.uniform(0.5, 2.0, (60, 50))           # at the left edge
    depth[150:240, 200:260] = rng.uniform(0.5, 2.0, (90, 60))      # at the bottom edge
    depth[0:20, 290:320] = rng.uniform(0.5, 2.0, (20, 30))         # in the top right corner
    depth[100:120, 120:150] = np.inf                                # beyond the far clip
    depth[rng.uniform(size=depth.shape) < 0.3] = 0                 # dropouts
    space = FreeSpace(depth, INTR, np.eye(4))
    assert space._minima.shape[0] == len(np.unique(space._ball))
    assert space._box[2] == 0 and space._box[3] == INTR.width
    ball = space._ball
    ys, xs = np.mgrid[0:INTR.height:3, 0:INTR.width:3]
    pixels = list(zip(ys.ravel(), xs.ravel()))
    from_rows = [nearest_by_rows(space._minima, space._slot, space._box, ball, y, x) for y, x in pixels]
    from_ball = [nearest_depth(space.depth, ball, y, x) for y, x in pixels]
    assert from_rows == from_ball
    assert np.isfinite(from_ball).mean() > 0.2 and np.isinf(from_ball).mean() > 0.2
    # a box away from the edges: the columns beyond it count as unmeasured
    inner = np.zeros_like(depth)
    inner[100:140, 140:180] = rng.uniform(0.5, 2.0, (40, 40))
    space = FreeSpace(inner, INTR, np.eye(4))
    assert space._box[2] > 0 and space._box[3] < INTR.width
    for y, x in zip(*np.mgrid[95:145, 0:INTR.width].reshape(2, -1)):     # every pixel of its rows
        assert nearest_by_rows(space._minima, space._slot, space._box, ball, y, x) == \
            nearest_depth(space.depth, ball, y, x)
    # mostly measured (a room) and nothing measured
    room = np.full_like(depth, 2.0)
    room[rng.uniform(size=depth.shape) < 0.05] = 0
    room[60:80, 100:140] = 0
    for image in (room, np.zeros_like(depth)):
        space = FreeSpace(image, INTR, np.eye(4))
        from_rows = [nearest_by_rows(space._minima, space._slot, space._box, ball, y, x) for y, x in pixels]
        assert from_rows == [nearest_depth(space.depth, ball, y, x) for y, x in pixels]
    assert np.isinf(from_rows).all()
