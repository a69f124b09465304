"""The silhouette route of `interreal motions`: a plain part's motion from its masks and the known cameras."""

from __future__ import annotations

import cv2
import numpy as np
from conftest import arc_camera, moved_front, silhouette, views_dataset
from edge_scenes import truth_states

from interreal.dataset import known_states
from interreal.motions.silhouette import front_corners, measure_silhouettes

W, H = 640, 480
K = np.array([[600.0, 0, W / 2], [0, 600.0, H / 2], [0, 0, 1]])
FRONT = np.array([[-0.2, 0.0, 0.1], [0.2, 0.0, 0.1], [0.2, 0.0, -0.1], [-0.2, 0.0, -0.1]])  # z up, facing -y


def capture(kind: str, sweep_deg: float = 60.0, n: int = 50, dist: np.ndarray | None = None,
            aim: tuple[float, float, float] = (0.0, 0.0, 0.0)):
    """A duck-typed dataset of n frames: cameras on an arc 1.5 units away, and the part's masks: a drawer (the
    prism its front sweeps, 0.15 units at state 1) or a door (its front turned up to 70 deg about its left edge);
    the cameras look at `aim` (the part off the image's centre) through a lens with `dist`."""
    states = truth_states(n, start=15)
    c2ws, masks = [], []
    for i, s in enumerate(states):
        c2ws.append(arc_camera(-sweep_deg / 2 + sweep_deg * i / (n - 1), 1.5, 0.3, aim))
        m, _ = silhouette(moved_front(FRONT, kind, s, 0.15, 70.0), c2ws[-1], K, (W, H))
        if dist is not None:  # what a lens with this distortion records: each pixel looks up its pinhole position
            m = cv2.remap(m, *lens_map(dist), cv2.INTER_NEAREST)
        masks.append(m)
    ds = views_dataset(c2ws, masks, K, dist)
    labelled = np.zeros(n, bool)
    labelled[[0, 5, 10, 14, 25, 30, 34, 45, 49]] = True
    st, kn = known_states(np.arange(n, dtype=float), np.where(labelled, states, 0)[:, None], labelled[:, None])
    return ds, states, st[:, 0], kn[:, 0], labelled


