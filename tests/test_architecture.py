"""The package's boundaries, read from the source: no import cycle, and no import from a lower layer up.

Every ``import`` and ``from ... import`` statement in ``sb3_hhp/`` counts, wherever it sits: at module
level, inside a function or method, and under ``if TYPE_CHECKING:``. An import deferred into a function
or hidden from the interpreter is still a dependency of the design (it is also the usual way a cycle is
papered over), so it is held to the same rules. Imports made from strings (``importlib.import_module``)
are not seen; the package makes none.

The layers, from the bottom up (a package may import from its own layer and the ones below it):

0. ``extras``, ``dqn``, ``curiosity``, ``goals``, ``preferences``: the building blocks. The optional
   dependencies, the learners, RND, the domains' sub-goal spaces, and preference learning with its data
   types (``Query``, ``Label``, ``Answer``), the predictor, the query selection, the store and the
   meta-controller's reward (eq. 3); ``subgoal_table``, the labeling page's sub-goal gallery kept in the
   store's file.
1. ``oracles``: answer preference queries; they use the preference types, the predictor's network (the
   synthetic oracle) and the goal spaces (the scripted oracles).
2. ``discovery``, ``hierarchy``: sub-goal discovery, and the options with their subpolicies and rewards
   (eq. 5, 6).
3. ``hhp`` and the package root ``sb3_hhp`` (which re-exports ``HhP``): the algorithm that wires them.
4. ``label``, ``gallery``, ``train``: the applications built on the algorithm.

A new module or subpackage of ``sb3_hhp`` must be given a layer here before the test passes.
"""

import ast
import itertools
import pathlib
from collections.abc import Iterator
from typing import NamedTuple

import networkx as nx
import pytest

import sb3_hhp

PACKAGE_DIR = pathlib.Path(sb3_hhp.__file__).parent
ROOT = "sb3_hhp"

LAYERS: tuple[frozenset[str], ...] = (
    frozenset({"arrays", "extras", "dqn", "curiosity", "goals", "preferences", "subgoal_table"}),
    frozenset({"oracles"}),
    frozenset({"discovery", "hierarchy"}),
    frozenset({"hhp", ROOT}),
    frozenset({"label", "gallery", "train", "zoo"}),
)


class Import(NamedTuple):
    importer: str  # dotted name of the importing module
    imported: str  # dotted name of the imported module (a package's __init__ is the package's name)
    path: pathlib.Path
    lineno: int


