"""Things found in homes, each with a short dictionary definition: what grounding knows about object kinds.

The definitions paraphrase WordNet 3.0's glosses of the same words (what the thing is and what it is for); none is
written for a scene of ours or a benchmark query. They serve twice: an object of a scene is also known by the
definitions of the household things its name (and description) read as, so "what cooks food by microwaves" finds
a "microwave door" named by name alone; and an absent thing is recognised by its definition as well as its word
("the machine that washes the dishes" reads as a dishwasher).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

KINDS: dict[str, str] = {
    "refrigerator": "an appliance in which food and drinks are stored at low temperatures to keep them cold",
    "freezer": "an appliance in which food is frozen and stored for long periods of time",
    "dishwasher": "a machine for washing dishes, plates and cutlery",
    "washing machine": "a home appliance for washing clothes and linens automatically",
    "clothes dryer": "an appliance that removes moisture from washed clothes by tumbling them in hot air",
    "oven": "a kitchen appliance used for baking or roasting food",
    "stove": "a kitchen appliance with burners, used for cooking food in pots and pans",
    "microwave": "a kitchen appliance that cooks or heats food quickly by passing microwaves through it",
    "toaster": "a small electric kitchen appliance for toasting slices of bread",
    "kettle": "a pot with a spout and a handle for boiling water",
    "coffee machine": "a kitchen appliance for brewing coffee automatically",
    "sink": "a basin fixed to a wall or counter, with a tap and a drain, for washing",
    "tap": "a valve that controls the flow of water from a pipe",
    "kitchen cabinet": "a piece of kitchen furniture with doors, shelves and drawers, for storage",
    "cupboard": "a small cabinet with a door and shelves, used for storage",
    "pantry": "a small room or cupboard in which food is stored",
    "drawer": "a box-shaped container in a piece of furniture, made to slide in and out",
    "dresser": "a chest of drawers, furniture with drawers for keeping clothes",
    "wardrobe": "a tall piece of furniture with doors and a rail, providing storage space for clothes",
    "closet": "a small room or recess used for storing clothes and household things",
    "bookshelf": "a set of shelves on which books are kept",
    "shelf": "a flat horizontal board fixed to a wall or in a cabinet, for holding things",
    "table": "a piece of furniture with a flat top supported by legs",
    "desk": "a piece of furniture with a writing surface and usually drawers",
    "chair": "a seat for one person, with a back",
    "sofa": "an upholstered seat for several people, with a back and arms",
    "armchair": "a comfortable chair with supports for the arms",
    "bed": "a piece of furniture that provides a place to sleep",
    "nightstand": "a small table beside a bed",
    "lamp": "a device that gives light, holding an electric bulb",
    "ceiling light": "a light fixture mounted on the ceiling of a room",
    "light switch": "a switch on the wall that turns the lights of a room on and off",
    "window": "a glass pane in a frame, set in a wall to admit light and air",
    "curtain": "a piece of cloth hung at a window to block light or keep out view",
    "blinds": "a window covering of slats that can be raised or tilted to shut out light",
    "front door": "the main door at the entrance of a house",
    "garage door": "a large door that closes the garage where a car is parked",
    "gate": "a movable barrier in a fence or wall",
    "door": "a swinging or sliding panel that closes the entrance to a room or building",
    "television": "an electronic device with a screen that receives and shows broadcast programmes",
    "TV": "a television set, for watching programmes",
    "remote control": "a small hand-held device for operating a television or another machine from a distance",
    "computer": "an electronic machine for calculating and processing data",
    "laptop": "a portable computer small enough to use on your lap",
    "monitor": "a screen that displays the output of a computer",
    "keyboard": "a set of keys for typing into a computer",
    "phone": "a device for talking to someone far away",
    "speaker": "a device that turns electrical signals into sound loud enough to be heard",
    "radio": "a receiver for listening to broadcast sound",
    "bathtub": "a large open container filled with water, in which you wash your body",
    "shower": "a fixture that sprays water over you while you wash",
    "toilet": "a bowl with a seat, connected to a drain, used to get rid of bodily waste",
    "mirror": "a polished surface that forms images by reflecting light",
    "medicine cabinet": "a small cabinet, usually above the bathroom sink, for storing medicines and toiletries",
    "trash can": "a bin that holds rubbish until it is collected",
    "laundry basket": "a basket that holds dirty clothes until they are washed",
    "box": "a rectangular container, usually with a lid",
    "chest": "a large sturdy box with a lid, used for storage",
    "suitcase": "a portable rectangular case for carrying clothes when travelling",
    "backpack": "a bag carried on the back by straps over the shoulders",
    "plant": "a living plant grown in a pot",
    "painting": "a picture made with paint, hung on a wall",
    "clock": "a device that shows the time of day",
    "fan": "a device that creates a current of air with rotating blades",
    "air conditioner": "a machine that keeps the air of a room cool and dry",
    "heater": "a device that supplies warmth to a room",
    "radiator": "a panel of pipes through which hot water passes to heat a room",
    "fireplace": "an open recess in a wall at the base of a chimney, where a fire is built",
    "stairs": "a series of steps leading from one floor to another",
    "carpet": "a heavy woven floor covering",
    "rug": "a piece of thick fabric covering part of a floor",
    "pillow": "a soft cushion used to support the head in bed",
    "blanket": "a large warm cover used on a bed",
    "book": "a written work printed on pages bound together",
    "bottle": "a narrow-necked container for liquids",
    "cup": "a small open container with a handle, for drinking",
    "plate": "a flat dish from which food is served or eaten",
    "car": "a motor vehicle with four wheels, for carrying people on roads",
    "bicycle": "a vehicle with two wheels, moved by pedals",
}
HOUSEHOLD: tuple[str, ...] = tuple(KINDS)

# a thing reads as a household kind when the kind is among its OWN_NEAREST nearest at OWN_SIM or closer (cosine)
OWN_NEAREST = 2
OWN_SIM = 0.5
_WORD = re.compile(r"[a-z0-9]+")
_STOP = {"the", "a", "an", "of", "to", "my", "this", "that", "on", "in", "with", "s"}
# words that say which one or what it looks like, not whose it is: "the left wardrobe door", "the white door"
MODIFIERS = frozenset(
    "white black grey gray red green blue yellow brown beige silver wooden wood glass metal steel plastic painted big "
    "small large little tall short long wide narrow deep shallow tiny huge left right top bottom upper lower middle "
    "front back rear side inner outer first second third last lowest highest uppermost topmost far near hand old new "
    "open closed".split())
# a noun phrase's head ends where a clause or a preposition starts: "the drawer where the pots are kept"
_CLAUSE = re.compile(r"\b(?:where|that|which|who|whose|for|with|in|on|at|by|next|near|from|under|above|below|behind|"
                     r"beside|underneath|beneath|over|inside|outside|upstairs|downstairs)\b")
_HYPHENATED = re.compile(r"\b[a-z0-9]+(?:-[a-z0-9]+)+\b")  # "drawer-less", "left-hand", "built-in": says what kind
_HOLDS = re.compile(r"\b(?:where|for|in which|on which)\b")
_KEEPING = frozenset("is are be go goes keep keeps kept store stores stored put away hang hangs live lives belong "
                     "belongs get gets stay stays sit sits usually normally i you we they my your our their at night "
                     "there can should".split())
_PRONOUNS = frozenset({"one", "ones", "thing", "things", "stuff", "something", "it"})  # "the left one of ..."
# a request by what a thing does or holds, not by what it is called
_FUNCTION = re.compile(r"^(?:the |a )?(?:where|what|which|something|somewhere|thing|place|one)\b")


@dataclass(frozen=True)
class SceneKinds:
    """What the household kinds say about one scene's objects (index order).

    owned[i]: the kinds object i reads as (its name's and description's OWN_NEAREST nearest, and the nearest of
    each word before its name's last one, at OWN_SIM or closer: "fridge door" -> refrigerator, door), each kept by
    the object closest to it; owner[i]: the kinds those words before the last read as (empty for "top drawer":
    "top" names no thing); here: every kind some object reads as;
    absent: the kinds no object does (what an absent query may read as)."""

    word_emb: np.ndarray  # (K, D) the kinds' words
    gloss_emb: np.ndarray  # (K, D) their definitions
    owned: tuple[frozenset[int], ...]
    owner: tuple[frozenset[int], ...]
    here: frozenset[int]
    absent: tuple[int, ...]

    def kind_sims(self, query_emb: np.ndarray, definitions: bool = True) -> np.ndarray:
        """(K,) a query's similarity to each kind: the better of its word and its definition (or its word alone)."""
        sims = self.word_emb @ query_emb
        return np.maximum(sims, self.gloss_emb @ query_emb) if definitions else sims


@lru_cache(maxsize=4)
def kind_embeddings(encoder: Any) -> tuple[np.ndarray, np.ndarray]:
    """(K, D) embeddings of the kinds' words and of their definitions (once per encoder)."""
    return encoder.encode(list(HOUSEHOLD)), encoder.encode([KINDS[k] for k in HOUSEHOLD])


@lru_cache(maxsize=256)
def encode_one(encoder: Any, text: str) -> np.ndarray:
    """One text's embedding, cached (words and phrases recur from query to query)."""
    return encoder.encode([text])[0]


def words(text: str) -> list[str]:
    """Content words in order ("the wardrobe's left door" -> wardrobe, left, door)."""
    return [w for w in _WORD.findall(text.lower().replace("_", " ").replace("'s ", " ")) if w not in _STOP]


def singular(word: str) -> str:
    """A plural's singular, roughly ("stairs" -> "stair", "glass" stays): both sides of a comparison alike."""
    return word[:-1] if word.endswith("s") and not word.endswith("ss") and len(word) > 3 else word


def thing_named(phrase: str) -> str:
    """The thing a noun phrase names, its head noun (singular): "the drawer where the pots are kept" -> "drawer",
    "the lid of the trunk" -> "lid"; "" for a request by function ("where the spoons go", "the thing that ...")."""
    text = phrase.lower().strip()
    if _FUNCTION.match(text):
        return ""
    ws = words(_HYPHENATED.sub(" ", _CLAUSE.split(text, 1)[0].split(" of ")[0]))
    while ws and ws[-1] in MODIFIERS:  # "pull the top drawer open"
        ws.pop()
    return singular(ws[-1]) if ws and ws[-1] not in _PRONOUNS else ""


def held_things(text: str) -> str:
    """What a place holds, in words: "where the spoons go" -> "spoons"; "the deep drawer, for pots and pans" ->
    "pots and pans"; "" when the text names no place that holds something. Its content words after the first "where",
    "for", "in which" or "on which", less the verbs and pronouns of keeping ("are kept", "I keep", "hang")."""
    m = _HOLDS.search(text.lower())
    return " ".join(w for w in words(text.lower()[m.end():]) if w not in _KEEPING) if m else ""


def scene_words(names: list[str], descriptions: list[str], kinds: SceneKinds) -> frozenset[str]:
    """Every content word (singular) of a scene's names, descriptions, the kinds its objects read as and their
    definitions: what the scene's texts mention."""
    texts = list(names) + list(descriptions)
    for own in kinds.owned:
        texts += [t for j in own for t in (HOUSEHOLD[j], KINDS[HOUSEHOLD[j]])]
    return frozenset(singular(w) for t in texts for w in words(t))


def reads_as(emb: np.ndarray, word_emb: np.ndarray, nearest: int = OWN_NEAREST) -> set[int]:
    """The kinds a text reads as: its `nearest` nearest kinds at OWN_SIM or closer."""
    sims = word_emb @ emb
    return {int(j) for j in np.argsort(-sims)[:nearest] if sims[j] >= OWN_SIM}


def scene_kinds(name_emb: np.ndarray, desc_emb: np.ndarray, names: list[str], encoder: Any) -> SceneKinds:
    """The kinds each object of a scene reads as (see `SceneKinds`); desc_emb rows of zeros: no description."""
    word_emb, gloss_emb = kind_embeddings(encoder)
    owned, owner = [], []
    for i, name in enumerate(names):
        own = reads_as(name_emb[i], word_emb)
        if np.linalg.norm(desc_emb[i]) > 0:
            own |= reads_as(desc_emb[i], word_emb)
        whose: set[int] = set()
        for w in words(name)[:-1]:  # a word names one thing: "nightstand" is a nightstand, not a bed
            whose |= reads_as(encode_one(encoder, w), word_emb, nearest=1)
        owned.append(own | whose)
        owner.append(frozenset(whose))
    here = frozenset().union(*owned)
    texts = np.stack([name_emb, desc_emb], 1)  # (M, 2, D)
    for j in here:  # a kind two objects read as stays with the closer ("oven": the oven door, not the microwave's)
        claims = [i for i in range(len(names)) if j in owned[i]]
        best = max(claims, key=lambda i: float((texts[i] @ word_emb[j]).max()))
        for i in claims:
            if i != best:
                owned[i].discard(j)
    absent = tuple(j for j in range(len(HOUSEHOLD)) if j not in here)
    return SceneKinds(word_emb, gloss_emb, tuple(frozenset(o) for o in owned), tuple(owner), here, absent)


def compound(phrase: str) -> tuple[str, str]:
    """(head, owner) of a noun phrase: "the car door" -> ("door", "car"); "the lid of the trunk" -> ("lid",
    "trunk"); ("", "") when there is no owner ("the door", "where the coats hang" -> its last word has none). A
    clause or preposition ends the phrase: "the closet door on the right" -> ("door", "closet"); a hyphenated word
    says what kind, not whose ("the drawer-less door")."""
    text = _HYPHENATED.sub(" ", _CLAUSE.split(phrase.lower(), 1)[0])
    if " of " in text:
        left, right = text.rsplit(" of ", 1)
        lw, rw = words(left), words(right)
        return (lw[-1], " ".join(rw)) if lw and rw else ("", "")
    ws = words(text)
    return (ws[-1], " ".join(ws[:-1])) if len(ws) > 1 else ("", "")


def owner_words(phrase: str) -> str:
    """Whose part a phrase names, less the words that say which one: "the wardrobe's left door" -> "wardrobe",
    "the left door" -> "" (`compound`'s owner, `MODIFIERS` out)."""
    return " ".join(w for w in words(compound(phrase)[1]) if w not in MODIFIERS)


def foreign_owner(kinds: SceneKinds, obj: int, owner_emb: np.ndarray) -> tuple[int | None, float] | None:
    """(kind, similarity) when a query's owner ("car" of "the car door") reads as a kind that is not the object's
    owner ("fridge" -> refrigerator), nor close (OWN_SIM) to it, while the query's owner does not read as the owner's
    definition either ("the wooden box" is a chest: "a large sturdy box with a lid"); (None, its best similarity)
    when the query's owner reads as no kind ("the safe door") and is not close to the object's owner's word or
    definition either; None when it fits, or the object has no owner ("the top drawer" fits any)."""
    mine = kinds.owner[obj]
    if not mine:
        return None
    sims = kinds.word_emb @ owner_emb
    k = int(np.argmax(sims))
    if k in mine:
        return None
    if sims[k] < OWN_SIM:
        near = max(max(float(kinds.word_emb[o] @ owner_emb), float(kinds.gloss_emb[o] @ owner_emb)) for o in mine)
        return None if near >= OWN_SIM else (None, near)
    if max(max(float(kinds.word_emb[k] @ kinds.word_emb[o]), float(kinds.gloss_emb[o] @ owner_emb))
           for o in mine) >= OWN_SIM:
        return None
    return k, float(sims[k])
