"""The import rules of docs/architecture.md, read from the source with `ast` (nothing is imported, so it is fast):

- no import cycle inside `livescene` or inside `interreal` (imports inside functions count: they are still edges);
- `livescene` imports from `interreal` only the dataset surface (`LIVESCENE_MAY_IMPORT`), a closed set: those
  modules import nothing else of `interreal` (and nothing of `livescene`);
- no `interreal` module imports `livescene`, except `interreal.demo` (the one command above both packages);
- no livescene library module imports a command module (`livescene.commands.*`, `livescene.cli`);
- no livescene import inside a function, except of an optional extra (`OPTIONAL_EXTRAS`);
- no interreal import inside a function, except optional extras and the lazy imports of `INTERREAL_LAZY`;
- `livescene eval --gt` finds the simulator's truth through the `livescene.truth` entry point, not an import.
"""

from __future__ import annotations

import ast
import tomllib
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# What livescene may import from interreal: the dataset reader and what its types speak in (conventions, layout,
# errors), plus the small utilities both packages share, each of which imports neither package's stages.
LIVESCENE_MAY_IMPORT = {
    "interreal",  # the package itself (its __init__: a version string)
    "interreal.dataset",  # the dataset API (types, readers, validate) and its modules
    "interreal.conventions", "interreal.layout",  # frame names, axes, the file layout the dataset speaks in
    "interreal.errors",  # one error hierarchy for both CLIs
    "interreal.atomic", "interreal.report",  # atomic writes; stage reports (RUN/reports/*.json)
    "interreal.runner",  # the command-line driver both entry points share
    "interreal.video",  # H.264 writing
    "interreal.localserver",  # the rules every local web app serves under (`livescene view`)
    "interreal.transients",  # the dataset's transient layer (DS/transients/: people, hands)
    "interreal.official",  # the official LiveScene layout rules and split (`--split official`)
}
# ... and what those need inside interreal, which livescene itself must not import
SURFACE_INTERNALS = {"interreal.provenance", "interreal.images"}
# the one interreal module above both packages
ABOVE_BOTH = {"interreal.demo"}
# top-level packages whose import inside a function is allowed in livescene: optional extras (not installed by
# default, or heavy and needed by one code path only)
OPTIONAL_EXTRAS = {"fastapi", "starlette", "uvicorn", "playwright", "open_clip", "sentence_transformers",
                   "transformers", "huggingface_hub", "webbrowser"}
COMMAND_MODULES = ("livescene.cli", "livescene.__main__", "livescene.commands")
# interreal: optional extras (pyproject extras, or stdlib used by one path) may be imported where used anywhere ...
INTERREAL_OPTIONAL_EXTRAS = {"fastapi", "starlette", "uvicorn", "ray", "playwright", "webbrowser",
                             "mediapipe"}  # the hand model (.ci/setup installs it without its numpy < 2 pin)
# ... and these imports stay inside functions in these modules only (module -> imported module prefixes), each why:
INTERREAL_LAZY = {
    "interreal.atomic": {"cv2"},  # on the `interreal validate` path (every dataset read); cv2 only to write images
    "interreal.images": {"cv2"},  # on the validate path: header checks need PIL only, decoding needs cv2
    "interreal.transients.layer": {"cv2"},  # on the validate path (its checks read no pixels)
    "interreal.dataset.io": {"trimesh"},  # on the validate path; trimesh (~1.8 s) only to read the point cloud
    "interreal.dataset.types": {"scipy"},  # on the validate path; scipy (~0.5 s) only for quaternion conversion
    "interreal.demo": {"livescene"},  # the command above both packages: torch only once training starts
    "interreal.annotate.server": {"interreal.masks"},  # propagation is looked up when run (a build without it)
}


@dataclass(frozen=True)
class Import:
    target: str  # absolute module (or module.name: resolved against the known modules)
    line: int
    in_function: bool
    type_only: bool  # under `if TYPE_CHECKING:`


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@lru_cache(maxsize=None)
def modules(package: str) -> dict[str, Path]:
    return {_module_name(p): p for p in sorted((ROOT / package).rglob("*.py"))}


def _is_package(name: str, path: Path) -> bool:
    return path.name == "__init__.py"


