"""livescene: a LiveScene dataset -> an interactive radiance field you can render at any object state.

A library (field, sampler, losses, run, trainer, render, evaluate, language, viewer ...) under one module per
command (`livescene.commands`). Datasets are read through `interreal.dataset` and the small surface beside it
(docs/architecture.md "Which way imports go"; the packages meet at the dataset folder).
"""

__version__ = "0.1.0"
