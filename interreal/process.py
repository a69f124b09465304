"""`interreal process INPUT DS`: frames -> masks (with --keyframes) -> poses -> labels (with --labels) -> motions
(with both).

The order matters: masks come before poses so object pixels are left out of SfM features, and the frames named by
the annotations are forced into the selection so every annotated frame survives.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from . import provenance
from .conventions import frame_index
from .errors import InputError
from .frames import FramesConfig, extract_frames, frames_options
from .masks.config import MasksConfig
from .motions import estimate_motions, measured_line
from .options import add_flags, options_of, values_from_args
from .labels import add_unit_arguments, import_labels, parse_range, read_label_file
from .labels.prompts import find_prompts, import_prompts, read_prompt_file
from .masks import left_view_lines, propagate, transient_line
from .report import StageReport, read_report, warning_lines
from .sfm import add_sfm_options, estimate_poses, sfm_options, summary_lines

KEYFRAME_SUFFIXES = (".png", ".json")


def keyframe_indices(keyframes_dir: Path) -> list[int]:
    """Source indices of annotated keyframes: files named by frame id (00042.png / 00042.json / frame_00042.png)."""
    if not keyframes_dir.is_dir():
        raise InputError(f"--keyframes {keyframes_dir} is not a folder")
    out = []
    for p in keyframes_dir.iterdir():
        if p.suffix.lower() in KEYFRAME_SUFFIXES:
            try:
                out.append(frame_index(p.stem))
            except ValueError:
                continue
    if not out:
        raise InputError(f"--keyframes {keyframes_dir} has no keyframe files named by frame id (e.g. 00042.png)")
    return sorted(set(out))


def label_indices(labels_file: Path) -> list[int]:
    """Source indices of the frames a labels file (key_frame_value YAML, or CSV frame,object,value) names, read
    by the parser `interreal label --import` uses."""
    out = []
    for row in read_label_file(labels_file):
        try:
            out.append(frame_index(str(row["frame"])))
        except ValueError:
            continue  # not a frame name: `import_labels` will name the row
    return sorted(set(out))



def process(source: str | Path, ds: str | Path, *, keyframes: str | Path | None = None,
            labels: str | Path | None = None, motions: bool = True, degrees: Any = None, cm: Any = None,
            trust_labels: bool = False, prompts: str | Path | None = None, **opts: Any) -> dict[str, Any]:
    """Run the stages in order; each writes its own reports/<stage>.json, and reports/process.json collects their
    warnings. Returns the pose figures. With masks and labels, `motions` also measures each object's rigid motion
    (`interreal motions`; `trust_labels` as its --trust-labels). degrees / cm: physical label values, as
    `interreal label --degrees / --cm`. `prompts`: the objects' descriptions for text grounding (prompts.yaml);
    without it, the `prompts.yaml` beside the keyframes or labels (a capture's annotations) fills the objects that
    have none.

    `opts`: the fields of `FramesConfig` (target, every, long_side, keep), of `MasksConfig` (work_long_side, flow,
    ...) and of `SfMConfig` (the rest; an unknown name is an InputError of the poses stage)."""
    ds = Path(ds)
    frames_opts, masks_opts = options_of(FramesConfig, opts), options_of(MasksConfig, opts)
    sfm = {k: v for k, v in opts.items() if k not in frames_opts and k not in masks_opts}
    if (degrees is not None or cm is not None) and labels is None:
        raise InputError("--degrees / --cm give the range of --labels values: add --labels FILE, or drop them")
    keep: set[int] = {int(k) for k in frames_opts.pop("keep", None) or ()}
    if keyframes is not None:
        keep |= set(keyframe_indices(Path(keyframes)))
    if labels is not None:
        keep |= set(label_indices(Path(labels)))
    if labels is not None and (degrees is not None or cm is not None):
        parse_range(degrees, "degrees"), parse_range(cm, "cm")  # a malformed range fails now, not after SfM
    prompt_file = Path(prompts) if prompts is not None else find_prompts(
        Path(keyframes) if keyframes is not None else None, Path(labels) if labels is not None else None)
    if prompt_file is not None:
        read_prompt_file(prompt_file)  # a malformed file fails now, not after SfM
    settings = {"keyframes": str(keyframes) if keyframes else None, "labels": str(labels) if labels else None,
                "prompts": str(prompt_file) if prompt_file else None,
                **frames_opts, "motions": motions, "trust_labels": trust_labels, "degrees": degrees, "cm": cm,
                **masks_opts, **sfm}
    ds.mkdir(parents=True, exist_ok=True)
    with StageReport(ds, "process", inputs={"source": str(source)}, settings=settings) as rep:
        with rep.step("frames") as st:
            paths = extract_frames(source, ds, keep=sorted(keep), **frames_opts)
            st["frames"] = len(paths)
        _collect_warnings(rep, ds, "frames")
        # a stage not asked for but already in the dataset runs again when its inputs changed (new frames, ...)
        kf_dir = Path(keyframes) if keyframes is not None else _stale_keyframes(ds)
        if kf_dir is not None:
            with rep.step("masks") as st:
                st["keyframes"] = str(kf_dir)
                propagate(ds, kf_dir, **masks_opts)
            _collect_warnings(rep, ds, "masks")
        with rep.step("poses"):
            fig = estimate_poses(ds, **sfm)
        _collect_warnings(rep, ds, "poses")
        if labels is not None:
            # labels of another capture (the frames now come from another video) are replaced, not merged
            replace = any(s.stage == "labels" and "capture" in s.reasons for s in provenance.stale_stages(ds))
            with rep.step("labels") as st:
                st["replace"] = replace
                units = {k: v for k, v in (("degrees", degrees), ("cm", cm)) if v is not None}
                import_labels(ds, Path(labels), **units, **({"replace": True} if replace else {}))
            _collect_warnings(rep, ds, "labels")
        if prompt_file is not None:
            with rep.step("prompts") as st:
                st.update(import_prompts(ds, prompt_file, overwrite=prompts is not None))
            for name, close in st["skipped"].items():
                rep.warn(f"{prompt_file} describes {name!r}, which is not an object of the dataset"
                         + (f" (did you mean {close!r}?)" if close else ""), cause="prompt-unknown-object")
        had_motions = read_report(ds, "motions") is not None
        if motions and ((kf_dir is not None and labels is not None) or had_motions):
            with rep.step("motions") as st:
                st.update(estimate_motions(ds, trust_labels=trust_labels))
            _collect_warnings(rep, ds, "motions")
        left = [s.message for s in provenance.stale_stages(ds)]
        for message in left:
            rep.warn(message, cause="stale")
        rep.figures.update({"frames": len(paths), "registered": fig.get("registered"), "total": fig.get("total"),
                            "stale": left})
    return {**fig, "stale": left}


def _collect_warnings(rep: StageReport, ds: Path, stage: str) -> None:
    """Copy a stage's warnings into the process report (tagged with the stage), so reports/process.json says
    everything the run noticed, not only its own bookkeeping."""
    for w in (read_report(ds, stage) or {}).get("warnings", []):
        entry = dict(w) if isinstance(w, dict) else {"message": str(w)}
        rep.warn(str(entry.pop("message", "")), cause=entry.pop("cause", None), **{**entry, "stage": stage})


def prompts_line(f: dict[str, Any]) -> str:
    """What the prompts step imported, and which objects text grounding finds by name alone."""
    return (f"prompts: {len(f.get('imported', []))} description(s) from {f.get('file')}"
            + (f"; found by name alone: {', '.join(f['without'])}" if f.get("without") else "")
            + "".join(f"\n  warning: {f.get('file')} describes {n!r}, which is not an object"
                      + (f" (did you mean {c!r}?)" if c else "") for n, c in (f.get("skipped") or {}).items()))


def stage_summary(ds: Path, stage: str) -> str | None:
    """What a stage made, from its report's figures: one line (motions: and one per part it measured); None when it
    has no report."""
    r = read_report(ds, stage)
    if r is None:
        return None
    f = r.get("figures", {})
    if stage == "frames":
        return (f"frames: {f.get('selected', '?')} selected of {f.get('source_frames', '?')} source frames"
                + (f", {len(f['unusable_indices'])} unusable" if f.get("unusable_indices") else "")
                + (f", size {f['size'][0]}x{f['size'][1]}" if len(f.get("size") or ()) == 2 else ""))
    if stage == "masks":
        mean = f.get("confidence_mean") or {}
        transients = transient_line(f)
        return (f"masks: {f.get('frames', '?')} frames from {len(f.get('keyframes') or [])} keyframes"
                + ("; predicted J " + ", ".join(f"{n} {v:.2f}" for n, v in mean.items()) if mean else "")
                + (f"; suggested keyframes {', '.join(map(str, f['suggested_frames'][:5]))}"
                   if f.get("suggested_frames") else "")
                + (f"\n  {transients}" if transients else "")
                + "".join(f"\n  {line}" for line in left_view_lines(f)))
    if stage == "labels":
        return (f"labels: {f.get('imported', '?')} imported, {f.get('labels', '?')} in the dataset"
                + (f" for {', '.join(f['objects'])}" if f.get("objects") else "")
                + (f", {len(f['skipped_frames'])} rows skipped" if f.get("skipped_frames") else ""))
    if stage == "motions":
        return measured_line(f)
    return None


def _stale_keyframes(ds: Path) -> Path | None:
    """The keyframe folder the dataset's masks were made from, when those masks are stale and it is still there
    (not when the frames come from another capture: its keyframes would be drawn on other images)."""
    stale = [s for s in provenance.stale_stages(ds) if s.stage == "masks"]
    if not stale or "capture" in stale[0].reasons:
        return None
    rec = provenance.recorded(read_report(ds, "masks")).get("keyframes") or {}
    folder = Path(str(rec.get("path", "")))
    folder = ds / folder if rec.get("inside") else folder
    if rec.get("path") and folder.is_dir():
        print(f"masks: the frames changed since the masks were made: propagating again from {folder}")
        return folder
    return None


def add_arguments(p) -> None:
    p.add_argument("input", type=Path, help="video file, image folder or RAW folder")
    p.add_argument("dataset", type=Path, help="dataset folder to create / update")
    p.add_argument("--keyframes", type=Path, help="keyframe masks folder (00042.png index masks or LabelMe .json)")
    p.add_argument("--labels", type=Path, help="keyframe states (key_frame_value.yaml format, or CSV)")
    add_flags(p.add_argument_group("frames"), FramesConfig)
    p.add_argument("--no-motions", dest="motions", action="store_false",
                   help="with --keyframes and --labels: skip measuring each object's rigid motion")
    p.add_argument("--prompts", type=Path, metavar="FILE",
                   help="object descriptions for text grounding (YAML: name: one line of what it is or does; "
                        "default: the prompts.yaml beside --keyframes or --labels, for objects that have none)")
    p.add_argument("--trust-labels", action="store_true",
                   help="let the state labels calibrate each measured motion and refuse it when most disagree "
                        "(default: the geometry measures every frame's state, the labels only orient it)")
    add_unit_arguments(p)
    add_flags(p.add_argument_group("masks (with --keyframes)"), MasksConfig)
    add_sfm_options(p.add_argument_group("poses"))
    p.epilog = ("examples:\n  interreal process room.mp4 out/room\n"
                "  interreal process cap/video.mp4 out/ds --keyframes cap/annotations/keyframes \\\n"
                "      --labels cap/annotations/states.yaml --target 200\n"
                "  interreal process photos/ out/obj --matcher exhaustive --mapper global")


def main(args) -> int:
    t0 = time.perf_counter()
    fig = process(args.input, args.dataset, keyframes=args.keyframes, labels=args.labels, motions=args.motions,
                  trust_labels=args.trust_labels, prompts=args.prompts, degrees=args.degrees, cm=args.cm,
                  **frames_options(args),
                  **values_from_args(MasksConfig, args),
                  **sfm_options(args))
    steps = (read_report(args.dataset, "process") or {}).get("steps", {})
    lines: list[str] = []
    for stage in steps:  # each stage that ran: what it made, then its warnings
        if stage == "poses":
            lines += summary_lines(fig, args.dataset)
            continue
        if stage == "prompts":  # a step of process itself (no report of its own)
            lines.append(prompts_line(steps[stage]))
            continue
        line = stage_summary(args.dataset, stage)
        lines += ([line] if line else []) + warning_lines(args.dataset, [stage])
    print("\n".join(lines + [f"  warning: {m}" for m in fig.get("stale", [])]))
    print(f"process: done in {time.perf_counter() - t0:.1f} s -> {args.dataset}")
    return 0
