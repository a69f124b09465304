"""`motions.colour`: the frames whose mask the masks stage lost, read by the part's colours; they steer the edge
route's angle path and never measure a state."""

from __future__ import annotations

import numpy as np
from edge_scenes import KEYS, TALL, capture, off_deg, painted

from interreal.motions.colour import SWEEP, ColourSilhouettes
from interreal.motions.edge import measure_edge
from interreal.motions.leaf import Leaf, Line, iou_curves
from interreal.motions.silhouette import Silhouettes, views_of


def test_a_frame_without_a_mask_reads_the_doors_angle_by_its_colour():
    """The keyframes teach the door's colour; a frame whose mask is lost says which angle of the leaf its pixels
    agree with, closed or open."""
    ds, truth, st, kn, labelled, masks = capture("hinge")
    images = painted(masks)
    ds.load_image = lambda f: images[f.index]
    views = views_of(ds, 0)
    leaf = Leaf(Line(TALL[3].copy(), TALL[0].copy(), 0.0, 0))  # the true hinge: the left edge, bottom to top
    size = np.array([0.25, 0.0, 1.0])  # 0.5 wide on a 2.0 line
    colour = ColourSilhouettes(views, Silhouettes(views, KEYS), KEYS, [leaf.corners(*size, a) for a in SWEEP])
    angles = np.radians(np.arange(-180, 180, 2.5))
    curves = iou_curves(colour, leaf, size, [5, 25], angles)  # closed, fully open; neither a keyframe
    turned = np.degrees(angles[curves[1].argmax()] - angles[curves[0].argmax()])
    assert abs(abs((turned + 180) % 360 - 180) - 80.0) <= 5.0, turned
    assert curves.max(1).min() > 0.8, curves.max(1)


def test_frames_whose_mask_is_lost_steer_the_path_by_colour_but_measure_nothing():
    ds, truth, st, kn, labelled, masks = capture("hinge")
    images = painted(masks)
    lost = range(13, 27)  # the door lost while it opened and came to rest open
    for i in lost:
        masks[i] = np.zeros_like(masks[i])
    ds.load_mask = lambda f: masks[f.index]
    ds.load_image = lambda f: images[f.index]
    motion, fig = measure_edge(ds, 0, st, kn, labelled, KEYS, min_pixels=50)
    assert motion is not None and fig["accepted"], fig
    assert off_deg(motion.axis, [0.0, 0.0, 1.0]) < 2.0 and abs(np.degrees(motion.range) - 80) < 12
    assert fig["edge_read_by_colour"] == len(lost)
    assert not {f for f, _ in fig["frame_states"]} & set(lost)  # a state is only ever read from a mask