def module_names(package_dir: pathlib.Path, root: str) -> dict[str, pathlib.Path]:
    """Dotted name of every module under ``package_dir`` (a package is named by its ``__init__.py``)."""
    names = {}
    for path in sorted(package_dir.rglob("*.py")):
        parts = (root, *path.relative_to(package_dir).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        names[".".join(parts)] = path
    return names


def _resolve(name: str, modules: dict[str, pathlib.Path]) -> str:
    """The longest prefix of ``name`` that is a module of the package (``a.b.Class`` -> ``a.b``)."""
    while name not in modules and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def find_imports(package_dir: pathlib.Path, root: str) -> Iterator[Import]:
    """Every import, at any depth of the syntax tree, of a module of the package by a module of the package."""
    modules = module_names(package_dir, root)
    for importer, path in modules.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:  # relative: from the importer's package, one level up per extra dot
                    base = importer.split(".")
                    base = base[: len(base) - node.level + (1 if is_package else 0)]
                    module = ".".join(base + ([node.module] if node.module else []))
                else:
                    module = node.module or ""
                # `from pkg import sub` depends on the submodule when there is one, else on pkg itself
                targets = [f"{module}.{alias.name}" if f"{module}.{alias.name}" in modules else module
                           for alias in node.names]
            for target in targets:
                if target == root or target.startswith(root + "."):
                    yield Import(importer, _resolve(target, modules), path, node.lineno)


def component(module: str, root: str) -> str:
    """The part of the package a module belongs to: its top-level subpackage or module, or the root."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else root


def layer_of(name: str, layers: tuple[frozenset[str], ...], root: str = ROOT) -> int:
    for index, members in enumerate(layers):
        if name in members:
            return index
    dotted = name if name == root else f"{root}.{name}"
    raise AssertionError(
        f"{dotted} has no layer: add it to LAYERS in tests/test_architecture.py, in the layer of the packages "
        "it builds on or above them"
    )


def import_cycles(imports: list[Import], root: str, limit: int = 20) -> list[str]:
    """Cycles between modules, then between the package's components (the first ``limit``), as ``a -> b -> a``."""
    modules = nx.DiGraph((i.importer, i.imported) for i in imports if i.importer != i.imported)
    components = nx.DiGraph(
        (component(i.importer, root), component(i.imported, root))
        for i in imports
        if component(i.importer, root) != component(i.imported, root)
    )
    cycles = itertools.chain.from_iterable(nx.simple_cycles(graph) for graph in (modules, components))
    return [" -> ".join([*cycle, cycle[0]]) for cycle in itertools.islice(cycles, limit)]


def upward_imports(imports: list[Import], root: str, layers: tuple[frozenset[str], ...]) -> list[str]:
    """Imports from a lower layer to a higher one, with where they are."""
    found = []
    for i in imports:
        low, high = component(i.importer, root), component(i.imported, root)
        low_layer, high_layer = layer_of(low, layers, root), layer_of(high, layers, root)
        if low_layer < high_layer:
            found.append(f"{i.path}:{i.lineno}: {i.importer} (layer {low_layer}) imports {i.imported} "
                         f"(layer {high_layer})")
    return found


@pytest.fixture(scope="module")
def imports() -> list[Import]:
    return list(find_imports(PACKAGE_DIR, ROOT))


def test_every_component_has_a_layer(imports):
    for module in module_names(PACKAGE_DIR, ROOT):
        layer_of(component(module, ROOT), LAYERS)


def test_no_import_cycle(imports):
    cycles = import_cycles(imports, ROOT)
    assert not cycles, "Import cycles in sb3_hhp (move the shared code down a layer):\n" + "\n".join(cycles)


def test_no_import_from_a_lower_layer_to_a_higher_one(imports):
    upward = upward_imports(imports, ROOT, LAYERS)
    assert not upward, (
        "Imports from a lower layer to a higher one (move the imported code down, or pass it in from above; "
        "the layers are listed in tests/test_architecture.py):\n" + "\n".join(upward)
    )


def test_the_reader_sees_the_real_imports(imports):
    # a few dependencies the design rests on, so that a reader that saw nothing would not pass silently
    edges = {(i.importer, i.imported) for i in imports}
    assert ("sb3_hhp.oracles.base", "sb3_hhp.preferences.types") in edges
    assert ("sb3_hhp.hierarchy.replay", "sb3_hhp.hierarchy.rewards") in edges
    assert ("sb3_hhp", "sb3_hhp.hhp") in edges  # inside a function: counted


def write_package(tmp_path: pathlib.Path, files: dict[str, str]) -> pathlib.Path:
    package_dir = tmp_path / "pkg"
    for name, source in {"__init__.py": "", **files}.items():
        (package_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (package_dir / name).write_text(source)
    return package_dir


def test_a_cycle_is_found_even_when_deferred_or_type_only(tmp_path):
    package_dir = write_package(
        tmp_path,
        {
            "low/__init__.py": "",
            "low/a.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.high.b import B\n",
            "high/__init__.py": "",
            "high/b.py": "def f():\n    from ..low import a\n",
        },
    )
    found = list(find_imports(package_dir, "pkg"))
    assert {(i.importer, i.imported) for i in found} == {("pkg.low.a", "pkg.high.b"), ("pkg.high.b", "pkg.low.a")}
    assert "pkg.low.a -> pkg.high.b -> pkg.low.a" in import_cycles(found, "pkg") or (
        "pkg.high.b -> pkg.low.a -> pkg.high.b" in import_cycles(found, "pkg")
    )
    layers = (frozenset({"low"}), frozenset({"high"}))
    (upward,) = upward_imports(found, "pkg", layers)
    assert "pkg.low.a (layer 0) imports pkg.high.b (layer 1)" in upward


def test_a_component_without_a_layer_is_reported(tmp_path):
    package_dir = write_package(tmp_path, {"extra.py": "import pkg.known\n", "known.py": ""})
    found = list(find_imports(package_dir, "pkg"))
    with pytest.raises(AssertionError, match="pkg.extra has no layer"):
        upward_imports(found, "pkg", (frozenset({"known", "pkg"}),))