def _absolute(module: str, path: Path, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if _is_package(module, path) else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _statements(body: list[ast.stmt], in_function: bool, type_only: bool):
    """(statement, in a function, under `if TYPE_CHECKING`) for every statement, nested ones included (imports are
    statements: expressions need no visit, which keeps this fast)."""
    for node in body:
        yield node, in_function, type_only
        inner = in_function or isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        checking = isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")
        yield from _statements(getattr(node, "body", []) if isinstance(getattr(node, "body", None), list) else [],
                               inner, type_only or checking)
        for field in ("orelse", "finalbody"):
            yield from _statements(getattr(node, field, []) or [], inner, type_only)
        for part in getattr(node, "handlers", []) + getattr(node, "cases", []):
            yield from _statements(part.body, inner, type_only)


@lru_cache(maxsize=None)
def imports(module: str, path: Path) -> tuple[Import, ...]:
    found = []
    for node, in_function, type_only in _statements(ast.parse(path.read_text(encoding="utf-8"), str(path)).body,
                                                     False, False):
        if isinstance(node, ast.Import):
            found += [Import(alias.name, node.lineno, in_function, type_only) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(module, path, node)
            # a submodule, or a name of `base` (`resolve` keeps the longest known module)
            found += [Import(f"{base}.{alias.name}", node.lineno, in_function, type_only) for alias in node.names]
    return tuple(found)


@lru_cache(maxsize=None)
def known() -> dict[str, Path]:
    return {**modules("interreal"), **modules("livescene")}


def resolve(target: str) -> str:
    """The module an import loads: the longest known module prefix of `target` (a third-party name stays)."""
    mods = known()
    parts = target.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        if name in mods:
            return name
    return target


def edges(package: str, runtime_only: bool = True) -> dict[str, set[str]]:
    """module -> the modules of `package` it imports (parent packages of the target included, as Python runs
    their __init__ first, except the importer's own parents)."""
    out: dict[str, set[str]] = {}
    for mod, path in modules(package).items():
        own_parents = {".".join(mod.split(".")[:n]) for n in range(1, mod.count(".") + 1)}
        if _is_package(mod, path):
            own_parents.add(mod)
        targets = set()
        for imp in imports(mod, path):
            if runtime_only and imp.type_only:
                continue
            name = resolve(imp.target)
            if not name.startswith(package + ".") and name != package:
                continue
            chain = name.split(".")
            for n in range(1, len(chain) + 1):
                part = ".".join(chain[:n])
                if part in modules(package) and part not in own_parents and part != mod:
                    targets.add(part)
        out[mod] = targets
    return out


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _within(name: str, allowed: set[str]) -> bool:
    return any(name == a or name.startswith(a + ".") for a in allowed if a != "interreal") or name == "interreal"


def _where(mod: str, imp: Import) -> str:
    return f"{known()[mod].relative_to(ROOT)}:{imp.line} imports {imp.target}"


# ---------------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("package", ["livescene", "interreal"])
def test_no_import_cycle_within_a_package(package):
    found = cycles(edges(package))
    assert not found, f"import cycles in {package} (each line one cycle): " + "; ".join(" <-> ".join(c) for c in found)


def test_livescene_imports_only_the_dataset_surface_of_interreal():
    bad = []
    for mod, path in modules("livescene").items():
        allowed = LIVESCENE_MAY_IMPORT
        for imp in imports(mod, path):
            name = resolve(imp.target)
            if name.split(".")[0] == "interreal" and not _within(name, allowed):
                bad.append(_where(mod, imp))
    assert not bad, "livescene reaches past the dataset surface of interreal:\n" + "\n".join(bad)


def test_the_surface_livescene_may_import_is_closed():
    """What livescene may import pulls in no interreal stage either (synth, sfm, masks ...), nor livescene."""
    seen, todo, bad = set(), [m for m in modules("interreal") if _within(m, LIVESCENE_MAY_IMPORT)], []
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        for imp in imports(mod, known()[mod]):
            name = resolve(imp.target)
            top = name.split(".")[0]
            if top == "livescene" or (top == "interreal" and not _within(name, LIVESCENE_MAY_IMPORT | SURFACE_INTERNALS)):
                bad.append(_where(mod, imp))
            elif top == "interreal" and name in known():
                todo.append(name)
    assert not bad, "the dataset surface imports beyond itself:\n" + "\n".join(bad)
    assert {"interreal.dataset", "interreal.conventions", "interreal.errors"} <= seen


def test_interreal_library_does_not_import_livescene():
    bad = [_where(mod, imp) for mod, path in modules("interreal").items() if mod not in ABOVE_BOTH
           for imp in imports(mod, path) if imp.target.split(".")[0] == "livescene"]
    assert not bad, "interreal imports livescene outside the demo (the one command above both):\n" + "\n".join(bad)
    assert any(imp.target.startswith("livescene") for imp in imports("interreal.demo", known()["interreal.demo"])), \
        "the demo no longer runs livescene: update ABOVE_BOTH and docs/architecture.md"


def test_no_livescene_library_module_imports_a_command():
    bad = []
    for mod, path in modules("livescene").items():
        if mod.startswith(COMMAND_MODULES):
            continue
        bad += [_where(mod, imp) for imp in imports(mod, path) if resolve(imp.target).startswith(COMMAND_MODULES)]
    assert not bad, "library modules import command modules:\n" + "\n".join(bad)
    for name in ("train", "render", "eval", "ground", "view"):  # every command: add_arguments + main
        tree = ast.parse(modules("livescene")[f"livescene.commands.{name}"].read_text(encoding="utf-8"))
        defined = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
        assert {"add_arguments", "main"} <= defined, name


def test_no_livescene_import_inside_a_function_but_optional_extras():
    bad = [_where(mod, imp) for mod, path in modules("livescene").items() for imp in imports(mod, path)
           if imp.in_function and imp.target.split(".")[0] not in OPTIONAL_EXTRAS]
    assert not bad, "imports inside functions (move them to the top; only optional extras stay lazy):\n" + "\n".join(bad)


def test_no_interreal_import_inside_a_function_but_the_allowed_ones():
    """Imports sit at the top, so the import graph is what the module header says; the few lazy ones keep the
    validate path and the demo's start fast, or are optional extras (`INTERREAL_LAZY`, `INTERREAL_OPTIONAL_EXTRAS`)."""
    bad = []
    for mod, path in modules("interreal").items():
        lazy = INTERREAL_LAZY.get(mod, set())
        bad += [_where(mod, imp) for imp in imports(mod, path) if imp.in_function
                and imp.target.split(".")[0] not in INTERREAL_OPTIONAL_EXTRAS
                and not any(imp.target == p or imp.target.startswith(p + ".") for p in lazy)]
    assert not bad, "imports inside functions (move them to the top, or justify one in INTERREAL_LAZY):\n" + "\n".join(bad)
    assert set(INTERREAL_LAZY) <= set(modules("interreal")), "INTERREAL_LAZY names a module that is gone"


def test_the_truth_reader_is_an_entry_point_interreal_registers():
    """`livescene eval --gt` reads the simulator's truth through the `livescene.truth` entry point group (declared
    in pyproject.toml, installed by .ci/setup), so livescene needs no import of interreal.synth."""
    from importlib.metadata import entry_points

    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["livescene.truth"]
    assert declared == {"synth": "interreal.synth.evaltruth:open_truth"}
    module, _, func = declared["synth"].partition(":")
    tree = ast.parse(known()[module].read_text(encoding="utf-8"))
    assert func in {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    installed = {ep.name: ep.value for ep in entry_points(group="livescene.truth")}
    assert installed == declared, "the installed metadata is stale: run `bash .ci/setup` (pip install -e .)"


def test_the_checker_sees_a_cycle_and_a_forbidden_import(tmp_path):
    """The rules above are not vacuous: the graph code finds a planted cycle and resolves relative imports."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
    run_edges = edges("livescene")
    assert "livescene.run" in run_edges["livescene.trainer"]  # `from .run import ...`
    assert "livescene.render" in run_edges["livescene.language.grounding"]  # `from ..render import ...`
    assert "livescene.language" in run_edges["livescene.commands.render"]  # parent package of the target
    src = tmp_path / "mod.py"
    src.write_text("import os\nif TYPE_CHECKING:\n    from .a import B\nclass C:\n    def f(self):\n"
                   "        try:\n            import cv2\n        except ImportError:\n            pass\n")
    found = {i.target: (i.in_function, i.type_only) for i in imports("livescene.mod", src)}
    assert found == {"os": (False, False), "livescene.a.B": (False, True), "cv2": (True, False)}


MAX_MODULE_LINES = 600  # a longer module holds more than one concept: split it along them
MAX_FUNCTION_LINES = 120  # ... and a longer function more than one step


def test_no_module_or_function_is_too_long():
    too_long = []
    for package in ("interreal", "livescene"):
        for name, path in modules(package).items():
            text = path.read_text(encoding="utf-8")
            lines = text.count("\n")
            if lines > MAX_MODULE_LINES:
                too_long.append(f"{path.relative_to(ROOT)}: {lines} lines (at most {MAX_MODULE_LINES})")
            for node in ast.walk(ast.parse(text, str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = node.end_lineno - node.lineno + 1
                    if n > MAX_FUNCTION_LINES:
                        too_long.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}: {n} lines "
                                        f"(at most {MAX_FUNCTION_LINES})")
    assert not too_long, "split along the concepts:\n" + "\n".join(too_long)
