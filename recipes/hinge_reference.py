"""A careful reference for a hinged part's per-frame state, independent of `interreal motions`: two points of the part
marked in every frame (here the laptop screen's top corners, `tests/fixtures/laptop/lid_corners.json`, made with
`recipes/track_corners.py` and checked by eye), the static scene's cameras from transforms.json, and one bundle
adjustment of a rigid pair of points turning about a fixed axis (axis, the points at the first marked frame, one
angle per frame) against the marks' reprojection. The labels only say which way is "open"; states are
(angle - most closed) / (most open - most closed) over the marked frames: 0 = the most closed, 1 = the most open.

Why two points suffice: the pair's line is parallel to the hinge (a check, `edge_axis_deg`), every frame fixes its
angle from four image coordinates, and the frames where the part rests see the same points from many cameras.
`point_spread` (the state from each point alone, RMS difference) measures the marks' own noise.

    python recipes/hinge_reference.py DS --marks tests/fixtures/laptop/lid_corners.json [--out ref.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares, minimize_scalar
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

import benchlib  # noqa: F401 - puts the repository on sys.path

from interreal.conventions import frame_index, opengl_to_opencv
from interreal.dataset import load_dataset, read_labels

STARTS = 4  # initial hinge offsets tried about the marked edge (a quarter turn apart); the cheapest fit is kept
LID_DEPTH = 0.6  # initial distance of the hinge from the marked edge, in units of the edge's length


@dataclass
class HingeReference:
    """frames (F,) source indices; theta_deg (F,) the part's turn from the first frame; states (F,) 0..1."""

    frames: np.ndarray
    theta_deg: np.ndarray
    states: np.ndarray
    axis: np.ndarray
    point: np.ndarray
    err_px: np.ndarray  # (F, P) reprojection error of each mark (nan where not marked)
    edge_axis_deg: float
    point_spread: float

    def figures(self) -> dict:
        e = self.err_px[np.isfinite(self.err_px)]
        return {"frames": int(len(self.frames)), "range_deg": round(float(np.ptp(self.theta_deg)), 2),
                "err_px_median": round(float(np.median(e)), 2), "err_px_p90": round(float(np.percentile(e, 90)), 2),
                "edge_axis_deg": round(self.edge_axis_deg, 2), "point_spread": round(self.point_spread, 4),
                "most_closed": int(self.frames[np.argmin(self.states)]),
                "most_open": int(self.frames[np.argmax(self.states)])}

    def state_of(self) -> dict[int, float]:
        return {int(f): float(s) for f, s in zip(self.frames, self.states)}


def _project(w2c: np.ndarray, X: np.ndarray) -> np.ndarray:
    """w2c (F, 3, 4) OpenCV, X (F, P, 3) world -> (F, P, 2) normalised image coordinates."""
    Xc = np.einsum("fij,fpj->fpi", w2c[:, :, :3], X) + w2c[:, None, :, 3]
    return Xc[..., :2] / Xc[..., 2:3]


