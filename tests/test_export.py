"""`livescene export`: a toy door (hinge) and drawer (slide) trained with their motions, exported as a URDF that two
independent readers (yourdfpy and MuJoCo) load; each joint moved through its range moves its part's mesh by the
motion of articulation.json (axis within 1 degree, amount within 1 % of the range) and leaves the static scene
where it is. The GLB and PLY carry the parts at the asked state, and a run without motions exports fixed links."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_livescene_rigid import TOY_DOOR  # noqa: E402
from test_livescene_toy import toy_dataset  # noqa: E402

from interreal.dataset import Articulation, read_articulation, write_articulation  # noqa: E402

DRAWER = Articulation("slide", np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0]), 0.45)  # toy drawer slides -x
RESOLUTION = 48  # voxels along the toy box's longest side: a coarse, fast export


@pytest.fixture(scope="module")
def export_run_dir(tmp_path_factory, one_thread):
    """The toy room with a door and a drawer, trained briefly with both motions (tiny preset, one thread)."""
    from livescene.config import load_preset
    from livescene.trainer import train

    root = tmp_path_factory.mktemp("export")
    ds = toy_dataset(root / "ds", n_frames=16, size=(32, 24), n_objects=2)
    write_articulation(ds, {"door": TOY_DOOR, "drawer": DRAWER}, {"source": "test"})
    cfg = load_preset("tiny")
    cfg.steps = 200
    train(ds, root / "run", cfg, device="cpu", show_progress=False)
    return root / "run", ds


@pytest.fixture(scope="module")
def urdf_export(export_run_dir, tmp_path_factory):
    """`livescene export RUN --format urdf,glb,ply,mesh --state door=1` through the command line."""
    from livescene.cli import main

    run, _ = export_run_dir
    out = tmp_path_factory.mktemp("asset")
    rc = main(["export", str(run), "--format", "urdf,glb,ply,mesh", "--out", str(out), "--resolution",
               str(RESOLUTION), "--state", "door=1", "--points", "20000", "--no-progress"])
    assert rc == 0
    return out


def _rigid_motion(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with b ~ R a + t for corresponding points (Kabsch)."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def _check_motion(rest: np.ndarray, moved: np.ndarray, motion: Articulation, state: float) -> None:
    """The part's points moved from state 0 to `state` as `motion` says: axis within 1 degree, amount within 1 % of
    the range, a hinge about its measured origin."""
    r, t = _rigid_motion(rest, moved)
    amount = state * motion.range
    if motion.kind == "hinge":
        from scipy.spatial.transform import Rotation

        rv = Rotation.from_matrix(r).as_rotvec()
        angle = np.linalg.norm(rv)
        assert abs(angle - abs(amount)) < 0.01 * abs(motion.range)
        if angle > 1e-3:
            cos = abs(float(rv @ motion.axis)) / angle
            assert np.degrees(np.arccos(min(1.0, cos))) < 1.0
            assert float(rv @ motion.axis) * amount > 0  # turns the way the state does
        assert np.linalg.norm(r @ motion.origin + t - motion.origin) < 0.01  # the hinge's axis stays put
    else:
        assert np.degrees(np.arccos(min(1.0, abs(np.trace(r) - 1) / 2))) < 1.0  # no turn
        assert abs(np.linalg.norm(t) - abs(amount)) < 0.01 * abs(motion.range)
        if abs(amount) > 1e-6:
            cos = float(t @ motion.axis) / (np.linalg.norm(t) * np.sign(amount))
            assert np.degrees(np.arccos(min(1.0, cos))) < 1.0
    assert np.abs(moved - (rest @ motion.pose(state)[0].T + motion.pose(state)[1])).max() < 0.01


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # yourdfpy calls a trimesh API trimesh deprecates
def test_urdf_loads_in_yourdfpy_and_each_joint_moves_its_part_as_measured(export_run_dir, urdf_export):
    yourdfpy = pytest.importorskip("yourdfpy")
    _, ds = export_run_dir
    motions = read_articulation(ds)
    report = json.loads((urdf_export / "export.json").read_text())
    urdf_path = urdf_export / report["urdf"]["urdf"]
    robot = yourdfpy.URDF.load(str(urdf_path), build_collision_scene_graph=True, load_collision_meshes=True)
    joints = {j.child: j for j in robot.robot.joints}
    assert set(joints) == {"door", "drawer"} and robot.base_link == "base"
    assert joints["door"].type == "revolute" and joints["drawer"].type == "prismatic"
    for link in robot.robot.links:  # positive inertials, relative mesh paths, convex collision pieces
        assert link.inertial.mass > 0 and np.all(np.linalg.eigvalsh(link.inertial.inertia) > 0)
        for geo in [*link.visuals, *link.collisions]:
            assert not Path(geo.geometry.mesh.filename).is_absolute()
        assert link.collisions
    import trimesh

    def world_vertices(link: str) -> np.ndarray:
        mesh = trimesh.load(urdf_export / robot.link_map[link].visuals[0].geometry.mesh.filename, process=False,
                            force="mesh")
        tf = robot.get_transform(frame_to=link, frame_from=robot.base_link)
        return np.asarray(mesh.vertices) @ tf[:3, :3].T + tf[:3, 3]

    robot.update_cfg(np.zeros(len(robot.actuated_joint_names)))
    rest = {name: world_vertices(name) for name in ("base", "door", "drawer")}
    for name, motion in (("door", motions["door"]), ("drawer", motions["drawer"])):
        j = joints[name]
        np.testing.assert_allclose(sorted([j.limit.lower, j.limit.upper]), sorted([0.0, motion.range]), atol=1e-6)
        for state in (0.25, 0.5, 1.0):
            cfg = {n: 0.0 for n in robot.actuated_joint_names}
            cfg[j.name] = state * motion.range
            robot.update_cfg(cfg)
            _check_motion(rest[name], world_vertices(name), motion, state)
            assert np.abs(world_vertices("base") - rest["base"]).max() == 0.0  # the static scene stays
            other = "drawer" if name == "door" else "door"
            assert np.abs(world_vertices(other) - rest[other]).max() < 1e-9
    # each part's mesh at rest is cut from where the probability field gives it the space: just inside its surface
    # the model (its own ownership rule, all states 0) says the part owns the point
    import torch

    from livescene.run import load_run

    run = load_run(export_run_dir[0], device="cpu")
    for i, name in enumerate(("door", "drawer")):
        mesh = trimesh.load(urdf_export / "parts" / f"{name}.ply", process=False)
        cell = report["pieces"][i + 1]["voxel"]
        inside = torch.as_tensor(np.asarray(mesh.vertices) - 0.3 * cell * np.asarray(mesh.vertex_normals),
                                 dtype=torch.float32)
        values = torch.zeros(len(inside), run.model.cfg.max_objects)
        with torch.no_grad():
            logits = run.model.place(inside, torch.zeros_like(inside), values, run.box, grad_logits=False).logits
        idx, owned = run.model.owner(logits)
        assert float((owned & (idx == i)).float().mean()) > 0.9


@pytest.mark.slow
def test_urdf_loads_in_mujoco_and_each_joint_moves_its_part_as_measured(export_run_dir, urdf_export):
    mujoco = pytest.importorskip("mujoco")
    _, ds = export_run_dir
    motions = read_articulation(ds)
    report = json.loads((urdf_export / "export.json").read_text())
    model = mujoco.MjModel.from_xml_path(str(urdf_export / report["urdf"]["urdf"]))
    data = mujoco.MjData(model)
    assert model.njnt == 2
    body = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b): b for b in range(model.nbody)}
    kinds = {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j): int(model.jnt_type[j]) for j in range(model.njnt)}
    assert kinds == {"door_joint": int(mujoco.mjtJoint.mjJNT_HINGE), "drawer_joint": int(mujoco.mjtJoint.mjJNT_SLIDE)}

    def world_vertices(name: str) -> np.ndarray:
        pts = []
        for g in np.nonzero(model.geom_bodyid == body[name])[0]:
            m = model.geom_dataid[g]
            if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or m < 0:
                continue
            v = model.mesh_vert[model.mesh_vertadr[m]: model.mesh_vertadr[m] + model.mesh_vertnum[m]]
            pts.append(v @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g])
        return np.concatenate(pts)

    def at(qpos: dict[str, float]) -> None:
        data.qpos[:] = 0.0
        for jname, q in qpos.items():
            data.qpos[model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, jname)]] = q
        mujoco.mj_kinematics(model, data)

    at({})
    static_name = "base" if "base" in body else "world"  # MuJoCo fuses a fixed base link into its world body
    rest = {n: world_vertices(n) for n in ("door", "drawer")}
    static_rest = world_vertices(static_name)
    assert len(static_rest) > 0
    for name in ("door", "drawer"):
        motion = motions[name]
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{name}_joint")
        np.testing.assert_allclose(sorted(model.jnt_range[j]), sorted([0.0, motion.range]), atol=1e-5)
        for state in (0.5, 1.0):
            at({f"{name}_joint": state * motion.range})
            _check_motion(rest[name], world_vertices(name), motion, state)
            assert np.abs(world_vertices(static_name) - static_rest).max() < 1e-9


@pytest.mark.slow
def test_glb_and_ply_hold_the_parts_at_the_asked_state(export_run_dir, urdf_export):
    import trimesh

    from livescene.export.ply import read_ply

    _, ds = export_run_dir
    door = read_articulation(ds)["door"]
    parts = {p.stem: trimesh.load(p, process=False) for p in (urdf_export / "parts").glob("*.ply")}
    assert set(parts) == {"static", "door", "drawer"}
    assert all(len(m.visual.vertex_colors) == len(m.vertices) for m in parts.values())
    scene = trimesh.load(urdf_export / "scene.glb")
    placed = {}
    for node in scene.graph.nodes_geometry:
        tf, geom = scene.graph[node]
        placed[node] = scene.geometry[geom].copy().apply_transform(tf)
    assert {"static", "door", "drawer"} <= set(placed)
    r, t = door.pose(1.0)  # --state door=1: the GLB's door is the rest door turned a quarter
    moved = np.asarray(parts["door"].vertices) @ r.T + t
    np.testing.assert_allclose(placed["door"].bounds, [moved.min(0), moved.max(0)], atol=1e-4)
    np.testing.assert_allclose(placed["drawer"].bounds, parts["drawer"].bounds, atol=1e-4)  # at rest
    rec = read_ply(urdf_export / "points.ply")
    ids, counts = np.unique(rec["object"], return_counts=True)
    assert set(ids) == {-1, 0, 1} and counts.sum() == pytest.approx(20000, rel=0.01)
    door_pts = np.stack([rec["x"], rec["y"], rec["z"]], 1)[rec["object"] == 0]
    lo, hi = placed["door"].bounds
    assert np.all(door_pts >= lo - 1e-4) and np.all(door_pts <= hi + 1e-4)


@pytest.mark.slow
def test_a_run_without_motions_exports_fixed_links_with_a_warning(export_run_dir, urdf_export, tmp_path):
    yourdfpy = pytest.importorskip("yourdfpy")
    from livescene.export import ExportOptions, export_run
    from livescene.run import load_run

    run_dir, _ = export_run_dir
    run = load_run(run_dir, device="cpu")
    run.model.motions = None  # as a run trained without articulation.json (the paper's k-axis alone) reads
    level = json.loads((urdf_export / "export.json").read_text())["level"]  # measured once already
    report = export_run(run, tmp_path, ExportOptions(formats=("urdf",), resolution=32, states={"drawer": 0.5},
                                                     level=level))
    assert any("no part motions" in w and "fixed" in w for w in report["warnings"])
    robot = yourdfpy.URDF.load(str(tmp_path / report["urdf"]["urdf"]))
    assert {j.type for j in robot.robot.joints} == {"fixed"} and not robot.actuated_joint_names
    assert report["states"] == {"door": 0.0, "drawer": 0.5}


def test_bad_export_options_are_one_line_errors(tmp_path, capsys):
    from livescene.cli import main

    for argv, needle in ((["--format", "usd"], "--format"), (["--resolution", "4"], "--resolution"),
                         (["--state", "door=2"], "door"), (["--metres-per-unit", "-1"], "--metres-per-unit")):
        rc = main(["export", str(tmp_path / "missing_run"), "--out", str(tmp_path / "o"), *argv])
        err = capsys.readouterr().err
        assert rc != 0 and needle in err and "Traceback" not in err
    rc = main(["export", str(tmp_path / "missing_run"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc != 0 and "missing_run" in err and "Traceback" not in err


def test_surface_level_is_measured_where_the_views_see_surfaces():
    import torch

    from livescene.export.level import level_from_profiles

    edges = torch.linspace(0.0, 4.0, 401).expand(8, -1)
    sigma = torch.full((8, 400), 0.01)
    sigma[:, 200:] = torch.linspace(5.0, 80.0, 8)[:, None]  # a wall at depth 2 on each ray, of growing density
    level, air = level_from_profiles(sigma, edges)
    assert 5.0 < level < 80.0 and air == pytest.approx(0.01)
    assert level == pytest.approx(float(torch.quantile(torch.linspace(5.0, 80.0, 8), 0.25)))
    fog, _ = level_from_profiles(torch.full((8, 400), 0.01), edges)  # 4 % of the light stopped: no surface
    assert fog is None


def test_surfaces_are_closed_and_face_outward_even_where_the_box_cuts_them():
    from livescene.export.mesh import surface

    x = np.linspace(-1.0, 1.0, 33)
    gx, gy, gz = np.meshgrid(x, x, x, indexing="ij")
    ball = (0.6 - np.sqrt(gx ** 2 + gy ** 2 + gz ** 2)).astype(np.float32)  # positive inside
    m = surface(ball, np.full(3, -1.0), float(x[1] - x[0]))
    assert m.is_watertight and m.volume == pytest.approx(4 / 3 * np.pi * 0.6 ** 3, rel=0.03)
    slab = (0.5 - np.abs(gz)).astype(np.float32)  # a slab the grid's sides cut
    m = surface(slab, np.full(3, -1.0), float(x[1] - x[0]))
    assert m.is_watertight and m.volume > 0 and np.allclose(m.bounds[:, 2], [-0.5, 0.5], atol=1e-3)
