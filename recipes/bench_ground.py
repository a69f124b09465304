"""Grounding benchmark: find an object by text, score the retrieval and the rendered mask against simulator truth.

On the default simulated capture (`interreal synth`, fridge door + top drawer) a LiveScene run is trained (cpu
preset, or reused with --run) on `interreal.synth.truth_dataset(...)`. Every query of the set below (>= 3 phrasings
per object: its name, a synonym, a paraphrase; none copies the stored descriptions) is retrieved with the packaged
MiniLM encoder; the retrieved object's probability map (> 0.5) is compared with the simulator's truth instance mask
of the intended object on the run's held-out views (rendered at the run's learned states for those frames, and
again at the simulator's truth states). A text-only pass scores retrieval among all ten simulator object kinds
(harder: top / bottom drawer, left / right wardrobe door) on the query sets of `recipes/ground_queries.yaml` (a
development set and held-out ones, each written before the change it judged: see its note).

Records: data, query, phrasing, object, retrieved, retrieved_ok, score, prob, iou (mean over held-out views where
the object or the mask is present), iou_oracle (the intended object's own mask), iou_truth_states (rendered at the
truth states), iou_dataset_masks (against the run's dataset masks rather than the simulator's truth: on a `--run` of
the demo those are propagated, and wrong where propagation was). Goals: retrieval accuracy >= 0.9, grounding mIoU
>= 0.85.

  python recipes/bench_ground.py --text-only --out bench/         # the query set alone (seconds)
  python recipes/bench_ground.py --quick --out bench/
  python recipes/bench_ground.py --out bench/                       # default capture, cpu preset (tens of minutes)
  python recipes/bench_ground.py --out bench/ --run out/run --capture out/cap   # reuse a trained run
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from benchlib import bench_args, print_table, write_results

NAME = "ground"
# object kind -> (name, synonym, paraphrase); the simulator's descriptions are in interreal/synth/scene.py
QUERIES: dict[str, dict[str, str]] = {
    "fridge door": {"name": "fridge door", "synonym": "the refrigerator", "paraphrase": "where the milk stays chilled"},
    "top drawer": {"name": "top drawer", "synonym": "the upper drawer",
                   "paraphrase": "the drawer with the forks and knives"},
    "microwave door": {"name": "microwave door", "synonym": "the microwave oven",
                       "paraphrase": "the appliance that warms up leftovers"},
    "oven door": {"name": "oven door", "synonym": "the stove", "paraphrase": "where you bake a cake"},
    "bottom drawer": {"name": "bottom drawer", "synonym": "the lower drawer",
                      "paraphrase": "the drawer with the saucepans"},
    "cupboard door": {"name": "cupboard door", "synonym": "the wall cabinet", "paraphrase": "where the mugs are stored"},
    "chest lid": {"name": "chest lid", "synonym": "the toy box", "paraphrase": "the top of the storage trunk"},
    "wardrobe left door": {"name": "wardrobe left door", "synonym": "the left closet door",
                           "paraphrase": "the closet door on the left, with the shirts"},
    "wardrobe right door": {"name": "wardrobe right door", "synonym": "the right closet door",
                            "paraphrase": "the closet door on the right, with the jackets"},
    "nightstand drawer": {"name": "nightstand drawer", "synonym": "the bedside drawer",
                          "paraphrase": "the little drawer next to the bed"},
}


def extra_args(p) -> None:
    p.add_argument("--text-only", action="store_true", help="only the query set's retrieval (present top-1, absent "
                                                             "refusals, with and without prompts): seconds")
    p.add_argument("--queries", choices=("all", *QUERY_SETS), default="all",
                   help="--text-only: the development query set (PRESENT/ABSENT), a held-out one, or all")
    p.add_argument("--run", type=Path, default=None, help="reuse this trained run (its dataset must be a truth dataset)")
    p.add_argument("--capture", type=Path, default=None, help="reuse this capture folder (interreal synth OUT)")
    p.add_argument("--work", type=Path, default=None, help="where capture / dataset / run go (default OUT/ground_work)")
    p.add_argument("--steps", type=int, default=0, help="training steps (default: 4000 cpu preset, 300 with --quick)")
    p.add_argument("--preset", default="cpu", help="livescene training preset (default cpu)")
    p.add_argument("--max-minutes", type=float, default=0.0, help="cap the training time (0 = the preset's steps)")
    p.add_argument("--eval-views", type=int, default=None,
                   help="held-out views to score, spread over the held-out set (default 12, 4 with --quick; 0 = all)")
    p.add_argument("--eval-scale", type=float, default=1.0,
                   help="render held-out views at this fraction of the dataset size (truth masks: nearest)")
    p.add_argument("--mask-threshold", type=float, default=0.5)


def make_capture(work: Path, quick: bool) -> Path:
    from interreal.synth import SynthConfig, write_capture

    cap = work / "capture"
    if (cap / "gt" / "meta.json").exists():
        return cap
    # quick: the default scene, a shorter clip at half the resolution
    cfg = SynthConfig(frames=64, width=320, height=240) if quick else SynthConfig()
    t0 = time.perf_counter()
    write_capture(cfg, cap)
    print(f"capture: {cfg.frames} frames {cfg.width}x{cfg.height} in {time.perf_counter() - t0:.0f} s -> {cap}")
    return cap


def make_run(work: Path, cap: Path, args) -> Path:
    from interreal.synth import truth_dataset

    ds = work / "ds"
    if not (ds / "transforms.json").exists():
        truth_dataset(cap, ds, size=(160, 120) if args.quick else (320, 240))
    run = work / "run"
    from interreal.report import read_report

    if (run / "latest.pt").exists() and (read_report(run, "train") or {}).get("status") == "ok":
        return run  # a finished run; an interrupted one is resumed below
    steps = args.steps or (300 if args.quick else 4000)
    cmd = [sys.executable, "-m", "livescene", "train", str(ds), "--out", str(run), "--preset", args.preset,
           "--steps", str(steps), "--device", "cpu"]
    if args.max_minutes:
        cmd += ["--max-minutes", str(args.max_minutes)]
    if (run / "latest.pt").exists():
        cmd.append("--resume")
    print("train:", " ".join(cmd[2:]), flush=True)
    subprocess.run(cmd, check=True)
    return run


def heldout_views(run, capture, count: int, scale: float = 1.0) -> list[dict]:
    """Render `count` held-out views (spread; 0 = all) once at the run's learned states for the frame (what the
    run reconstructs, as `livescene ground --views` renders) and once at the simulator's truth states. Each view's
    `truth` is the simulator's instance mask in the run's object order; `dataset` the run's dataset masks (the
    propagated ones on a demo or `process` run: an estimate, wrong where propagation was)."""
    import cv2
    from tqdm import tqdm

    from interreal.conventions import onehot_to_index
    from livescene.data import load_frame
    from livescene.render import render_view

    views = run.views
    cap_states = np.asarray(capture.states)
    lut = np.zeros(256, np.uint8)  # the simulator's instance ids -> the run's object indices + 1
    for k, name in enumerate(run.names):
        if name in capture.names:
            lut[capture.names.index(name) + 1] = k + 1
    held = list(views.held_out) or list(range(0, len(views.times), 8))
    if count and count < len(held):
        held = [held[int(j)] for j in np.linspace(0, len(held) - 1, count).round()]
    out = []
    for i in tqdm(held, desc="render held-out", unit="view"):
        frame = views.dataset.frames[i]
        _, dataset = load_frame(views, i)  # index map at the working size (0 = background)
        if dataset is None:
            dataset = onehot_to_index(views.dataset.load_mask(frame))
        intr = views.intrinsics[i]
        if scale != 1.0:
            intr = intr.scaled(max(8, round(intr.w * scale)), max(8, round(intr.h * scale)))
        size = (intr.w, intr.h)
        if dataset.shape[::-1] != size:
            dataset = cv2.resize(dataset, size, interpolation=cv2.INTER_NEAREST_EXACT)
        truth = lut[cv2.resize(capture.instance(frame.index).astype(np.uint8), size,
                               interpolation=cv2.INTER_NEAREST_EXACT)]
        learned = render_view(run, views.c2w_gl[i], intr, None, time=float(views.times[i]))
        at_truth = render_view(run, views.c2w_gl[i], intr, cap_states[frame.index])
        out.append({"fid": frame.fid, "probs": learned["probs"], "probs_truth_states": at_truth["probs"],
                    "truth": truth, "dataset": dataset,
                    "state_err": float(np.abs(learned["states"] - cap_states[frame.index]).mean())})
    return out


def view_iou(views: list[dict], obj: int, expected: int, thr: float, key: str = "probs",
             truth: str = "truth") -> tuple[float | None, int]:
    from livescene.language.grounding import mask_iou

    ious = [mask_iou(v[key][..., obj] > thr, v[truth] == expected + 1) for v in views]
    ious = [x for x in ious if x is not None]
    return (float(np.mean(ious)) if ious else None), len(ious)


def grounding_records(run_dir: Path, cap: Path, thr: float, data: str, count: int,
                      scale: float = 1.0) -> tuple[list[dict], dict]:
    from interreal.synth import Capture
    from livescene.language import get_encoder, ground_query
    from livescene.language.grounding import check_run_has_masks
    from livescene.trainer import load_run

    capture = Capture.open(cap)
    run = load_run(run_dir, device="cpu")
    check_run_has_masks(run)
    names = run.names
    t0 = time.perf_counter()
    views = heldout_views(run, capture, count, scale)
    render_s = time.perf_counter() - t0
    enc = get_encoder()
    records = []
    for obj in names:
        for phrasing, query in QUERIES[obj].items():
            t1 = time.perf_counter()
            res = ground_query(run_dir, query, encoder=enc)
            ms = (time.perf_counter() - t1) * 1000
            best = res.best
            iou, n = view_iou(views, best.index, names.index(obj), thr) if res.ok else (0.0, len(views))
            oracle, _ = view_iou(views, names.index(obj), names.index(obj), thr)
            at_truth, _ = (view_iou(views, best.index, names.index(obj), thr, "probs_truth_states") if res.ok
                           else (0.0, 0))
            on_dataset, _ = view_iou(views, best.index, names.index(obj), thr, truth="dataset") if res.ok else (0.0, 0)
            records.append({"data": data, "query": query, "phrasing": phrasing, "object": obj,
                            "retrieved": best.name if res.ok else None, "retrieved_ok": bool(res.ok and best.name == obj),
                            "score": round(best.score, 4), "prob": round(best.prob, 4),
                            "iou": None if iou is None else round(iou, 4),
                            "iou_oracle": None if oracle is None else round(oracle, 4),
                            "iou_truth_states": None if at_truth is None else round(at_truth, 4),
                            "iou_dataset_masks": None if on_dataset is None else round(on_dataset, 4), "views": n,
                            "retrieval_ms": round(ms, 2)})
    meta = {"heldout_views": len(views), "render_s_per_view": round(render_s / max(len(views), 1) / 2, 3),
            "eval_size": list(views[0]["truth"].shape[::-1]) if views else None,
            "heldout_state_mae": round(float(np.mean([v["state_err"] for v in views])), 4),
            "run": str(run_dir), "run_step": run.step, "objects": names}
    return records, meta


def text_only_records(data: str) -> list[dict]:
    """Retrieval among all ten simulator object kinds, with their real descriptions (no rendering)."""
    from interreal.synth import SynthConfig, build_scene
    from livescene.language import ObjectIndex, get_encoder, retrieve

    scene = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24))
    enc = get_encoder()
    index = ObjectIndex.build(scene.object_names, scene.descriptions, enc)
    records = []
    for obj in scene.object_names:
        for phrasing, query in QUERIES[obj].items():
            res = retrieve(index, query, enc)
            records.append({"data": data, "query": query, "phrasing": phrasing, "object": obj,
                            "retrieved": res.best.name if res.ok else None,
                            "retrieved_ok": bool(res.ok and res.best.name == obj), "score": round(res.best.score, 4),
                            "prob": round(res.best.prob, 4), "iou": None, "iou_oracle": None,
                            "iou_truth_states": None, "views": 0})
    return records


QUERY_FILE = Path(__file__).with_name("ground_queries.yaml")  # the text-only query sets (each with its note)


def query_sets(path: Path = QUERY_FILE) -> dict[str, tuple[dict[str, list[str]], list[str]]]:
    """{set name: (present queries per object, absent queries)} from the query sets' file, in its order."""
    data = yaml.safe_load(path.read_text())
    return {name: (dict(s["present"]), list(s["absent"])) for name, s in data.items()}