def _turned(X0: np.ndarray, p: np.ndarray, a: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """X0 (P, 3) turned by theta (F,) radians about the axis a through p -> (F, P, 3)."""
    R = Rotation.from_rotvec(theta[:, None] * a[None]).as_matrix()
    return np.einsum("fij,pj->fpi", R, X0 - p) + p


def _triangulate(w2c: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Linear triangulation of one point from (N, 3, 4) cameras and (N, 2) normalised observations."""
    rows = [np.stack([u * P[2] - P[0], v * P[2] - P[1]]) for P, (u, v) in zip(w2c, uv)]
    _, _, vt = np.linalg.svd(np.concatenate(rows))
    return vt[-1, :3] / vt[-1, 3]


def _best_angles(w2c: np.ndarray, obs: np.ndarray, focal: float, p: np.ndarray, a: np.ndarray, X: np.ndarray
                 ) -> np.ndarray:
    """Each frame's turn (F,) on a 1 deg grid over the whole circle, the rest held: a frame started at the wrong
    side of a view where the turn moves the marks little falls into a mirrored minimum otherwise."""
    grid = np.radians(np.arange(-180.0, 180.0, 1.0))
    Xc = np.einsum("fij,gpj->fgpi", w2c[:, :, :3], _turned(X, p, a, grid)) + w2c[:, None, None, :, 3]
    r2 = np.sum(((Xc[..., :2] / Xc[..., 2:3]) - obs[:, None]) ** 2, axis=-1) * focal ** 2  # (F, G, P)
    cost = np.sum(np.where(np.isfinite(r2), np.log1p(r2 / 2.25), 0.0), axis=-1)
    cost[(Xc[..., 2] <= 0).any(-1)] = np.inf
    return grid[np.argmin(cost, axis=1)]


def _across(a: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to a."""
    u = np.cross(a, [0.0, 0.0, 1.0] if abs(a[2]) < 0.9 else [1.0, 0.0, 0.0])
    return u / np.linalg.norm(u)


def fit(w2c: np.ndarray, obs: np.ndarray, focal: float, rest: list[int]) -> tuple[np.ndarray, float]:
    """w2c (F, 3, 4), obs (F, P, 2) normalised marks (nan: not marked), rest: positions of frames where the part
    is at the first frame's pose (for the start only). Returns the parameters and the cost."""
    n, P = obs.shape[:2]
    X0 = np.array([_triangulate(w2c[rest], obs[rest, k]) for k in range(P)])
    edge = X0[-1] - X0[0]
    a0 = edge / np.linalg.norm(edge)
    ok = np.isfinite(obs)
    obs0 = np.where(ok, obs, 0.0)
    n_glob = 6 + 3 * P

    def unpack(x):
        return x[:3], x[3:6] / np.linalg.norm(x[3:6]), x[6:n_glob].reshape(P, 3), np.r_[0.0, x[n_glob:]]

    def resid(x):
        p, a, X, th = unpack(x)
        r = np.where(ok, (_project(w2c, _turned(X, p, a, th)) - obs0) * focal, 0.0).ravel()
        gauge = [1e3 * float((p - X.mean(0)) @ a), 1e3 * (float(np.linalg.norm(x[3:6])) - 1.0)]
        return np.r_[r, gauge]

    def solve(x0):
        return least_squares(resid, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=1.5, x_scale="jac",
                             max_nfev=300)

    def regrid(x):
        p, a, X, _ = unpack(x)
        th = _best_angles(w2c, obs, focal, p, a, X)
        return np.r_[x[:n_glob], th[1:] - th[0]]

    sparsity = lil_matrix((n * P * 2 + 2, n_glob + n - 1), dtype=int)
    sparsity[:, :n_glob] = 1
    for f in range(1, n):
        sparsity[f * P * 2:(f + 1) * P * 2, n_glob + f - 1] = 1
    best = None
    for k in range(STARTS):
        off = Rotation.from_rotvec(a0 * (np.pi / 2 * k)).apply(_across(a0))
        p0 = X0.mean(0) + LID_DEPTH * np.linalg.norm(edge) * off
        sol = solve(regrid(np.r_[p0, a0, X0.ravel(), np.zeros(n - 1)]))
        again = regrid(sol.x)
        if np.max(np.abs(np.angle(np.exp(1j * (again[n_glob:] - sol.x[n_glob:]))))) > np.radians(2.0):
            sol = min(sol, solve(again), key=lambda s: s.cost)
        if best is None or sol.cost < best.cost:
            best = sol
    return best.x, float(best.cost)


def reference(w2c: np.ndarray, obs: np.ndarray, focal: float, frames: np.ndarray, rest: list[int],
              opens_with: dict[int, float]) -> HingeReference:
    """The fit, its states oriented by `opens_with` (frame -> a label: only the sign of its trend is used), and its
    checks (`HingeReference`)."""
    n, P = obs.shape[:2]
    x, _ = fit(w2c, obs, focal, rest)
    p, a, X0 = x[:3], x[3:6] / np.linalg.norm(x[3:6]), x[6:6 + 3 * P].reshape(P, 3)
    th = np.angle(np.exp(1j * np.r_[0.0, x[6 + 3 * P:]]))  # a turn and a turn + 2 pi are the same pose
    err = np.linalg.norm(_project(w2c, _turned(X0, p, a, th)) - obs, axis=-1) * focal
    lab = [(np.flatnonzero(frames == f)[0], v) for f, v in opens_with.items() if f in set(frames.tolist())]
    sign = 1.0
    if len(lab) >= 2:
        pos, val = np.array([i for i, _ in lab]), np.array([v for _, v in lab])
        sign = 1.0 if np.corrcoef(th[pos], val)[0, 1] >= 0 else -1.0
    s = sign * th
    states = (s - s.min()) / max(float(np.ptp(s)), 1e-12)
    edge = X0[-1] - X0[0]
    edge_axis = float(np.degrees(np.arccos(min(1.0, abs(edge @ a) / np.linalg.norm(edge)))))
    spread = _point_spread(w2c, obs, focal, p, a, X0, th) / max(float(np.ptp(th)), 1e-12)
    return HingeReference(frames, np.degrees(th), states, a, p, err, edge_axis, spread)


def _point_spread(w2c, obs, focal, p, a, X0, th) -> float:
    """RMS difference (radians) between the angles the first and the last mark give alone, frame by frame."""
    diffs = []
    for f in range(len(th)):
        one = []
        for k in (0, X0.shape[0] - 1):
            if not np.isfinite(obs[f, k]).all():
                break
            cost = lambda t: float(np.sum((_project(w2c[f:f + 1], _turned(X0[k:k + 1], p, a, np.array([t])))[0, 0]
                                           - obs[f, k]) ** 2))
            one.append(minimize_scalar(cost, bounds=(th[f] - 0.3, th[f] + 0.3), method="bounded").x)
        if len(one) == 2:
            diffs.append(one[0] - one[1])
    return float(np.sqrt(np.mean(np.square(diffs)))) if diffs else float("nan")


def marks_in(ds_root: Path, marks: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The dataset's frames that are marked: (frames, w2c (F, 3, 4), obs (F, P, 2) normalised, focal px)."""
    import cv2

    ds = load_dataset(ds_root)
    by_index = {fr.index: fr for fr in ds.frames if fr.c2w is not None}
    size = marks.get("size")  # the marks' pixel grid (the video's); the dataset's images may be smaller
    zoom = ds.frame_intrinsics(ds.frames[0]).w / float(size[0]) if size else 1.0
    rows = {int(k): zoom * np.array([c if c is not None else [np.nan, np.nan] for c in v], float)
            for k, v in marks["frames"].items()}
    rows = {k: v for k, v in rows.items() if np.isfinite(v).any()}  # null: outside the image, not marked
    frames = np.array(sorted(set(rows) & set(by_index)))
    if len(frames) < 3:
        raise SystemExit(f"only {len(frames)} marked frames have a camera in {ds_root}")
    w2c, obs = [], []
    for f in frames:
        fr = by_index[f]
        K = ds.frame_intrinsics(fr)
        w2c.append(np.linalg.inv(opengl_to_opencv(fr.c2w))[:3])
        uv = rows[f].reshape(-1, 2)
        und = cv2.undistortPoints(np.nan_to_num(uv)[:, None], K.K(), K.dist())[:, 0]
        obs.append(np.where(np.isfinite(uv), und, np.nan))
    return frames, np.asarray(w2c), np.asarray(obs), float(ds.frame_intrinsics(by_index[frames[0]]).fl_x)


def first_object_labels(ds_root: Path) -> dict[int, float]:
    """Source frame index -> the dataset's label of its first labelled object (only their trend is used)."""
    return {frame_index(k): float(next(iter(v.values()))) for k, v in read_labels(ds_root).items() if v}


def from_files(ds_root: Path, marks_file: Path, labels: dict[int, float]) -> HingeReference:
    marks = json.loads(Path(marks_file).read_text())
    frames, w2c, obs, focal = marks_in(Path(ds_root), marks)
    rest_frames = marks.get("rest", [int(frames[0]), int(frames[min(len(frames) - 1, 20)])])
    rest = [int(np.flatnonzero(frames == f)[0]) for f in rest_frames if f in set(frames.tolist())]
    return reference(w2c, obs, focal, frames, rest, labels)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n")[-1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", type=Path)
    p.add_argument("--marks", type=Path, required=True, help="JSON: {frames: {index: [[x, y], ...]}, rest: [...]}")
    p.add_argument("--out", type=Path, default=None, help="write the per-frame states and figures here (JSON)")
    args = p.parse_args()
    labels = first_object_labels(args.dataset)
    ref = from_files(args.dataset, args.marks, labels)
    print(json.dumps(ref.figures()))
    if args.out:
        from interreal.atomic import write_json

        write_json(args.out, {**ref.figures(), "states": {str(k): round(v, 4) for k, v in ref.state_of().items()},
                              "axis": ref.axis.round(4).tolist()})


if __name__ == "__main__":
    main()
