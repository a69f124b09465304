"""`interreal batch`: the naming rule and manifest, both engines' stage semantics, a real batch of tiny simulated
captures with a corrupt video among them, and resuming."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pytest

from interreal import batch as B
from interreal import cli
from interreal.batch_engine import CaptureJob, LocalEngine, StageCommand, run_stage, stage_error
from interreal.errors import InputError


def _args(**kw) -> argparse.Namespace:
    base = {"target": None, "long_side": None, "train": False, "train_preset": None, "train_steps": None,
            "train_minutes": None}
    return argparse.Namespace(**{**base, **kw})


def _touch(path: Path, data: bytes = b"x") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


# ---------------------------------------------------------------------------------------------------------------
# where a capture's files are found
# ---------------------------------------------------------------------------------------------------------------
def test_naming_rule_finds_source_keyframes_and_labels(tmp_path):
    synth_like = tmp_path / "kitchen"
    _touch(synth_like / "video.mp4")
    (synth_like / "annotations" / "keyframes").mkdir(parents=True)
    _touch(synth_like / "annotations" / "states.yaml")
    cap = B.capture_from_path(synth_like)
    assert (cap.name, cap.source.name, cap.keyframes.name, cap.labels.name) == \
        ("kitchen", "video.mp4", "keyframes", "states.yaml")

    photos = tmp_path / "shelf"
    _touch(photos / "images" / "0001.jpg")
    _touch(photos / "states.csv")
    cap = B.capture_from_path(photos)
    assert cap.source == photos / "images" and cap.labels == photos / "states.csv" and cap.keyframes is None

    loose = tmp_path / "loose"
    _touch(loose / "a.jpg")
    assert B.capture_from_path(loose).source == loose  # the folder is itself the image folder

    video = _touch(tmp_path / "vids" / "hall.mov")
    (tmp_path / "vids" / "hall.keyframes").mkdir()
    _touch(tmp_path / "vids" / "hall.states.yaml")
    cap = B.capture_from_path(video)
    assert (cap.name, cap.keyframes.name, cap.labels.name) == ("hall", "hall.keyframes", "hall.states.yaml")

    two = tmp_path / "two"
    _touch(two / "a.mp4"), _touch(two / "b.mp4")
    with pytest.raises(InputError, match="holds 2 videos"):
        B.capture_from_path(two)
    with pytest.raises(InputError, match="no video, images/"):
        B.capture_from_path((tmp_path / "empty").mkdir() or tmp_path / "empty")
    with pytest.raises(InputError, match="does not exist"):
        B.capture_from_path(tmp_path / "nowhere")


def test_manifest_defaults_overrides_and_cli_options(tmp_path):
    _touch(tmp_path / "caps" / "a" / "video.mp4")
    _touch(tmp_path / "caps" / "b.mp4")
    (tmp_path / "masks_b").mkdir()
    manifest = tmp_path / "batch.yaml"
    manifest.write_text("defaults:\n  process: {target: 50, matcher: sequential}\n  train: {steps: 100}\n"
                        "captures:\n  - caps/a\n  - source: caps/b.mp4\n    name: bee\n    keyframes: masks_b\n"
                        "    process: {target: 80, no_motions: true}\n    train: false\n")
    caps = B.collect([], manifest, _args(long_side=320, train_preset="tiny"))
    a, b = caps
    assert (a.name, a.process, a.train) == ("a", {"long_side": 320, "target": 50, "matcher": "sequential"},
                                            {"preset": "tiny", "steps": 100})
    assert (b.name, b.keyframes, b.train) == ("bee", tmp_path / "masks_b", None)
    assert b.process == {"long_side": 320, "target": 80, "matcher": "sequential", "no_motions": True}
    argv = B.stage_commands(b, tmp_path / "out", cpus=2, gpu=False, resume_run=False)[0].argv
    assert argv[-7:] == ["--long-side", "320", "--target", "80", "--matcher", "sequential", "--no-motions"]
    assert argv[argv.index("--keyframes") + 1] == str(tmp_path / "masks_b")
    assert a.key() != b.key()

    for text, message in [("captures: [{name: x}]", "at least source"),
                          ("captures: [{source: caps/a, colour: red}]", "unknown key"),
                          ("captures: [{source: caps/a, train: {epochs: 3}}]", "unknown train option"),
                          ("[1, 2]", "'captures:' list"), ("captures: [caps/a, caps/a]", "two captures are named"),
                          ("captures: [{source: caps/a, labels: nope.yaml}]", "labels .* does not exist")]:
        manifest.write_text(text)
        with pytest.raises(InputError, match=message):
            B.collect([], manifest, _args())
    manifest.write_text("captures: [\n")
    with pytest.raises(InputError, match="not valid YAML"):
        B.collect([], manifest, _args())


def test_train_stage_command_resume_and_stale_run(tmp_path):
    cap = B.Capture("c", _touch(tmp_path / "c.mp4"), train={"preset": "tiny", "steps": 30, "set": ["lr=0.01"]})
    root = tmp_path / "out"
    cmds = B.stage_commands(cap, root, cpus=2, gpu=False, resume_run=False)
    assert [c.stage for c in cmds] == ["process", "train"]
    t = cmds[1].argv
    assert t[1:4] == ["-m", "livescene", "train"] and t[t.index("--steps") + 1] == "30"
    assert t[t.index("--set") + 1] == "lr=0.01" and "--resume" not in t and cmds[1].gpus == 0
    gpu = B.stage_commands(cap, root, cpus=4, gpu=True, resume_run=True)[1]
    assert (gpu.gpus, gpu.cpus, "--resume" in gpu.argv, "--threads" in gpu.argv) == (1, 1, True, False)

    key = cap.key()
    assert not B.prepare_run(root, cap, key)  # no run yet
    _touch(root / "c" / "run" / "latest.pt")
    B.write_state(root, cap, key, None)  # a batch killed while training: same inputs -> continue the run
    assert B.prepare_run(root, cap, key) and (root / "c" / "run" / "latest.pt").exists()
    assert not B.prepare_run(root, cap, "other-inputs")  # other inputs: never trained on top of
    assert (root / "c" / "run.stale" / "latest.pt").exists() and not (root / "c" / "run").exists()


# ---------------------------------------------------------------------------------------------------------------
# engines
# ---------------------------------------------------------------------------------------------------------------
def _py(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def _jobs(tmp_path: Path) -> list[CaptureJob]:
    def cmd(cap, stage, code):
        return StageCommand(cap, stage, _py(code), str(tmp_path / cap / f"{stage}.log"))

    return [CaptureJob("good", [cmd("good", "process", "print('made it')"), cmd("good", "train", "pass")]),
            CaptureJob("bad", [cmd("bad", "process", "import sys; print('interreal process: error: the video is "
                                                     "broken:'); print('  re-export it'); sys.exit(2)"),
                               cmd("bad", "train", "print('never')")]),
            CaptureJob("crash", [cmd("crash", "process", "import os; os.kill(os.getpid(), 9)")])]


def _check_engine_results(results: dict[str, list]) -> None:
    assert [r.ok for r in results["good"]] == [True, True]
    proc, train = results["bad"]
    assert not proc.ok and proc.returncode == 2
    assert proc.error == "interreal process: error: the video is broken: re-export it"
    assert not train.ok and train.returncode is None and train.error == "not run: process failed"
    assert results["crash"][0].error.startswith("killed by signal 9")


def test_local_engine_stage_semantics(tmp_path):
    events = []
    eng = LocalEngine(2)
    results = {job.name: res for job, res in eng.run(_jobs(tmp_path), lambda *e: events.append(e[:3]))}
    _check_engine_results(results)
    assert ("good", "train", "end") in events and ("bad", "train", "start") not in events
    assert "made it" in (tmp_path / "good" / "process.log").read_text()
    with pytest.raises(InputError):
        LocalEngine(0)


def test_ray_engine_same_semantics(tmp_path):
    pytest.importorskip("ray")
    from interreal.batch_engine import RayEngine

    eng = RayEngine(2)
    try:
        results = {job.name: res for job, res in eng.run(_jobs(tmp_path), lambda *e: None)}
        assert eng.cpus >= 1 and "local Ray" in eng.describe()
    finally:
        eng.close()
    _check_engine_results(results)


def test_stage_error_falls_back_to_exit_status(tmp_path):
    assert stage_error("progress 10%\rprogress 100%\nTraceback...\nValueError: x\n", 1) == \
        "exit status 1: ValueError: x"
    assert stage_error("", -9) == "killed by signal 9 (no output)"
    res = run_stage(StageCommand("c", "s", ["/nonexistent/python"], str(tmp_path / "s.log")))
    assert not res.ok and "could not start" in res.error


# ---------------------------------------------------------------------------------------------------------------
# a real batch: tiny simulated captures and a corrupt video, on the local pool
# ---------------------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> Path:
    from interreal.synth import SynthConfig, write_capture

    root = tmp_path_factory.mktemp("caps")
    for seed in (0, 1):
        write_capture(SynthConfig(frames=24, width=160, height=120, seed=seed, label_fraction=0.5),
                      root / f"cap{seed}", progress=False)
    _touch(root / "broken" / "video.mp4", bytes(range(256)) * 64)  # not a video
    return root


def test_batch_corrupt_capture_leaves_others_finished_and_resumes(captures, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["batch", str(captures / "cap0"), str(captures / "broken"), str(captures / "cap1"), "--out", str(out),
            "--engine", "local", "--workers", "2", "--target", "12"]
    assert cli.main(argv) == 1  # one capture failed
    printed = capsys.readouterr().out
    assert "broken: process FAILED" in printed and "2 ok, 1 failed" in printed
    summary = json.loads((out / "summary.json").read_text())
    rows = {r["capture"]: r for r in summary["captures"]}
    assert list(rows) == ["cap0", "broken", "cap1"] and summary["total"] == 3
    assert "not a readable video" in rows["broken"]["error"] and rows["broken"]["status"] == "failed"
    for name in ("cap0", "cap1"):
        r = rows[name]
        assert r["status"] == "ok" and r["error"] is None
        assert r["registered"] >= 8 and r["frames"] >= 12, r
        assert set(r["seconds"]) >= {"frames", "masks", "poses", "labels", "process"}, r["seconds"]
        assert set(r["mask_confidence"]) == {"fridge door", "top drawer"}
        assert (out / name / "dataset" / "transforms.json").exists()
    md = (out / "summary.md").read_text()
    assert all(f"| {n} |" in md for n in rows) and "| registered |" in md.replace("registered | mask", "registered |")
    assert summary["captures_per_hour"] > 0 and summary["workers"] == 2

    # again: the finished captures are skipped (not touched), the failed one runs again and fails again
    stamps = {n: (out / n / "batch.json").stat().st_mtime_ns for n in ("cap0", "cap1")}
    assert cli.main(argv) == 1
    again = json.loads((out / "summary.json").read_text())
    rows = {r["capture"]: r for r in again["captures"]}
    assert (rows["cap0"]["status"], rows["cap1"]["status"], rows["broken"]["status"]) == ("skipped", "skipped",
                                                                                           "failed")
    assert rows["cap0"]["registered"] == summary["captures"][0]["registered"]  # the table still has its figures
    assert {n: (out / n / "batch.json").stat().st_mtime_ns for n in ("cap0", "cap1")} == stamps
    assert "2 finished earlier, 1 to run" in capsys.readouterr().out


def test_a_workers_cpu_budget_bounds_pycolmap(monkeypatch):
    """A batch worker's OMP_NUM_THREADS (its CPU budget) is what pycolmap gets for "all cores" (-1); an explicit
    count wins; without the variable pycolmap keeps every core."""
    from interreal.batch_engine import THREAD_VARS
    from interreal.sfm.colmap import threads

    assert "OMP_NUM_THREADS" in THREAD_VARS
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads(-1) == 1 and threads(3) == 3
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert threads(-1) == -1
