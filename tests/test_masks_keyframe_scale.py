"""Keyframes drawn on the source video are scaled to the extracted frames when the aspect ratio matches."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from interreal.atomic import write_image
from interreal.errors import InputError
from interreal.masks.keyframes import load_keyframes, same_aspect


def test_same_aspect():
    assert same_aspect((640, 480), (320, 240)) and same_aspect((1920, 1080), (1600, 900))
    assert not same_aspect((640, 480), (640, 360))


def test_png_drawn_at_video_size_is_scaled(tmp_path):
    m = np.zeros((480, 640), np.uint8)
    m[100:300, 200:400] = 1
    write_image(tmp_path / "00005.png", m)
    (tmp_path / "mapping.yaml").write_text(yaml.safe_dump({0: "door"}))
    kf = load_keyframes(tmp_path, ["00000", "00005"], (320, 240), {})
    got = kf.masks["00005"]
    assert got.shape == (240, 320)
    assert (got == 1).sum() == 100 * 100 and got[50:150, 100:200].all()


def test_labelme_drawn_at_video_size_is_scaled(tmp_path):
    doc = {"shapes": [{"label": "door", "shape_type": "polygon", "points": [[200, 100], [400, 100], [400, 300], [200, 300]]}],
           "imageWidth": 640, "imageHeight": 480}
    (tmp_path / "00005.json").write_text(json.dumps(doc))
    kf = load_keyframes(tmp_path, ["00005"], (320, 240), {0: "door"})
    got = kf.masks["00005"]
    ys, xs = np.nonzero(got == 1)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (100, 200, 50, 150)


def test_other_aspect_is_refused(tmp_path):
    write_image(tmp_path / "00005.png", np.ones((360, 640), np.uint8))
    (tmp_path / "mapping.yaml").write_text(yaml.safe_dump({0: "door"}))
    with pytest.raises(InputError, match="another aspect ratio"):
        load_keyframes(tmp_path, ["00005"], (320, 240), {})
