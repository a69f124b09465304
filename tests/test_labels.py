"""`interreal label`: set / unset / list / import, unit conversion, bad values, object add and rename."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from interreal import labels as L
from interreal.atomic import write_image, write_json, write_yaml
from interreal.cli import main as cli
from interreal.dataset import read_labels, read_mapping, read_prompts
from interreal.errors import InputError
from interreal.report import read_report

FRAMES = (0, 5, 10, 42)


@pytest.fixture
def ds(tmp_path):
    root = tmp_path / "ds"
    for i in FRAMES:
        write_image(root / "images" / f"frame_{i:05d}.png", np.full((12, 16, 3), 10 * i % 255, np.uint8))
    write_yaml(root / "mapping.yaml", {0: "fridge door"})
    return root


def run(ds, *argv) -> int:
    return cli(["label", str(ds), *argv])


def test_set_unset_list(ds, capsys):
    assert run(ds, "--set", "fridge door", "42", "0.25", "--set", "fridge door", "frame_00005", "1") == 0
    assert read_labels(ds) == {"frame_00005": {"fridge door": 1.0}, "frame_00042": {"fridge door": 0.25}}
    assert run(ds, "--unset", "fridge door", "00042") == 0
    assert read_labels(ds) == {"frame_00005": {"fridge door": 1.0}}
    capsys.readouterr()
    assert run(ds, "--list") == 0
    table = capsys.readouterr().out
    assert "frame_00005" in table and "1.000" in table and "fridge door" in table
    assert run(ds, "--list", "--json") == 0
    assert json.loads(capsys.readouterr().out) == [{"frame": "frame_00005", "object": "fridge door", "value": 1.0}]
    rep = read_report(ds, "labels")
    assert rep["status"] == "ok" and rep["figures"]["labels"] == 1


def test_unit_conversion(ds):
    assert run(ds, "--set", "fridge door", "5", "45", "--degrees", "0:90") == 0
    assert run(ds, "--add-object", "top drawer", "--set", "top drawer", "10", "12", "--cm", "0:40") == 0
    assert run(ds, "--set", "fridge door", "42", "30", "--degrees", "90:0") == 0  # closed at 90 degrees
    got = read_labels(ds)
    assert got["frame_00005"]["fridge door"] == pytest.approx(0.5)
    assert got["frame_00010"]["top drawer"] == pytest.approx(0.3)
    assert got["frame_00042"]["fridge door"] == pytest.approx(2 / 3)
    assert L.normalise_value("90", L.parse_range("0:90", "degrees")) == 1.0
    u = {"degrees": L.parse_range("0:90", "degrees"), "cm": L.parse_range("10:50", "cm")}
    assert L.normalise_value(math.pi / 4, row_unit="rad", units=u) == pytest.approx(0.5)
    assert L.normalise_value(300, row_unit="mm", units=u) == pytest.approx(0.5)


@pytest.mark.parametrize("value, unit, message", [
    ("nan", [], "not a finite number"),
    ("inf", [], "not a finite number"),
    ("1.2", [], "outside [0, 1]"),
    ("-0.1", [], "outside [0, 1]"),
    ("half", [], "is not a number"),
    ("100", ["--degrees", "0:90"], "outside the range 0:90"),
])
def test_bad_values_rejected(ds, capsys, value, unit, message):
    assert run(ds, "--set", "fridge door", "5", value, *unit) == 2
    assert message in capsys.readouterr().err
    assert read_labels(ds) == {}
    assert read_report(ds, "labels") is None  # a typo does not leave a failed stage behind for `validate`


def test_unknown_object_and_frame(ds, capsys):
    assert run(ds, "--set", "oven", "5", "0.5") == 2
    err = capsys.readouterr().err
    assert "unknown object 'oven'" in err and "--add-object" in err
    assert run(ds, "--set", "fridge door", "7", "0.5") == 2
    err = capsys.readouterr().err
    assert "frame 7 is not among the dataset's frames" in err and "frame_00005" in err
    assert run(ds, "--set", "fridge door", "5", "0.5", "--set", "fridge door", "99", "0.5") == 2
    assert read_labels(ds) == {}  # all --set are checked before any is written
    assert run(ds, "--add-object", "oven", "--set", "oven", "5", "2") == 2
    assert read_mapping(ds) == {0: "fridge door"}  # nor an object added by the same, refused, command
    assert run(ds, "--add-object", "oven", "--rename", "oven", "stove", "--set", "stove", "5", "1") == 0
    assert read_mapping(ds) == {0: "fridge door", 1: "stove"} and read_labels(ds) == {"frame_00005": {"stove": 1.0}}
    capsys.readouterr()
    assert run(ds, "--degrees", "5:5", "--set", "fridge door", "5", "1") == 2
    assert "LO and HI must be finite and different" in capsys.readouterr().err
    with pytest.raises(InputError, match="no frames"):
        L.dataset_frames(ds / "nowhere")
    assert run(ds, "--add-object", "a=b") == 2
    assert "contains" in capsys.readouterr().err


def test_import_csv_with_units_adds_objects(ds, tmp_path):
    csv = tmp_path / "states.csv"
    csv.write_text("frame,object,value,unit\n0,fridge door,0,deg\nframe_00042,fridge door,90,deg\n"
                   "5,top drawer,20,cm\n10,top drawer,0.75,\n")
    res = L.import_labels(ds, csv, degrees="0:90", cm=(0, 40), add_objects=True)  # new objects only on request
    assert res["imported"] == 4 and res["added_objects"] == ["top drawer"]
    assert read_mapping(ds) == {0: "fridge door", 1: "top drawer"}
    assert read_labels(ds) == {"frame_00000": {"fridge door": 0.0}, "frame_00005": {"top drawer": 0.5},
                               "frame_00010": {"top drawer": 0.75}, "frame_00042": {"fridge door": 1.0}}
    rep = read_report(ds, "labels")
    assert rep["status"] == "ok" and rep["figures"]["imported"] == 4


def test_import_rejects_whole_file_on_any_bad_row(ds, tmp_path, capsys):
    csv = tmp_path / "bad.csv"
    csv.write_text("frame,object,value\n0,fridge door,0.5\n7,fridge door,0.5\n5,fridge door,nan\n10,fridge door,2\n")
    assert run(ds, "--from", str(csv)) == 2
    err = capsys.readouterr().err
    assert "3 bad label(s), nothing imported" in err
    assert "bad.csv:3" in err and "bad.csv:4" in err and "bad.csv:5" in err
    assert read_labels(ds) == {}
    deg = tmp_path / "deg.csv"
    deg.write_text("frame,object,value,unit\n0,fridge door,45,deg\n")
    assert run(ds, "--from", str(deg)) == 2
    assert "give its range, e.g. --degrees 0:90" in capsys.readouterr().err
    assert run(ds, "--from", str(tmp_path / "missing.csv")) == 2
    assert "no such file" in capsys.readouterr().err


def test_import_yaml_synth_format(ds, tmp_path, capsys):
    states = tmp_path / "states.yaml"
    write_yaml(states, {"frame_00000": {"fridge door": 0.0, "top drawer": 0.1}, "frame_00042": {"fridge door": 1.0},
                        "frame_00077": {"fridge door": 0.4}})
    assert run(ds, "--from", str(states)) == 2
    assert "frame 77 is not among the dataset's frames" in capsys.readouterr().err
    assert run(ds, "--from", str(states), "--no-new-objects", "--skip-unknown-frames") == 2
    assert "unknown objects ['top drawer']" in capsys.readouterr().err
    assert run(ds, "--from", str(states), "--skip-unknown-frames") == 2  # new objects only with --add-objects
    assert "unknown objects ['top drawer']" in capsys.readouterr().err
    assert run(ds, "--from", str(states), "--skip-unknown-frames", "--add-objects") == 0
    assert read_labels(ds) == {"frame_00000": {"fridge door": 0.0, "top drawer": 0.1},
                               "frame_00042": {"fridge door": 1.0}}
    rep = read_report(ds, "labels")
    assert any("not in the dataset" in w["message"] for w in rep["warnings"])
    # merge by default, --replace on request
    write_yaml(states, {"frame_00005": {"fridge door": 0.5}})
    assert run(ds, "--from", str(states)) == 0
    assert set(read_labels(ds)) == {"frame_00000", "frame_00005", "frame_00042"}
    assert run(ds, "--from", str(states), "--replace") == 0
    assert read_labels(ds) == {"frame_00005": {"fridge door": 0.5}}


def test_rename_updates_everything(ds, capsys):
    kf = ds / "keyframes"
    write_yaml(kf / "mapping.yaml", {0: "fridge door"})
    write_json(kf / "00042.json", {"shapes": [{"label": "fridge door", "shape_type": "polygon", "points": [[0, 0], [4, 0], [4, 4]]}]})
    write_yaml(ds / "prompts.yaml", {"fridge door": "keeps food cold"})
    assert run(ds, "--add-object", "top drawer", "--set", "fridge door", "5", "0.5", "--set", "top drawer", "5", "0.1") == 0
    assert read_mapping(kf) == {0: "fridge door", 1: "top drawer"}  # keyframes mapping follows the dataset's
    assert run(ds, "--rename", "fridge door", "fridge") == 0
    assert read_mapping(ds) == {0: "fridge", 1: "top drawer"}
    assert read_mapping(kf) == {0: "fridge", 1: "top drawer"}
    assert read_labels(ds) == {"frame_00005": {"top drawer": 0.1, "fridge": 0.5}}
    assert read_prompts(ds) == {"fridge": "keeps food cold"}
    assert json.loads((kf / "00042.json").read_text())["shapes"][0]["label"] == "fridge"
    assert run(ds, "--rename", "fridge", "top drawer") == 2
    assert "exists already" in capsys.readouterr().err
    assert run(ds, "--rename", "oven", "stove") == 2
    assert "unknown object 'oven'" in capsys.readouterr().err


def test_add_object_is_idempotent_and_describe(ds):
    assert L.add_object(ds, "fridge door") == 0
    assert L.add_object(ds, "  laptop lid ", description="a lid that hinges") == 1
    assert read_mapping(ds) == {0: "fridge door", 1: "laptop lid"}
    assert read_prompts(ds) == {"laptop lid": "a lid that hinges"}
    assert run(ds, "--describe", "fridge door", "white, tall") == 0
    assert read_prompts(ds)["fridge door"] == "white, tall"
    out = L.set_label(ds, "laptop lid", 10, 0.5)
    assert out == {"key": "frame_00010", "object": "laptop lid", "value": 0.5, "previous": None}
    assert L.unset_label(ds, "laptop lid", 10) == 0.5 and L.unset_label(ds, "laptop lid", 10) is None
    assert L.list_labels(ds) == []
    assert yaml.safe_load((ds / "key_frame_value.yaml").read_text()) == {}


def test_written_files_validate(ds):
    """What `label` writes is accepted by the dataset validator's label checks."""
    from interreal.dataset import validate

    assert run(ds, "--set", "fridge door", "5", "0.5") == 0
    kinds = {p.kind for p in validate(ds, check_masks=False).problems}
    assert not kinds & {"bad-labels", "label-bad-value", "label-unknown-object", "bad-mapping", "bad-yaml"}


