"""interreal: a phone video (or photos, or RAW files) -> a LiveScene dataset.

Stages (one module each): ingest, frames, sfm, masks, labels, dataset, synth, annotate.
The dataset folder is the only thing the stages (and `livescene`) share; see `interreal.dataset`.
"""

__version__ = "0.1.0"
