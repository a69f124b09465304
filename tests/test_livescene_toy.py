"""A toy articulated room rendered by a numpy ray caster, for the livescene tests (no simulator needed).

Room walls with smooth procedural textures, a static box, a door (object 0) turning on a vertical hinge and,
optionally, a drawer (object 1) sliding out. `toy_dataset` writes a valid LiveScene dataset; `ToyScene.render`
renders any OpenGL camera at any states (the truth for novel-state checks).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from interreal import dataset as D
from interreal.atomic import write_image
from interreal.conventions import fid_of_index, frame_name, index_to_onehot, opencv_to_opengl

NAMES = ["door", "drawer"]


def _texture(u: np.ndarray, v: np.ndarray, base: tuple[float, float, float], f: float) -> np.ndarray:
    pat = 0.75 + 0.25 * np.sin(f * u) * np.cos(f * 0.7 * v)
    return np.clip(np.asarray(base)[None] * pat[:, None], 0, 1)


@dataclass
class ToyScene:
    n_objects: int = 1

    def _quads(self, states: np.ndarray):
        """(origin, edge_u, edge_v, colour fn, id) per rectangle; id 0 = static, k = object k-1."""
        quads = []
        half, top = 2.0, 2.5
        walls = [((-half, -half, 0), (2 * half, 0, 0), (0, 2 * half, 0), (0.6, 0.55, 0.5), 2.0),  # floor
                 ((-half, -half, top), (2 * half, 0, 0), (0, 2 * half, 0), (0.9, 0.9, 0.85), 1.0),  # ceiling
                 ((-half, -half, 0), (2 * half, 0, 0), (0, 0, top), (0.3, 0.5, 0.8), 3.0),
                 ((-half, half, 0), (2 * half, 0, 0), (0, 0, top), (0.8, 0.7, 0.3), 2.5),
                 ((-half, -half, 0), (0, 2 * half, 0), (0, 0, top), (0.4, 0.75, 0.4), 3.5),
                 ((half, -half, 0), (0, 2 * half, 0), (0, 0, top), (0.7, 0.4, 0.6), 2.0)]
        for o, eu, ev, col, f in walls:
            quads.append((np.array(o, float), np.array(eu, float), np.array(ev, float), col, f, 0))
        # static box (5 visible faces)
        lo, hi = np.array([0.3, -0.9, 0.0]), np.array([0.9, -0.3, 0.6])
        quads += self._box_faces(lo, hi, (0.2, 0.6, 0.6), 8.0, 0)
        # door: hinge at (-0.9, 0.6), 0.8 wide, 1.3 tall, turns 90 degrees
        a = np.pi / 2 * float(states[0])
        eu = 0.8 * np.array([np.cos(a), np.sin(a), 0.0])
        quads.append((np.array([-0.9, 0.6, 0.0]), eu, np.array([0, 0, 1.3]), (0.85, 0.25, 0.2), 9.0, 1))
        if self.n_objects > 1:
            off = 0.45 * float(states[1])
            lo, hi = np.array([0.8 - off, 0.5, 0.2]), np.array([1.4 - off, 1.0, 0.5])
            quads += self._box_faces(lo, hi, (0.95, 0.8, 0.2), 12.0, 2)
        return quads

    @staticmethod
    def _box_faces(lo, hi, col, f, oid):
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        return [(np.array([x0, y0, z1]), np.array([x1 - x0, 0, 0]), np.array([0, y1 - y0, 0]), col, f, oid),
                (np.array([x0, y0, z0]), np.array([x1 - x0, 0, 0]), np.array([0, 0, z1 - z0]), col, f, oid),
                (np.array([x0, y1, z0]), np.array([x1 - x0, 0, 0]), np.array([0, 0, z1 - z0]), col, f, oid),
                (np.array([x0, y0, z0]), np.array([0, y1 - y0, 0]), np.array([0, 0, z1 - z0]), col, f, oid),
                (np.array([x1, y0, z0]), np.array([0, y1 - y0, 0]), np.array([0, 0, z1 - z0]), col, f, oid)]

    def render(self, c2w_gl: np.ndarray, states, intr: D.Intrinsics) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb uint8 (H, W, 3), z-depth (H, W), index map uint8 (H, W)) of an OpenGL camera."""
        from livescene.data import camera_rays

        o, d, zs = camera_rays(c2w_gl, intr)
        o, d = o.astype(np.float64), d.astype(np.float64)
        n = d.shape[0]
        best = np.full(n, np.inf)
        rgb = np.zeros((n, 3))
        idx = np.zeros(n, np.uint8)
        for p0, eu, ev, col, f, oid in self._quads(np.asarray(states, float)):
            nrm = np.cross(eu, ev)
            denom = d @ nrm
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((p0 - o) @ nrm) / denom
            hit = o + d * t[:, None] - p0
            u = hit @ eu / (eu @ eu)
            v = hit @ ev / (ev @ ev)
            ok = (np.abs(denom) > 1e-9) & (t > 1e-4) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1) & (t < best)
            if not ok.any():
                continue
            best[ok] = t[ok]
            rgb[ok] = _texture(u[ok] * np.linalg.norm(eu), v[ok] * np.linalg.norm(ev), col, f)
            idx[ok] = oid
        h, w = intr.h, intr.w
        img = (np.clip(rgb, 0, 1) * 255).round().astype(np.uint8).reshape(h, w, 3)
        return img, (best * zs).reshape(h, w).astype(np.float32), idx.reshape(h, w)