QUERY_SETS = query_sets()


def query_set_records(data: str, objects: list[str], described: bool, queries: str = "heldout") -> list[dict]:
    """Retrieval of a query set's present queries (for `objects`) and absent ones among a simulated scene's
    `objects`, with the scene's descriptions (prompts) or by name alone: right object / refused."""
    from interreal.synth import SynthConfig, build_scene
    from livescene.language import ObjectIndex, get_encoder, retrieve

    scene = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24))
    enc = get_encoder()
    index = ObjectIndex.build(objects, {n: scene.descriptions[n] for n in objects} if described else None, enc)
    present, absent = QUERY_SETS[queries]
    rows = [(q, o, _phrasing(q)) for o in objects for q in present[o]]
    rows += [(q, None, "absent") for q in absent]
    records = []
    for query, obj, phrasing in rows:
        res = retrieve(index, query, enc)
        got = res.best.name if res.ok else None
        records.append({"set": queries, "data": data, "prompts": described, "query": query, "phrasing": phrasing, "object": obj,
                        "retrieved": got, "retrieved_ok": got == obj, "score": round(res.best.score, 4),
                        "reads_as": res.reads_as})
    return records


def _phrasing(query: str) -> str:
    q = query.lower()
    if q.split()[0] in ("open", "close", "shut", "pull", "lift"):
        return "command"
    return "function" if q.split()[0] in ("where", "what", "the thing") or " where " in q else "name/synonym"


