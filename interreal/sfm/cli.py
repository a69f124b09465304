"""`interreal poses DS`: its flags (shared with `interreal process`), the options they give, and the summary printed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..layout import COLMAP_DIR, PLY_FILE, TRANSFORMS_FILE
from ..report import report_path, warning_lines
from ..options import add_flags, values_from_args
from .config import SfMConfig
from .stage import estimate_poses


def add_arguments(p) -> None:
    p.add_argument("dataset", type=Path, help="dataset folder with images/ (from `interreal frames`)")
    add_sfm_options(p)
    p.add_argument("--poses", type=Path, help="import poses from a transforms.json (nerfstudio/Polycam) or a COLMAP "
                                              "model folder instead of running SfM")
    p.epilog = ("examples:\n  interreal poses out/room                       # auto matcher, incremental mapping\n"
                "  interreal poses out/room --mapper global       # GLOMAP-style global SfM\n"
                "  interreal poses out/room --matcher exhaustive --camera-model OPENCV\n"
                "  interreal poses out/room --poses polycam/transforms.json   # skip SfM\n"
                "  interreal poses out/room --intrinsics K.txt    # known camera (3x3 K as text, or JSON), held fixed")


def add_sfm_options(p) -> None:
    """The SfM flags (shared with `interreal process`): one per `option` field of `SfMConfig`."""
    add_flags(p, SfMConfig)


def sfm_options(args) -> dict[str, Any]:
    """`estimate_poses` options from the parsed flags (every flagged field, its default when not given)."""
    return values_from_args(SfMConfig, args)


def summary_lines(fig: dict[str, Any], ds: Path) -> list[str]:
    intr = fig.get("intrinsics", {})
    lines = [f"poses: {fig.get('registered')}/{fig.get('total')} frames registered"
             + (f", reprojection {fig['mean_reproj_error_px']:.2f} px, track length {fig['mean_track_length']:.1f}, "
                f"{fig['points3D']} points" if "mean_reproj_error_px" in fig else ""),
             f"  camera: {intr.get('w')}x{intr.get('h')} f=({intr.get('fl_x', 0):.1f}, {intr.get('fl_y', 0):.1f}) "
             f"c=({intr.get('cx', 0):.1f}, {intr.get('cy', 0):.1f}) k1={intr.get('k1', 0):.4f}"]
    given = fig.get("intrinsics_given")
    if given:
        lines.append(f"  intrinsics from {given['source']} ({given['note']}), "
                     + ("held fixed" if given.get("held") else "refined by bundle adjustment"))
    if fig.get("parallax", {}).get("parallax_deg_max") is not None:
        px = fig["parallax"]
        lines.append(f"  parallax before mapping: {px['parallax_deg_max']:.1f} deg (largest of {px['pairs_judged']} "
                     f"frame pairs; median {px['parallax_deg_median']:.1f} deg; checked in {px['wall_s']:.1f}s)")
    if fig.get("steps"):
        lines.append("  time: " + ", ".join(f"{k} {v:.1f}s" for k, v in fig["steps"].items() if v is not None))
    if len(fig.get("ladder", [])) > 1:
        tried = ", ".join(f"{t['rung']} {t['registered']}/{fig.get('total')}" for t in fig["ladder"])
        lines.append(f"  retry ladder: {tried}; kept '{fig.get('chosen_attempt')}'")
    lines += warning_lines(ds, ["poses"])
    outs = [ds / TRANSFORMS_FILE] + ([ds / COLMAP_DIR / "sparse" / "0", ds / PLY_FILE] if "imported" not in fig else [])
    lines.append("  -> " + ", ".join(str(p) for p in outs + [report_path(ds, "poses")]))
    return lines


def main(args) -> int:
    opts = sfm_options(args)
    fig = estimate_poses(args.dataset, poses=args.poses, **opts)
    print("\n".join(summary_lines(fig, args.dataset)))
    return 0
