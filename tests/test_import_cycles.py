"""No import circle between the project's modules: a module that imports another (at the top or
inside a function) never gets imported back through any chain. Read from the sources (ast),
so a circle through a lazy import counts too; imports for annotations only (under
`if TYPE_CHECKING:`) never run and are left out."""

import ast
from pathlib import Path

ROOT = Path(__file__).parent.parent
# folder -> the module name it installs as (pyproject.toml's package mapping)
PACKAGES = {"minority": "minority", "protocol": "minority.protocol",
            "insitu": "minority.insitu", "sim": "minority.sim", "gns": "minority.gns",
            "render_server": "minority.render_server"}


def project_modules() -> dict[str, Path]:
    """Module name -> source file, for every module of the package (bench/ and tests/ are
    not part of it)."""
    found = {}
    for folder, name in PACKAGES.items():
        for path in sorted((ROOT / folder).glob("*.py")):
            if path.is_symlink() or (ROOT / folder).is_symlink():
                continue
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


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_imports_itself_back():
    modules = project_modules()
    assert len(modules) > 100  # every package was found
    graph = {m: imports_of(m, p, modules) for m, p in modules.items()}
    assert graph["minority.cli"]  # imports were resolved
    assert cycles(graph) == []