def query_set_summary(records: list[dict]) -> list[dict]:
    """Per scene and prompts on / off: top-1 on present objects, refusals of absent ones (targets 0.95 with prompts,
    0.8 by name; 0.9 refused)."""
    out = []
    for key in dict.fromkeys((r["set"], r["data"], r["prompts"]) for r in records):
        rs = [r for r in records if (r["set"], r["data"], r["prompts"]) == key]
        present, absent = [r for r in rs if r["object"]], [r for r in rs if not r["object"]]
        out.append({"set": key[0], "data": key[1], "prompts": key[2], "queries": len(rs),
                    "top1_present": round(float(np.mean([r["retrieved_ok"] for r in present])), 3),
                    "refused_absent": round(float(np.mean([r["retrieved"] is None for r in absent])), 3),
                    "misses": "; ".join(f"{r['query']} -> {r['retrieved'] or ('absent: ' + str(r['reads_as']))}"
                                        for r in rs if not r["retrieved_ok"])})
    return out


def capture_label(cap: Path) -> str:
    """e.g. "synth-300f-640x480-2parts" (the default capture), from the capture's gt/meta.json."""
    import json

    cfg = json.loads((Path(cap) / "gt" / "meta.json").read_text())["config"]
    return f"synth-{cfg['frames']}f-{cfg['width']}x{cfg['height']}-{cfg['parts']}parts"


