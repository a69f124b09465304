"""The user-facing settings of the `masks` stage (`MasksConfig`): the flags of `interreal masks` and of
`interreal process`, the keyword options of `propagate`, and the `TrackConfig` they make."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import InputError
from ..options import option
from .appearance import AppearanceConfig
from .flow import FlowConfig
from .track import TrackConfig
from .workframes import WORK_LONG_SIDE

PREVIEW_KINDS = ("sheet", "video", "both", "none")
TRANSIENT_MODES = ("auto", "off")


@dataclass
class MasksConfig:
    """Settings of one `interreal masks` run; the fields declared with `option` are its flags."""

    work_long_side: int = option(-1, "long side of the flow/propagation resolution (0 = full size; -1 = the default, "
                                     f"{WORK_LONG_SIDE})",
                                 flag="--work-size", metavar="PX")
    flow: str = option("dis", "optical flow", choices=("dis", "rlof", "farneback"))
    preset: str = option("fast", "DIS preset", choices=("ultrafast", "fast", "medium"))
    appearance: float = option(0.25, "weight of the colour model (0 = off)")
    rigid: float = option(1.0, "weight of the per-object homography motion (0 = off)")
    cut: float = option(0.5, "share of each object's probability a GrabCut of the frame sets, on the frames before "
                                  "the first and after the last keyframe (0 = off: faster)")
    fusion: bool = option(True, "forward chain only (no backward fusion)", flag="--no-fusion")
    refine: bool = option(True, "no guided-filter boundary refinement", flag="--no-refine")
    suggest: int = option(5, "print the N frames where one more keyframe would help most", metavar="N")
    preview: str = option("both", "DS/previews/masks_sheet.png and/or masks_overlay.mp4", choices=PREVIEW_KINDS)
    transients: str = option("auto", "the transient layer (hands, arms) without painting: auto = from the hand model "
                                     "(mediapipe), grown to the arm; off = only the painted ignore class",
                             choices=TRANSIENT_MODES)
    reuse: bool = option(True, "make every frame again (by default the stretches between keyframes that no keyframe "
                               "change touched are taken from the last run)", flag="--no-reuse")
    sfm_dilate: int | None = None  # px the SfM masks grow by (None = 0.6 % of the image diagonal, at least 2)

    def __post_init__(self) -> None:
        for name, lo, hi in (("cut", 0.0, 1.0), ("rigid", 0.0, 1.0), ("appearance", 0.0, float("inf"))):
            v = getattr(self, name)
            if not lo <= v <= hi:  # also refuses NaN
                raise InputError(f"--{name} {v}: give a value in [{lo:g}, {hi:g}]" if hi < float("inf")
                                 else f"--{name} {v}: give a value of at least {lo:g}")

    def track_config(self) -> TrackConfig:
        """The propagation settings these options give."""
        return TrackConfig(flow=FlowConfig(method=self.flow, preset=self.preset),
                           appearance=AppearanceConfig(weight=self.appearance), work_long_side=self.work_long_side,
                           rigid=self.rigid, cut=self.cut, fusion=self.fusion,
                           refine_radius=TrackConfig.refine_radius if self.refine else 0,
                           out_radius=TrackConfig.out_radius if self.refine else 0)
