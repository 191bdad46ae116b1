"""Who imports whom, read from the sources: the module graph (every import, lazy ones
included; annotation-only ones under `if TYPE_CHECKING:` left out), its circles, and the
picture of the layers that docs/architecture.md shows.

    python tools/layers.py            print the picture
    python tools/layers.py --write    put it into docs/architecture.md (between its markers)

tests/test_import_cycles.py checks that no circle exists and that the document's picture is
this script's output.
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "architecture.md"
BEGIN = "<!-- imports: written by `python tools/layers.py --write`; checked by the tests -->"
END = "<!-- /imports -->"
# folder -> the module name it installs as; top of the building first
PACKAGES = {"minority": "minority", "sim": "minority.sim", "gns": "minority.gns",
            "render_server": "minority.render_server", "insitu": "minority.insitu",
            "protocol": "minority.protocol"}


def project_modules(root: Path = ROOT) -> dict[str, Path]:
    """Module name -> source file, for every module of the package (bench/, tests/ and
    tools/ are not part of it; symlinked folders are the same files under another name)."""
    found = {}
    for folder, name in PACKAGES.items():
        if (root / folder).is_symlink():
            continue
        for path in sorted((root / folder).glob("*.py")):
            if not path.is_symlink():
                found[name if path.stem == "__init__" else f"{name}.{path.stem}"] = path
    return found


def imports_of(module: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project modules `module` imports: `import a.b`, `from a import b` (b a module or
    a name of a), relative imports resolved. A package's own `__init__`, run before any of
    its modules, is not counted as imported by them."""
    package = module if path.stem == "__init__" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    type_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                 and ast.unparse(block.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")
                 for n in ast.walk(block)}  # annotations only: never run
    out = set()
    for node in ast.walk(tree):
        if id(node) in type_only:
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{parent}.{base}" if base else parent
            # `from pkg import sub` imports the module pkg.sub; `from pkg import name`, pkg
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                       for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in modules:  # `a.b.name` -> the module `a.b`
                target = target.rpartition(".")[0]
            if target and target != module and target != "minority":
                out.add(target)
    return out


def module_graph(root: Path = ROOT) -> dict[str, set[str]]:
    modules = project_modules(root)
    return {m: imports_of(m, p, modules) for m, p in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def folder_of(module: str) -> str:
    """`minority.sim.driver` -> `sim`; `minority.cli` -> `minority` (the command layer)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in PACKAGES else "minority"


def picture(graph: dict[str, set[str]]) -> str:
    """One line per folder, top of the building first: the folders its modules import."""
    uses = {folder: set() for folder in PACKAGES}
    for module, targets in graph.items():
        here = folder_of(module)
        uses[here].update(folder_of(t) for t in targets if folder_of(t) != here)
    width = max(len(f) for f in PACKAGES) + 2
    return "\n".join(f"{folder + '/':<{width}}imports "
                     + (", ".join(f"{u}/" for u in PACKAGES if u in uses[folder])
                        or "none of the others")
                     for folder in PACKAGES)


def document_block(text: str) -> str | None:
    """The picture between the markers of a document (None: no markers)."""
    if BEGIN not in text or END not in text:
        return None
    inner = text.split(BEGIN, 1)[1].split(END, 1)[0]
    return inner.strip().removeprefix("```").removesuffix("```").strip()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--write", action="store_true", help=f"update {DOC.relative_to(ROOT)}")
    args = p.parse_args(argv)
    graph = module_graph()
    if found := cycles(graph):
        print(f"import circles: {found}", file=sys.stderr)
    text = picture(graph)
    if not args.write:
        print(text)
        return 1 if found else 0
    doc = DOC.read_text()
    if document_block(doc) is None:
        print(f"{DOC}: no markers {BEGIN!r} ... {END!r}", file=sys.stderr)
        return 2
    head, rest = doc.split(BEGIN, 1)
    DOC.write_text(f"{head}{BEGIN}\n```\n{text}\n```\n{END}{rest.split(END, 1)[1]}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
