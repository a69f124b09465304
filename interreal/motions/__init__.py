"""`interreal motions`: how each object moves with its state, measured from the video -> DS/articulation.json.

One module per route, one for the decision they share, and the stage that runs them:
- `stage`: the command (`estimate_motions`): every part measured (several at once, a process each), the report;
- `part`: one part: its masks, its own SfM (the first route), the routes in turn (`measure_part`);
- `known`: a refused own reconstruction's (or a slide's) tracks posed by the known cameras, moved as the kind can;
- `reach`: a hinge from poses carried by the part's masks into the frames past the angles its route registered,
  and the frames a person is asked to draw where an end is still the labels' guess;
- `pnp`: the part triangulated where it rests with the known cameras, then located in every frame by PnP;
- `silhouette`: a part too plain for both: its flat front from its masks, the motion whose silhouettes fit them;
- `edge`: a plain door or lid cut by the image border, hinged on the one edge of its outline that stays put;
- `prism`: a plain drawer: its front at rest on such an edge, pulled out along its normal, judged against a door;
- `fit`: poses or displacements -> a hinge or a slide decided by the geometry, every frame's state, the labels only
  orienting it (the ones that disagree flagged).
A new route is a module here that returns what `fit.articulate` reads.
"""

from .fit import PartViews, fit_motion
from .part import MotionConfig, PartMasks, measure_part, part_masks, part_pairs
from .stage import (add_arguments, estimate_motions, flagged_labels, frame_state_rows, frames_asked, main,
                    measured_line, part_line, part_summary, routes_text)

__all__ = ["MotionConfig", "PartMasks", "PartViews", "add_arguments", "estimate_motions", "fit_motion",
           "flagged_labels", "frame_state_rows", "frames_asked", "main", "measure_part", "measured_line", "part_line",
           "part_masks", "part_pairs", "part_summary", "routes_text"]
