"""No import circles in the tree (issue 42): every import statement of every module of the shipped
packages, at the top, inside functions and under TYPE_CHECKING alike, read from the source (not by
importing), and not one cycle among the modules they join. A module importing its own package's
``__init__`` for a name that ``__init__`` re-exports counts as importing the module it comes from."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"datagen": ROOT / "datagen", "schemas": ROOT / "schemas", "storage": ROOT / "storage",
            "jobs": ROOT / "jobs", "osvp": ROOT / "osvp" / "src" / "osvp"}  # fmt: skip


def module_files() -> dict[str, Path]:
    found = {}
    for package, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = [package, *path.relative_to(folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def reexports(modules: dict[str, Path]) -> dict[tuple[str, str], str]:
    """(package, name) -> the module a package's ``__init__`` takes ``name`` from."""
    found = {}
    for name, path in modules.items():
        if path.name != "__init__.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module in modules:
                for alias in node.names:
                    found[(name, alias.asname or alias.name)] = node.module
    return found


def imports(name: str, path: Path, modules: dict[str, Path], via: dict[tuple[str, str], str]) -> set[str]:
    """The modules of the tree that ``name`` imports (any import statement anywhere in it)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                if submodule in modules:
                    targets.add(submodule)
                elif (base, alias.name) in via and path.name != "__init__.py":
                    targets.add(via[(base, alias.name)])
                else:
                    targets.add(base)
    return {target for target in targets if target in modules and target != name}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def test_the_cycle_finder_finds_a_two_module_circle() -> None:
    assert cycles({"a": {"b"}, "b": {"a"}, "c": {"a"}}) == [["a", "b"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_no_module_of_the_tree_imports_itself_back() -> None:
    modules = module_files()
    via = reexports(modules)
    graph = {name: imports(name, path, modules, via) for name, path in modules.items()}
    assert len(graph) > 150 and graph["storage.checks.validation"] >= {"storage.samples.label_judges", "schemas.config"}
    assert cycles(graph) == []