def summary(records: list[dict]) -> dict:
    out = {}
    for data in dict.fromkeys(r["data"] for r in records):
        rs = [r for r in records if r["data"] == data]
        ious = [r["iou"] for r in rs if r["iou"] is not None]
        oracle = [r["iou_oracle"] for r in rs if r["iou_oracle"] is not None]
        at_truth = [r["iou_truth_states"] for r in rs if r["iou_truth_states"] is not None]
        on_dataset = [r["iou_dataset_masks"] for r in rs if r.get("iou_dataset_masks") is not None]
        out[data] = {"queries": len(rs), "retrieval_accuracy": round(float(np.mean([r["retrieved_ok"] for r in rs])), 4),
                     "miou": round(float(np.mean(ious)), 4) if ious else None,
                     "miou_oracle": round(float(np.mean(oracle)), 4) if oracle else None,
                     "miou_truth_states": round(float(np.mean(at_truth)), 4) if at_truth else None,
                     "miou_dataset_masks": round(float(np.mean(on_dataset)), 4) if on_dataset else None}
    return out


def chart(path: Path, records: list[dict], summ: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    datas = list(summ)
    fig, axes = plt.subplots(1, len(datas), figsize=(6 * len(datas), 4.8), dpi=110, squeeze=False)
    for ax, data in zip(axes[0], datas):
        rs = [r for r in records if r["data"] == data]
        labels = [r["query"][:28] for r in rs]
        grounded = any(r["iou"] is not None for r in rs)
        vals = [(r["iou"] or 0.0) if grounded else r["score"] for r in rs]
        colors = ["tab:green" if r["retrieved_ok"] else "tab:red" for r in rs]
        ax.barh(range(len(rs)), vals, color=colors)
        if grounded:
            ax.scatter([r["iou_oracle"] or 0 for r in rs], range(len(rs)), marker="|", color="k", s=80,
                       label="intended object's IoU")
            ax.axvline(0.85, ls="--", color="gray", lw=1)
            ax.legend(fontsize=7, loc="lower right")
        ax.set_yticks(range(len(rs)), labels, fontsize=6)
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        s = summ[data]
        ax.set_xlabel("mask IoU on held-out views" if grounded else "text similarity of the retrieved object")
        ax.set_title(f"{data}: retrieval {s['retrieval_accuracy']:.2f}"
                     + (f", mIoU {s['miou']:.3f}" if s["miou"] is not None else ""), fontsize=9)
    fig.suptitle("livescene ground (green: right object retrieved, red: wrong / none)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def text_main(args) -> int:
    """--text-only: the query set over the demo's two objects and all ten simulator kinds, with and without
    prompts (seconds; no run)."""
    from interreal.synth import SynthConfig, build_scene

    kinds = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24)).object_names
    records = []
    for queries in (tuple(QUERY_SETS) if args.queries == "all" else (args.queries,)):
        for data, objects in (("synth-2parts", kinds[:2]), ("synth-10kinds", kinds)):
            for described in (True, False):
                records += query_set_records(data, objects, described, queries)
    summ = query_set_summary(records)
    write_results(args.out, NAME + "_text", records, summary=summ)
    print_table(summ, ["set", "data", "prompts", "queries", "top1_present", "refused_absent", "misses"],
                title="text grounding: present top-1 and absent refusals")
    return 0