def lens_map(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y): for every pixel of the distorted image, where it lies in the pinhole image."""
    ys, xs = np.mgrid[:H, :W].astype(np.float32)
    und = cv2.undistortPoints(np.stack([xs, ys], -1).reshape(-1, 1, 2), K, dist, P=K).reshape(H, W, 2)
    return np.ascontiguousarray(und[..., 0]), np.ascontiguousarray(und[..., 1])


def measure(kind: str) -> tuple:
    """The route on a simulated plain part: (motion, figures, state RMSE against the truth); the right kind."""
    ds, truth, st, kn, labelled = capture(kind)
    motion, fig = measure_silhouettes(ds, 0, st, kn, labelled, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert motion.kind == kind
    rows = np.array(fig["frame_states"])
    return motion, fig, float(np.sqrt(np.mean((rows[:, 1] - truth[rows[:, 0].astype(int)]) ** 2)))


def off_deg(axis: np.ndarray, truth: list[float]) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(axis @ truth)))))


def test_front_corners_are_sub_pixel():
    m = np.zeros((120, 160), np.uint8)
    quad = np.array([[40.3, 30.6], [120.2, 25.1], [118.7, 90.4], [42.5, 95.8]])
    cv2.fillConvexPoly(m, np.round(quad * 16).astype(np.int32), 1, shift=4)
    got = front_corners(m > 0)
    assert got is not None and np.abs(got - quad).max() < 0.8, got
    m[:, :45] = 1                                    # touches the border: a cut part has no trustworthy corners
    assert front_corners(m > 0) is None


def test_plain_drawer_is_measured_as_a_slide_from_its_silhouettes():
    motion, fig, rmse = measure("slide")
    assert off_deg(motion.axis, [0.0, 1.0, 0.0]) < 1.0, motion.axis
    assert abs(motion.range - 0.15) / 0.15 < 0.03, motion.range
    assert rmse < 0.03
    assert fig["silhouette_iou"]["slide"] > max(v for k, v in fig["silhouette_iou"].items() if k != "slide")


def test_plain_door_is_measured_as_a_hinge_about_its_edge():
    motion, fig, rmse = measure("hinge")
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 1.0, motion.axis
    assert abs(np.degrees(motion.range) - 70) < 3, np.degrees(motion.range)
    off = motion.origin - FRONT[0]
    assert np.linalg.norm(off - (off @ motion.axis) * motion.axis) < 0.01        # on the left edge
    assert rmse < 0.05


def test_views_that_barely_move_are_refused_with_the_cause():
    ds, truth, st, kn, labelled = capture("slide", sweep_deg=1.0)
    motion, fig = measure_silhouettes(ds, 0, st, kn, labelled, min_pixels=50)
    assert motion is None, fig
    # the front from a run of frames 1 deg apart is refused, or the motion from it fits nothing
    assert "not pinned down" in fig["silhouette_reason"] or "overlap" in fig["silhouette_reason"], fig


def test_motions_stage_takes_the_silhouette_route(tmp_path):
    """`--route silhouette` tries it first; an accepted motion ends the search (no SfM, no PnP is run)."""
    from interreal.motions import part as motions

    ds, truth, st, kn, labelled = capture("slide")
    cfg = motions.MotionConfig(route="silhouette", min_pixels=50)
    motion, fig = motions.measure_part(None, ds, [], tmp_path, st, kn, cfg, labelled=labelled, obj=0)
    assert motion is not None and motion.kind == "slide" and fig["accepted"]
    assert list(fig["routes"]) == ["silhouette"] and fig["routes"]["silhouette"]["accepted"]


def test_front_from_a_run_where_it_rests_when_labels_are_few():
    """Two labels only (closed at frame 5, open at frame 30): no known state shows the front in six frames, so it is
    triangulated from a run of frames where it rests; the slide is still measured."""
    ds, truth, _, _, _ = capture("slide")
    n = len(truth)
    labelled = np.zeros(n, bool)
    labelled[[5, 30]] = True
    st, kn = known_states(np.arange(n, dtype=float), np.where(labelled, truth, 0)[:, None], labelled[:, None])
    motion, fig = measure_silhouettes(ds, 0, st[:, 0], kn[:, 0], labelled, min_pixels=50)
    assert motion is not None and motion.kind == "slide" and fig["front_state"] is None, fig
    assert off_deg(motion.axis, [0.0, 1.0, 0.0]) < 1.5 and abs(motion.range - 0.15) / 0.15 < 0.05, motion


def test_a_refused_motion_names_what_the_other_routes_said():
    from interreal.motions import routes_text

    fig = {"route": "sfm", "routes": {"sfm": {"kind": "hinge", "reason": "its reconstruction turned"},
                                      "pnp": {"kind": None, "reason": None},
                                      "silhouette": {"kind": None, "reason": "the part's front is not pinned down"}}}
    text = routes_text(fig)
    assert text == "; the other routes: pnp: no motion; silhouette: the part's front is not pinned down", text
    assert routes_text({"route": "sfm", "routes": {"sfm": {}}}) == ""


def test_lens_distortion_is_taken_into_account():
    """Masks recorded through a phone-like lens (k1 = 0.2) with the part off the image's centre: the corners are
    undistorted before triangulation, so the front lands within 5 mm of the truth (1.7-3.4 mm; 13-16 mm at two
    corners with the lens ignored), and the silhouettes are bent by the lens: the drawer still measures as a slide."""
    from interreal.conventions import opengl_to_opencv
    from interreal.motions.silhouette import Views, find_front

    ds, truth, st, kn, labelled = capture("slide", dist=np.array([0.2, 0.0, 0.0, 0.0, 0.0]), aim=(-0.3, 0.0, -0.2))
    masks = [ds.load_mask(f)[..., 0] for f in ds.frames]
    w2c = np.stack([np.linalg.inv(opengl_to_opencv(f.c2w)) for f in ds.frames])
    face, fig = find_front(Views(masks, w2c, K, ds.intrinsics.dist()), st, kn)
    assert face is not None and np.linalg.norm(face - FRONT, axis=1).max() < 0.005, (face, fig)
    motion, fig = measure_silhouettes(ds, 0, st, kn, labelled, min_pixels=50)
    assert motion is not None and motion.kind == "slide" and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 1.0, 0.0]) < 1.5 and abs(motion.range - 0.15) / 0.15 < 0.08, motion  # 1.0, 5 %


def test_view_spread_is_the_widest_angle_between_cameras_seen_from_the_part():
    """What a refusal states instead of "the views are too close together": cameras 90 deg apart around a point."""
    from interreal.motions.silhouette import view_spread_deg

    w2c = []
    for deg in (0.0, 30.0, 90.0):
        a = np.radians(deg)
        c = np.array([np.sin(a), 0.0, -np.cos(a)]) * 2.0  # on a circle about the origin
        r = np.eye(3)
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, -r @ c
        w2c.append(m)
    assert abs(view_spread_deg(np.zeros(3), np.stack(w2c)) - 90.0) < 1e-6


def test_frames_no_displacement_explains_are_not_measured():
    """Masks a flat front cannot make (here: four frames of the opening door replaced by a disc, as when a door is
    edge-on with its inside in view) are left out, not measured by the best wrong angle; the rest still measure."""
    ds, truth, st, kn, labelled = capture("hinge")
    masks = [ds.load_mask(f).copy() for f in ds.frames]
    for i in (18, 19, 20, 21):
        disc = np.zeros((H, W), np.uint8)
        cv2.circle(disc, (W // 2, H // 2), 60, 1, -1)
        masks[i] = disc[..., None] > 0
    ds.load_mask = lambda f: masks[f.index]
    motion, fig = measure_silhouettes(ds, 0, st, kn, labelled, min_pixels=50)
    assert motion is not None and fig["accepted"] and fig["silhouette_unfit_frames"] >= 4, fig
    measured = dict(fig["frame_states"])
    assert not {18, 19, 20, 21} & set(measured)
    assert abs(np.degrees(motion.range) - 70) < 3


def test_overlaps_counted_at_once_equal_the_plain_count_with_an_occluder_and_a_point_behind_the_camera():
    """`Silhouettes.ious` (a grid of shapes, one projection) and `iou` (one shape) are the same overlap as the plain
    count: the convex silhouette less what the occluder hides, against the mask, in the crop; 0 behind the camera."""
    from interreal.motions.silhouette import Silhouettes, Views

    masks = [np.zeros((H, W), bool) for _ in range(2)]
    masks[0][150:330, 200:420] = True
    masks[1][100:300, 260:500] = True
    occ = np.zeros((H, W), bool)
    occ[200:260, :] = True  # an arm across the part and beyond it
    w2c = np.stack([np.eye(4), np.eye(4)])
    w2c[1, :3, 3] = (-0.1, 0.05, 0.2)
    sil = Silhouettes(Views(masks, w2c, K, occluders=[None, occ]), [0, 1])
    rng = np.random.default_rng(3)
    shapes = np.concatenate([rng.normal((0.0, 0.0, 2.0), (0.3, 0.3, 0.5), (40, 8, 3)),
                             [[[0.0, 0.0, -1.0]] + [[0.1, 0.1, 2.0]] * 7],  # one corner behind the camera
                             [[[50.0, 50.0, 1.0]] * 8]])  # far off the image
    for i in (0, 1):
        (x0, y0), m = sil.crop[i].corner, sil.crop[i].mask > 0
        hidden = np.zeros_like(m) if sil.crop[i].hidden is None else sil.crop[i].hidden > 0
        plain = []
        for s in shapes:
            if (s @ w2c[i, 2, :3] + w2c[i, 2, 3] <= 1e-6).any():
                plain.append(0.0)
                continue
            uv, _ = cv2.projectPoints(s, *sil.pose[i], sil.k, sil.dist)
            uv = np.clip(uv.reshape(-1, 2) - (x0, y0), -4 * max(m.shape), 4 * max(m.shape))
            pred = np.zeros(m.shape, np.uint8)
            cv2.fillConvexPoly(pred, cv2.convexHull(np.round(uv * 16).astype(np.int32)), 1, shift=4)
            pred = (pred > 0) & ~hidden
            plain.append((pred & m).sum() / max(1, (pred | m).sum()))
        at_once = sil.ious(shapes, i)
        assert at_once.tolist() == [sil.iou(s, i) for s in shapes] == plain
        assert at_once[-2] == 0.0 and at_once[-1] == 0.0 and 0.2 < at_once.max() < 1.0
    assert sil.crop[1].hidden is not None and sil.crop[1].hidden.any() and sil.crop[0].hidden is None
