"""The `livescene` commands: one module each, `add_arguments(parser)` + `main(args) -> int`, over the library.

`livescene.cli` dispatches to them by name (`COMMANDS`); no library module imports a command module
(tests/test_architecture.py checks it). A new command is a module here and a line in `COMMANDS`.
"""

from __future__ import annotations

# name -> (module, one-line help); modules are imported only for the command that runs
COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("livescene.commands.train", "fit the interactive radiance field to a dataset (progress, checkpoints, resume)"),
    "render": ("livescene.commands.render", "render images / videos at chosen object states and cameras"),
    "eval": ("livescene.commands.eval", "PSNR, SSIM, depth L1, state error, mask IoU, novel-state PSNR -> JSON"),
    "ground": ("livescene.commands.ground", "find an object by text and render its mask in any view"),
    "view": ("livescene.commands.view", "local browser viewer: orbit / fly camera, a slider per object, save views"),
    "export": ("livescene.commands.export", "URDF (parts + joints), GLB at any state, PLY points with object ids, meshes"),
}
