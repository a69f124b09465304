"""Language grounding: command parsing, retrieval with the real packaged MiniLM model, the object-embedding cache,
the `livescene ground` CLI (retrieval path), a pluggable CLIP encoder, mask IoU, and the missing-extra message."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from interreal.errors import InputError, MissingExtraError
from livescene import cli
from livescene.errors import LiveSceneError
from livescene.language import encoders
from livescene.language.commands import apply_command, ground_query, object_texts, parse_command
from livescene.language.grounding import mask_iou, overlay
from livescene.language.retrieval import CACHE_FILE, ObjectIndex, RetrievalConfig, require_match, retrieve, run_index

NAMES = ["fridge door", "top drawer", "laptop lid", "cabinet door"]
DESCRIPTIONS = {
    "fridge door": "the door of the white refrigerator where food and drinks are kept cold",
    "top drawer": "the upper drawer of the wooden dresser, used for socks and small things",
    "laptop lid": "the screen of the notebook computer on the desk, it folds shut",
    "cabinet door": "the hinged door of the kitchen cupboard above the counter",
}
# (query, expected object): names, synonyms and paraphrases that are not copies of the descriptions
QUERIES = [
    ("fridge door", "fridge door"), ("the refrigerator", "fridge door"), ("where I keep the milk cold", "fridge door"),
    ("top drawer", "top drawer"), ("the upper drawer", "top drawer"), ("a drawer in the chest of drawers", "top drawer"),
    ("laptop lid", "laptop lid"), ("the notebook computer", "laptop lid"), ("the display of the laptop", "laptop lid"),
    ("cabinet door", "cabinet door"), ("the cupboard", "cabinet door"), ("kitchen cupboard door", "cabinet door"),
]


@pytest.fixture(scope="module")
def minilm():
    return encoders.get_encoder("minilm")


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    """A run folder with objects.yaml only: enough for retrieval, which never loads the model."""
    run = tmp_path / "run"
    run.mkdir()
    objects = {"objects": [{"name": n, "description": DESCRIPTIONS[n]} for n in NAMES]}
    (run / "objects.yaml").write_text(yaml.safe_dump(objects))
    return run


# ---------------------------------------------------------------------------------------------------------------
def test_parse_commands():
    cases = {
        "open the fridge": ("the fridge", 1.0), "Close the drawer.": ("the drawer", 0.0),
        "half open the door": ("the door", 0.5), "half-open the door": ("the door", 0.5),
        "open the door halfway": ("the door", 0.5), "shut the laptop lid": ("the laptop lid", 0.0),
        "please open the cabinet fully": ("the cabinet", 1.0), "open the door 30%": ("the door", 0.3),
        "set the lid to 0.25": ("the lid", 0.25),
    }
    for text, (query, value) in cases.items():
        cmd = parse_command(text)
        assert (cmd.query, cmd.value) == (query, pytest.approx(value)), text
    for bad in ("", "   ", "the fridge", "open the door 150%"):
        with pytest.raises(InputError):
            parse_command(bad)


def test_encoder_embeddings_are_normalised(minilm):
    emb = minilm.encode(["fridge door", "the thing that keeps food cold"])
    assert emb.shape == (2, 384) and emb.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    assert minilm.id.startswith("minilm:")
    assert encoders.get_encoder("minilm") is minilm  # loaded once per process


def test_retrieval_names_synonyms_paraphrases(minilm):
    index = ObjectIndex.build(NAMES, DESCRIPTIONS, minilm)
    wrong = []
    for query, expected in QUERIES:
        res = retrieve(index, query, minilm)
        assert res.ok, (query, res.table())
        assert [c.name for c in res.candidates] and abs(sum(c.prob for c in res.candidates) - 1) < 1e-5
        if res.best.name != expected:
            wrong.append((query, res.best.name))
    assert len(wrong) <= 1, wrong  # >= 11/12 (the benchmark asks for >= 0.9)
    assert retrieve(index, "the thing that keeps food cold", minilm).best.name == "fridge door"


def test_unrelated_query_matches_nothing(minilm):
    index = ObjectIndex.build(NAMES, DESCRIPTIONS, minilm)
    res = retrieve(index, "a purple elephant", minilm)
    assert not res.ok
    with pytest.raises(LiveSceneError, match="no object matches") as err:
        require_match(res)
    assert all(n in str(err.value) for n in NAMES)  # the ranked candidates are listed
    with pytest.raises(InputError, match="empty query"):
        retrieve(index, "  ", minilm)


class _Counting:
    def __init__(self, inner):
        self.inner, self.id, self.calls = inner, inner.id, 0

    def encode(self, texts):
        self.calls += 1
        return self.inner.encode(texts)


def test_run_index_is_cached_and_invalidated(run_dir, minilm):
    enc = _Counting(minilm)
    names, descs = object_texts(run_dir)
    assert names == NAMES and descs == DESCRIPTIONS
    a = run_index(run_dir, names, descs, enc)
    assert (run_dir / CACHE_FILE).exists() and enc.calls == 2  # names, descriptions
    b = run_index(run_dir, names, descs, enc)
    assert enc.calls == 2  # loaded from RUN/language.npz
    np.testing.assert_array_equal(a.name_emb, b.name_emb)
    descs2 = dict(descs, **{"laptop lid": "the lid of a laptop"})
    c = run_index(run_dir, names, descs2, enc)
    assert enc.calls == 4 and c.descriptions[2] == "the lid of a laptop"
    assert not list(run_dir.glob(".*.tmp"))  # atomic write left no temporary file


def test_absent_objects_are_refused_present_ones_found_as_people_ask(minilm):
    """The demo's scene (issue 60): "the dishwasher" went to the top drawer at 0.404; now it, and other things no
    object here is, are refused with what they read as; functions, commands and names find their object, with and
    without descriptions; the words of a name break a near tie (left / right)."""
    from interreal.synth import SynthConfig, build_scene

    scene = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24))
    names = scene.object_names[:2]  # fridge door, top drawer: the demo's
    for descriptions in ({n: scene.descriptions[n] for n in names}, None):
        index = ObjectIndex.build(names, descriptions, minilm)
        for query in ("the dishwasher", "the TV", "the garage door", "a purple elephant"):
            res = retrieve(index, query, minilm)
            assert not res.ok, (query, res.table())
        assert retrieve(index, "the dishwasher", minilm).reads_as == "dishwasher"
        for query, expected in (("open the top drawer", "top drawer"), ("the fridge", "fridge door"),
                                ("close the refrigerator", "fridge door"), ("the upper drawer", "top drawer")):
            res = retrieve(index, query, minilm)
            assert res.ok and res.best.name == expected, (query, res.table(), res.reads_as)
    index = ObjectIndex.build(names, {n: scene.descriptions[n] for n in names}, minilm)
    for query, expected in (("the thing that keeps food cold", "fridge door"),
                            ("where the cutlery is kept", "top drawer")):
        assert retrieve(index, query, minilm).best.name == expected
    with pytest.raises(LiveSceneError, match="not in this scene") as err:
        require_match(retrieve(index, "the dishwasher", minilm))
    assert "fridge door" in str(err.value) and "top drawer" in str(err.value)  # the nearest, listed
    doors = ObjectIndex.build(["wardrobe left door", "wardrobe right door"], None, minilm)
    assert retrieve(doors, "close the right wardrobe door", minilm).best.name == "wardrobe right door"
    assert retrieve(doors, "the left wardrobe door", minilm).best.name == "wardrobe left door"
    with pytest.raises(InputError, match="names nothing"):
        retrieve(index, "the of a", minilm)


def test_names_without_descriptions(minilm):
    index = ObjectIndex.build(["door", "drawer"], None, minilm)
    assert retrieve(index, "the drawer", minilm).best.name == "drawer"
    assert retrieve(index, "the door", minilm).best.matched == "name"


def test_cli_retrieval(run_dir, capsys):
    assert cli.main(["ground", str(run_dir), "the thing that keeps food cold"]) == 0
    out = capsys.readouterr().out
    assert "-> fridge door" in out and "top drawer" in out
    assert cli.main(["ground", str(run_dir), "open the upper drawer", "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["object"] == "top drawer" and payload["command"] == {"verb": "open", "value": 1.0}


def test_cli_bad_input(run_dir, tmp_path, capsys):
    assert cli.main(["ground", str(run_dir), ""]) == 2
    assert "empty query" in capsys.readouterr().err
    out = tmp_path / "g"
    assert cli.main(["ground", str(run_dir), "a purple elephant", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no object matches" in err and "fridge door" in err
    saved = json.loads((out / "ground.json").read_text())
    assert saved["ok"] is False and len(saved["candidates"]) == len(NAMES)
    assert cli.main(["ground", str(tmp_path / "nope"), "fridge"]) == 2
    assert "not a run folder" in capsys.readouterr().err


def test_apply_command(run_dir):
    assert apply_command(run_dir, "open the fridge") == {"fridge door": 1.0}
    assert apply_command(run_dir, "close the drawer") == {"top drawer": 0.0}
    assert apply_command(run_dir, "half open the cupboard") == {"cabinet door": 0.5}
    with pytest.raises(LiveSceneError, match="no object matches"):
        apply_command(run_dir, "open the purple elephant")
    with pytest.raises(InputError):
        apply_command(run_dir, "fridge")


def test_ground_query_threshold(run_dir):
    res = ground_query(run_dir, "the laptop's lid", config=RetrievalConfig(threshold=0.99))
    assert res.best.name == "laptop lid" and not res.ok


def test_missing_extra(monkeypatch, run_dir, capsys):
    """Without sentence-transformers the command says which extra to install."""
    monkeypatch.setitem(sys.modules, "sentence_transformers", None)  # makes `import sentence_transformers` fail
    encoders._cached.cache_clear()
    try:
        with pytest.raises(MissingExtraError, match=r"interreal\[language\]"):
            encoders.MiniLMEncoder()
        assert cli.main(["ground", str(run_dir), "the fridge"]) == 2
        err = capsys.readouterr().err
        assert "optional extra 'language'" in err and "pip install 'interreal[language]'" in err
        with pytest.raises(MissingExtraError):
            apply_command(run_dir, "open the fridge")
    finally:
        encoders._cached.cache_clear()


def _tiny_clip(folder: Path) -> Path:
    """A randomly initialised transformers CLIP with a character-level tokenizer, saved locally."""
    import torch
    import transformers as tr

    chars = "abcdefghijklmnopqrstuvwxyz"
    vocab = {t: i for i, t in enumerate(["<|startoftext|>", "<|endoftext|>", *chars, *(c + "</w>" for c in chars)])}
    folder.mkdir(parents=True)
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    tok = tr.CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"))
    text = dict(vocab_size=len(vocab), hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                num_attention_heads=2, max_position_embeddings=64, bos_token_id=0, eos_token_id=1, pad_token_id=1)
    vision = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=32,
                  patch_size=16)
    torch.manual_seed(0)
    tr.CLIPModel(tr.CLIPConfig(text_config=text, vision_config=vision, projection_dim=16)).save_pretrained(folder)
    tok.save_pretrained(folder)
    return folder


def test_clip_encoder_plugs_in(tmp_path):
    enc = encoders.get_encoder(f"clip:{_tiny_clip(tmp_path / 'clip')}")
    assert isinstance(enc, encoders.TextEncoder)
    emb = enc.encode(["fridge door", "laptop"])
    assert emb.shape == (2, 16)
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    index = ObjectIndex.build(NAMES, None, enc)
    res = retrieve(index, "laptop lid", enc, RetrievalConfig(threshold=0.0))
    assert res.best.name == "laptop lid" and res.best.score == pytest.approx(1.0, abs=1e-5)
    with pytest.raises(InputError, match="do not exist"):
        encoders.ClipEncoder(tmp_path / "missing")
    with pytest.raises(LiveSceneError, match="encoder"):  # embeddings of one encoder, a query from another
        retrieve(ObjectIndex.build(NAMES, None, enc), "fridge", _Counting(encoders.get_encoder("minilm")))


def test_mask_iou_and_overlay():
    a = np.zeros((10, 10), bool)
    b = np.zeros((10, 10), bool)
    a[2:6, 2:6] = True  # 16 px
    b[4:8, 4:8] = True  # 16 px, 4 shared
    assert mask_iou(a, b) == pytest.approx(4 / 28)
    assert mask_iou(a, a) == 1.0
    assert mask_iou(np.zeros_like(a), np.zeros_like(a)) is None
    rgb = np.full((10, 10, 3), 100, np.uint8)
    ov = overlay(rgb, a)
    assert ov.shape == rgb.shape and ov.dtype == np.uint8
    assert ov[0, 0].tolist() == [100, 100, 100] and ov[3, 3, 0] > 150 and ov[3, 3, 1] < 100


def test_household_kinds_find_functions_and_refuse_other_things_parts(minilm):
    """Issue 60 (2026-12-05): what the scene's objects read as among household kinds, each with a dictionary
    definition. By names alone a function finds its object through the kind's definition ("reheat ... dinner": a
    microwave); a part of a thing the scene does not hold is refused ("the car door" where the doors are a fridge's,
    an oven's ...), an owner that fits is kept ("the wooden box" is a chest: its definition), and a name word names
    one thing ("nightstand" owns no bed, so "what you sleep on" is refused)."""
    from interreal.synth import SynthConfig, build_scene
    from livescene.language.household import HOUSEHOLD, compound, scene_kinds

    assert compound("the car door") == ("door", "car") and compound("the lid of the trunk") == ("lid", "trunk")
    assert compound("the wardrobe's left door") == ("door", "wardrobe left") and compound("the door") == ("", "")
    scene = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24))
    names = scene.object_names
    for descriptions in (scene.descriptions, None):
        index = ObjectIndex.build(names, descriptions, minilm)
        kinds = scene_kinds(index.name_emb, index.desc_emb, index.names, minilm)
        owner = {n: {HOUSEHOLD[j] for j in kinds.owner[i]} for i, n in enumerate(names)}
        assert owner["fridge door"] == {"refrigerator"} and owner["nightstand drawer"] == {"nightstand"}
        assert owner["top drawer"] == set()  # "top" names no thing: any owner fits it
        for query, reads in (("the car door", "car"), ("the piano lid", None), ("what you sleep on", "bed"),
                             ("a purple elephant", None)):
            res = retrieve(index, query, minilm)
            assert not res.ok and (reads is None or res.reads_as == reads), (query, res.table(), res.reads_as)
        for query, expected in (("the lid of the wooden box", "chest lid"), ("the left door of the closet",
                                "wardrobe left door"), ("the microwave's door", "microwave door"),
                                ("what you use to reheat last night's dinner", "microwave door"),
                                ("the refrigerator's door", "fridge door"), ("the upper drawer", "top drawer")):
            res = retrieve(index, query, minilm)
            assert res.ok and res.best.name == expected, (query, res.table(), res.reason)
    with pytest.raises(LiveSceneError, match="no door here belongs to one"):
        require_match(retrieve(index, "the car door", minilm))
    res = retrieve(index, "what you use to reheat last night's dinner", minilm)
    assert res.best.matched == "definition of 'microwave'"  # names alone: the kind's definition found it


def test_things_the_household_list_lacks_and_unknown_owners_are_refused(minilm):
    """A third held-out query set found absent things refused 0.6-0.67: "the ironing board" and "the cat flap" are in
    no list, so nothing read as them and the nearest object took them. A query that names a thing (its head noun)
    no text of the scene mentions, with no object reading close to it, is refused; so is a part whose owner reads
    as no known thing and is not near the object's owner ("the safe door"); words that say which one ("left",
    "white") are no owner, and a request by function names no thing."""
    from interreal.synth import SynthConfig, build_scene
    from livescene.language.household import compound, thing_named

    assert thing_named("the drawer where the pots are kept") == "drawer" and thing_named("the lid of the trunk") == "lid"
    assert thing_named("the stairs") == "stair" and thing_named("where the spoons go") == ""
    assert thing_named("pull the top drawer open") == "drawer" and thing_named("the left one of the doors") == ""
    assert thing_named("the drawer underneath") == "drawer" and thing_named("the cupboard upstairs") == "cupboard"
    assert compound("the drawer-less door with the milk behind it") == ("", "")  # a hyphenated word is no owner
    assert compound("the left-hand wardrobe door") == ("door", "wardrobe")
    assert thing_named("the thing that keeps food cold") == "" and compound("the closet door on the right") == (
        "door", "closet")
    scene = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24))
    for names in (scene.object_names[:2], scene.object_names):
        for descriptions in (scene.descriptions, None):
            index = ObjectIndex.build(names, descriptions, minilm)
            for query, reads in (("the umbrella stand", None), ("the rocking horse", None), ("the attic door", "attic"),
                                 ("the garden shed door", "garden shed")):
                res = retrieve(index, query, minilm)
                assert not res.ok and (reads is None or res.reads_as == reads), (query, res.table(), res.reason)
            for query, expected in (("the white door", "fridge door"), ("the big drawer", "top drawer"),
                                    ("the door of the fridge on the left", "fridge door"), ("the fridge", "fridge door"),
                                    ("the drawer with the knives in it", "top drawer")):
                res = retrieve(index, query, minilm)
                assert res.ok and res.best.name == expected, (query, res.table(), res.reason)
    index = ObjectIndex.build(scene.object_names, scene.descriptions, minilm)
    for query in ("the coat hook", "the kitchen scales"):  # the wardrobe's coats, the kitchen carry the query
        res = retrieve(index, query, minilm)
        assert not res.ok and res.reads_as in ("hook", "scale"), (query, res.table(), res.reason)
    index = ObjectIndex.build(scene.object_names, None, minilm)
    with pytest.raises(LiveSceneError, match="names a 'stand', which no object here is or mentions"):
        require_match(retrieve(index, "the umbrella stand", minilm))
    with pytest.raises(LiveSceneError, match="no door here belongs to a 'attic'"):
        require_match(retrieve(index, "the attic door", minilm))


def test_a_request_by_place_is_compared_by_what_it_holds(minilm):
    """"where the glasses are kept" went to the chest lid, whose description shares the sentence's frame ("the
    storage chest where the toys are"); compared by what it holds ("glasses") with what each description holds
    ("cups", "toys", "cutlery"), it finds the cupboard. Names alone are left as they were."""
    from interreal.synth import SynthConfig, build_scene
    from livescene.language.household import held_things

    assert held_things("where the spoons go") == "spoons" and held_things("the door of the oven") == ""
    assert held_things("the deep bottom drawer of the wooden cabinet, for pots and pans") == "pots and pans"
    assert held_things("where I keep my phone charger at night") == "phone charger"
    scene = build_scene(SynthConfig(parts=10, frames=2, width=32, height=24))
    index = ObjectIndex.build(scene.object_names, scene.descriptions, minilm)
    for query, expected in (("where the glasses are kept", "cupboard door"), ("where the jackets hang",
                            "wardrobe right door"), ("where the frying pans are kept", "bottom drawer"),
                            ("the thing that keeps food cold", "fridge door")):
        res = retrieve(index, query, minilm)
        assert res.ok and res.best.name == expected, (query, res.table())
    assert retrieve(index, "where the glasses are kept", minilm).best.matched == "what its description holds"