def main() -> int:
    args = bench_args(NAME, __doc__.split("\n\n")[0], extra_args)
    if args.text_only:
        return text_main(args)
    work = args.work or (args.out / "ground_work")
    t0 = time.perf_counter()
    if args.run:
        run_dir = args.run
        if args.capture is None:
            raise SystemExit("--run needs --capture (the capture the run's truth dataset was made from)")
        cap = args.capture
    else:
        cap = args.capture or make_capture(work, args.quick)
        run_dir = make_run(work, cap, args)
    data = capture_label(cap)
    count = args.eval_views if args.eval_views is not None else (4 if args.quick else 12)
    records, meta = grounding_records(run_dir, cap, args.mask_threshold, data, count, args.eval_scale)
    records += text_only_records("synth-10kinds-text")
    summ = summary(records)
    write_results(args.out, NAME, records, summary=summ, wall_s=round(time.perf_counter() - t0, 1),
                  capture=str(cap), mask_threshold=args.mask_threshold, **meta)
    chart(args.out / f"{NAME}.png", records, summ)
    print_table(records, ["data", "query", "phrasing", "object", "retrieved_ok", "score", "iou", "iou_oracle",
                          "iou_truth_states"],
                title="grounding per query")
    print_table([{"data": k, **v} for k, v in summ.items()],
                ["data", "queries", "retrieval_accuracy", "miou", "miou_oracle", "miou_truth_states",
                 "miou_dataset_masks"], title="summary")
    print(f"-> {args.out / (NAME + '.json')}, {args.out / (NAME + '.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