def test_list_warns_about_stale_labels(ds, capsys):
    write_yaml(ds / "key_frame_value.yaml", {"frame_00005": {"fridge door": 0.5, "oven": 0.2}, "frame_00099": {"fridge door": 1.0}})
    assert run(ds, "--list") == 0
    err = capsys.readouterr().err
    assert "object 'oven' is not in mapping.yaml" in err and "frame 99 is not among the dataset's frames" in err


@pytest.mark.parametrize("sep", [";", "\t"])
def test_spreadsheets_from_decimal_comma_locales_import(ds, tmp_path, sep):
    """What Excel writes where the decimal mark is a comma: `;` (or tab) separated, `0,5` for a half. It was told
    its header lacked frame,object,value and that 0,5 is not a number."""
    f = tmp_path / "states.csv"
    f.write_text(sep.join(["frame", "object", "value"]) + "\n" + sep.join(["0", "fridge door", "0,5"]) + "\n"
                 + sep.join(["5", "fridge door", "1"]) + "\n", encoding="utf-8-sig")
    assert L.import_labels(ds, f)["imported"] == 2
    assert read_labels(ds) == {"frame_00000": {"fridge door": 0.5}, "frame_00005": {"fridge door": 1.0}}


def test_a_frame_and_object_labelled_twice_is_refused_by_name(ds, tmp_path):
    """Two rows for one (frame, object) with different values imported as "2 labels", keeping the last, silently;
    a duplicate YAML key the same. Now both name the rows; the same value twice is one label."""
    f = tmp_path / "states.csv"
    f.write_text("frame,object,value\n0,fridge door,0.2\n5,fridge door,1\nframe_00000,fridge door,0.8\n")
    with pytest.raises(InputError, match=r"'fridge door' on frame_00000 is labelled twice, 0.2 at states.csv:2 and "
                                         r"0.8 here"):
        L.import_labels(ds, f)
    assert read_labels(ds) == {}  # nothing written
    f.write_text("frame,object,value\n0,fridge door,0.2\n0,fridge door,0.2\n")
    assert L.import_labels(ds, f)["imported"] == 1
    y = tmp_path / "states.yaml"
    y.write_text("frame_00005:\n  fridge door: 0.0\nframe_00005:\n  fridge door: 1.0\n")
    with pytest.raises(InputError, match="'frame_00005' is given twice"):
        L.import_labels(ds, y)
