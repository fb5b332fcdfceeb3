"""The layout of `benchmark/` shows its architecture: one subpackage per layer, and a layer
imports only from itself and the layers before it, in the order `benchmark/__init__.py` lists
them. Read from the source (nothing is imported), so an import inside a function counts too."""

import ast
import re
from pathlib import Path

BENCHMARK = Path(__file__).resolve().parents[1] / "benchmark"


def _layers() -> list[str]:
    """The layers in `benchmark/__init__.py`'s order: its docstring's list "- `core`: ..."."""
    doc = ast.get_docstring(ast.parse((BENCHMARK / "__init__.py").read_text(encoding="utf-8")))
    return re.findall(r"^- `(\w+)`:", doc, flags=re.MULTILINE)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of a benchmark module in ``path``, at any depth."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = ".".join(path.relative_to(BENCHMARK.parent).with_suffix("").parts[:-1])
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolved against the module's package
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            # `from reelbench.benchmark import runs` imports the subpackage `runs`
            found += [(node.lineno, f"{module}.{a.name}" if module == "reelbench.benchmark" else module)
                      for a in node.names]
    # the installed name is reelbench.benchmark; a bare `benchmark` import would be the folder's duplicate
    return [(line, m.removeprefix("reelbench.")) for line, m in found
            if m.removeprefix("reelbench.") == "benchmark" or m.removeprefix("reelbench.").startswith("benchmark.")]


def test_the_layers_are_the_subpackages_in_order():
    layers = _layers()
    assert layers == ["core", "work", "runs", "figures", "answer", "studies", "contract", "cli"]
    packages = sorted(p.name for p in BENCHMARK.iterdir() if (p / "__init__.py").is_file())
    assert packages == sorted(layers), "every subpackage of benchmark/ is a layer listed in benchmark/__init__.py"


def test_no_module_at_the_top_level_of_benchmark():
    top = sorted(p.name for p in BENCHMARK.glob("*.py"))
    assert top == ["__init__.py", "__main__.py"], f"a module belongs in its layer's subpackage: {top}"


def test_each_layer_imports_only_from_itself_and_the_layers_before_it():
    layers = _layers()
    rank = {name: k for k, name in enumerate(layers)}
    wrong = []
    for path in sorted(BENCHMARK.rglob("*.py")):
        parts = path.relative_to(BENCHMARK).parts
        if len(parts) < 2:  # __init__ and __main__ of benchmark/ itself: the command line's entry
            continue
        mine = parts[0]
        for line, module in _imports(path):
            target = module.split(".")[1] if "." in module else None
            if target is None or target not in rank:
                wrong.append(f"benchmark/{'/'.join(parts)}:{line} imports {module} (not a layer)")
            elif rank[target] > rank[mine]:
                wrong.append(f"benchmark/{'/'.join(parts)}:{line} ({mine}) imports {module} ({target} comes after it)")
    assert not wrong, "layers import only from the layers before them:\n" + "\n".join(wrong)


def test_code_imports_the_installed_names_only():
    """models, integrators and benchmark install as reelbench.models, reelbench.integrators and
    reelbench.benchmark; a bare `import models` would load a second copy of the folder (from
    the repository root on sys.path), with registries of its own."""
    root = BENCHMARK.parent
    bare = []
    for folder in ("models", "integrators", "benchmark", "tests"):
        for path in sorted((root / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
                bare += [f"{path.relative_to(root)}:{node.lineno} imports {n}" for n in names
                         if n.split(".")[0] in ("models", "integrators", "benchmark")]
    assert not bare, "import the installed names (reelbench.models, ...):\n" + "\n".join(bare)