def look_at_gl(eye, target, up=(0, 0, 1.0)) -> np.ndarray:
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, :3] = np.stack([x, y, z], 1)
    m[:3, 3] = eye
    return opencv_to_opengl(m)


def toy_states(n_frames: int, n_objects: int) -> np.ndarray:
    t = np.linspace(0, 1, n_frames)
    cols = [0.5 - 0.5 * np.cos(2 * np.pi * t), 0.5 - 0.5 * np.cos(2 * np.pi * (2 * t + 0.25))]
    return np.stack(cols[:n_objects], 1)


def toy_cameras(n_frames: int) -> np.ndarray:
    out = []
    for i in range(n_frames):
        a = -0.4 + 1.6 * np.pi * i / max(n_frames - 1, 1) / 2
        eye = (1.5 * np.cos(a) + 0.3, 1.5 * np.sin(a) - 1.2, 1.2 + 0.1 * np.sin(3 * a))
        out.append(look_at_gl(eye, (-0.2, 0.4, 0.6)))
    return np.stack(out)


def toy_dataset(root: Path, n_frames: int = 24, size: tuple[int, int] = (40, 30), n_objects: int = 1,
                label_every: int = 4, blender: bool = False) -> Path:
    """Write a toy LiveScene dataset (ours, or the OmniSim/blender layout with camera_angle_x)."""
    import json

    root = Path(root)
    scene = ToyScene(n_objects)
    w, h = size
    f = 0.9 * w
    intr = D.Intrinsics(w=w, h=h, fl_x=f, fl_y=f, cx=w / 2, cy=h / 2,
                        k1=0.0 if blender else -0.02, camera_model="PINHOLE" if blender else "OPENCV")
    states = toy_states(n_frames, n_objects)
    cams = toy_cameras(n_frames)
    names = NAMES[:n_objects]
    frames, labels = [], {}
    for i in range(n_frames):
        idx = 3 * i  # source video index
        rgb, _, index = scene.render(cams[i], states[i], intr)
        write_image(root / "images" / f"{frame_name(idx)}.png", rgb)
        D.write_mask(root, fid_of_index(idx), index_to_onehot(index, n_objects))
        frames.append(D.Frame(file_path=f"images/{frame_name(idx)}.png", c2w=cams[i]))
        if i % label_every == 0 or i == n_frames - 1:
            labels[frame_name(idx)] = {n: float(round(states[i, j], 4)) for j, n in enumerate(names)}
    if blender:
        meta = {"camera_angle_x": float(2 * np.arctan(0.5 * w / f)),
                "frames": [{"file_path": f"./images/{Path(fr.file_path).stem}",
                            "transform_matrix": fr.c2w.tolist()} for fr in frames]}
        (root / "transforms.json").write_text(json.dumps(meta))
    else:
        D.write_transforms(root, intr, frames)
    D.write_mapping(root, dict(enumerate(names)))
    D.write_labels(root, labels)
    np.save(root / "toy_states.npy", states)
    return root


def test_toy_scene_masks_follow_the_door(tmp_path):
    scene = ToyScene(1)
    intr = D.Intrinsics(w=40, h=30, fl_x=36, fl_y=36, cx=20, cy=15)
    cam = toy_cameras(8)[3]
    rgb0, depth0, idx0 = scene.render(cam, [0.0], intr)
    rgb1, depth1, idx1 = scene.render(cam, [1.0], intr)
    assert (idx0 == 1).sum() > 20 and (idx1 == 1).sum() > 20
    changed = np.any(rgb0 != rgb1, -1)
    assert changed.any()
    # only pixels that show the door in one of the two states change
    assert not np.any(changed & (idx0 == 0) & (idx1 == 0))
    assert np.all(np.isfinite(depth0)) and depth0.min() > 0
    ds = toy_dataset(tmp_path / "ds", n_frames=8)
    assert D.validate(ds).ok, D.format_problems(D.validate(ds))


def test_a_spiking_density_logit_stays_finite():
    """A logit past float32's exp overflow (88.7) once made an inf density and a NaN loss that no rollback cured."""
    import pytest
    import torch

    from livescene.field import trunc_exp
    from livescene.sampler import volume_weights

    x = torch.tensor([[1.0, 89.5, 120.0, 3.0]], requires_grad=True)
    sigma = trunc_exp(x)
    edges = torch.tensor([[0.0, 0.1, 0.1, 0.2, 0.3]])  # a zero-length step, as resampling makes
    w = volume_weights(sigma, edges)
    w.sum().backward()
    assert torch.isfinite(sigma).all() and torch.isfinite(w).all() and torch.isfinite(x.grad).all()
    assert float(w.detach().sum()) == pytest.approx(1.0, abs=1e-6)  # opaque at the spike
