"""livescene: a LiveScene dataset -> an interactive radiance field you can render at any object state.

Modules: field, sampler, losses, trainer, render, evaluate, language. Datasets are read through the public
`interreal.dataset.load_dataset` API only (the packages meet at the dataset folder).
"""

__version__ = "0.1.0"
