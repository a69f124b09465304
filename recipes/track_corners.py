"""Mark a bright quadrilateral's corners (a screen in its dark bezel) in every frame of a video, for a careful
reference (`recipes/hinge_reference.py`): one start quad typed by hand, then frame to frame a RANSAC homography of
SIFT matches inside the quad moves it, and each side snaps to the strongest bright-inside edge within SNAP_PX of
where it landed (a robust line through 40 edge samples); a corner keeps the snapped position only where the snap
agrees with the tracked one within AGREE_PX, so a hand on an edge does not pull it. A corner outside the image is
written as null: it is carried on by the homography, not marked. Check the result by eye
(`--sheet`): this is an annotation tool, its output is trusted only once looked at.

    python recipes/track_corners.py ../shared/data/laptop/laptop_orbit.mp4 --quad 373,241 536,142 545,288 402,408 \\
        --keep 0,1 --rest 0,20 --out tests/fixtures/laptop/lid_corners.json --sheet /tmp/sheet.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

SNAP_PX = 6.0  # how far from the tracked side its edge is searched
AGREE_PX = 4.0  # a snapped corner further than this from the tracked one is not trusted


def edge_line(gx: np.ndarray, gy: np.ndarray, a: np.ndarray, b: np.ndarray, centre: np.ndarray, samples: int = 40
              ) -> tuple[np.ndarray, np.ndarray] | None:
    """The side a-b moved onto the strongest edge with the brighter side towards `centre`: (point, direction), or
    None where fewer than 6 samples found one."""
    d = (b - a) / np.linalg.norm(b - a)
    nrm = np.array([-d[1], d[0]])
    if nrm @ ((a + b) / 2 - centre) < 0:
        nrm = -nrm  # outward
    offs = np.arange(-SNAP_PX, SNAP_PX + 0.25, 0.5)
    pts = []
    for t in np.linspace(0.12, 0.88, samples):
        q = (a + t * (b - a))[None] + offs[:, None] * nrm[None]
        g = cv2.remap(np.dstack([gx, gy]), q[:, :1].astype(np.float32), q[:, 1:].astype(np.float32),
                      cv2.INTER_LINEAR)[:, 0]
        resp = -(g @ nrm)  # intensity falls outward
        j = int(np.argmax(resp))
        if 0 < j < len(offs) - 1 and resp[j] > 0:
            pts.append(q[j])
    if len(pts) < 6:
        return None
    P = np.asarray(pts)
    keep = np.ones(len(P), bool)
    for _ in range(3):
        c = P[keep].mean(0)
        direction = np.linalg.svd(P[keep] - c)[2][0]
        res = np.abs((P - c) @ np.array([-direction[1], direction[0]]))
        keep = res < max(1.0, 2.5 * float(np.median(res[keep])))
    return c, direction


def snap(gray: np.ndarray, quad: np.ndarray) -> np.ndarray:
    """quad (4, 2) in order around -> each corner where its two sides' edge lines cross (unchanged where a side
    found no edge)."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.2)
    gx, gy = cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1)
    lines = [edge_line(gx, gy, quad[k], quad[(k + 1) % 4], quad.mean(0)) for k in range(4)]
    out = quad.copy()
    for k in range(4):
        l1, l2 = lines[(k - 1) % 4], lines[k]
        if l1 is not None and l2 is not None:
            A = np.array([l1[1], -l2[1]]).T
            if abs(np.linalg.det(A)) > 1e-6:
                out[k] = l1[0] + np.linalg.solve(A, l2[0] - l1[0])[0] * l1[1]
    return out


def track(frames: list[np.ndarray], quad: np.ndarray) -> list[np.ndarray]:
    """The quad in every frame (grey images), starting from `quad` in the first."""
    sift = cv2.SIFT_create(2000)
    q = snap(frames[0], quad.astype(np.float64))
    out = [q]
    for g1, g2 in tqdm(list(zip(frames[:-1], frames[1:])), desc="corners", unit="frame"):
        m = np.zeros_like(g1)
        cv2.fillConvexPoly(m, q.astype(np.int32), 255)
        m = cv2.dilate(m, np.ones((15, 15), np.uint8))
        k1, d1 = sift.detectAndCompute(g1, m)
        k2, d2 = sift.detectAndCompute(g2, cv2.dilate(m, np.ones((61, 61), np.uint8)))
        good = [a for a, b in cv2.BFMatcher().knnMatch(d1, d2, k=2) if a.distance < 0.75 * b.distance]
        if len(good) < 8:
            raise SystemExit(f"lost the quad after {len(out)} frames ({len(good)} matches): start again from there")
        H, _ = cv2.findHomography(np.float32([k1[a.queryIdx].pt for a in good]),
                                  np.float32([k2[a.trainIdx].pt for a in good]), cv2.RANSAC, 2.0)
        moved = cv2.perspectiveTransform(q[None], H)[0]
        snapped = snap(g2, moved)
        q = np.where(np.linalg.norm(snapped - moved, axis=1)[:, None] < AGREE_PX, snapped, moved)
        out.append(q)
    return out


def _mark(corner: np.ndarray, shape: tuple[int, ...]) -> list[float] | None:
    """A corner as written: None where it lies outside the image (the homography's guess, not a mark)."""
    x, y = float(corner[0]), float(corner[1])
    if not (0 <= x <= shape[1] - 1 and 0 <= y <= shape[0] - 1):
        return None
    return [round(x, 1), round(y, 1)]


def contact_sheet(images: list[np.ndarray], quads: list[np.ndarray], every: int, path: Path) -> None:
    """Crops around the quad every `every` frames, the quad drawn, for checking by eye."""
    tiles = []
    for i in range(0, len(images), every):
        q = quads[i]
        x0, y0 = np.maximum(np.floor(q.min(0) - 20).astype(int), 0)
        x1, y1 = np.ceil(q.max(0) + 20).astype(int)
        z = 320 / max(y1 - y0, x1 - x0)
        c = cv2.resize(images[i][y0:y1, x0:x1], None, fx=z, fy=z, interpolation=cv2.INTER_CUBIC)
        cv2.polylines(c, [((q - [x0, y0]) * z).astype(np.int32)], True, (0, 255, 0), 1)
        tile = np.zeros((320, 320, 3), np.uint8)
        tile[:c.shape[0], :c.shape[1]] = c[:320, :320]
        cv2.putText(tile, str(i), (5, 22), 0, 0.7, (0, 255, 255), 2)
        tiles.append(tile)
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % 6)
    cv2.imwrite(str(path), np.vstack([np.hstack(tiles[r:r + 6]) for r in range(0, len(tiles), 6)]))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__.split("\n\n")[-1],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("video", type=Path)
    p.add_argument("--quad", nargs=4, required=True, metavar="X,Y", help="the first frame's corners, in order around")
    p.add_argument("--keep", default="0,1,2,3", help="which corners to write (default all)")
    p.add_argument("--rest", default="", help="frames where the part rests as in the first (for the reference)")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--sheet", type=Path, default=None, help="also write a contact sheet every 10 frames")
    args = p.parse_args()
    cap = cv2.VideoCapture(str(args.video))
    images = []
    while True:
        ok, im = cap.read()
        if not ok:
            break
        images.append(im)
    if not images:
        raise SystemExit(f"no frames read from {args.video}")
    quad = np.array([[float(v) for v in s.split(",")] for s in args.quad])
    quads = track([cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in images], quad)
    keep = [int(k) for k in args.keep.split(",")]
    from interreal.atomic import write_json

    write_json(args.out, {"what": f"corners {keep} of the quad tracked from {args.quad} in {args.video.name}",
                          "rest": [int(v) for v in args.rest.split(",") if v],
                          "size": [int(images[0].shape[1]), int(images[0].shape[0])],  # the marks' pixel grid
                          "frames": {str(i): [_mark(c, images[0].shape) for c in q[keep]]
                                     for i, q in enumerate(quads)}})
    if args.sheet:
        contact_sheet(images, quads, 10, args.sheet)


if __name__ == "__main__":
    import benchlib  # noqa: F401 - puts the repository on sys.path

    main()
