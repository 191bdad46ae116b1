"""One import name: the distribution adds only `minority` to the import namespace (the
repository's folders protocol/, insitu/, sim/, gns/, render_server/ are its subpackages through
the symlinks minority/X -> ../X, so the source tree resolves without an install or an import
hook, as static tools read it), and the layering holds: protocol imports none of the others;
insitu (the in situ API) imports protocol only; sim imports protocol and insitu; gns and
render_server import protocol; sim, gns and render_server never import each other; none of
them imports the command layer (minority.cli, ...)."""

import ast
import subprocess
import sys
from importlib.metadata import distribution, packages_distributions
from pathlib import Path

import pytest

ROOT = Path(__file__).parent.parent
LAYERS = {"protocol": set(), "insitu": {"protocol"}, "sim": {"protocol", "insitu"},
          "gns": {"protocol"}, "render_server": {"protocol"}}
OLD_NAMES = ("protocol", "insitu", "sim", "gns", "render_server")


def test_the_only_top_level_import_name_is_minority():
    names = sorted(n for n, dists in packages_distributions().items() if "minority" in dists)
    assert names == ["minority"]
    assert distribution("minority").read_text("top_level.txt").split() == ["minority"]


def test_the_subpackages_import_from_anywhere_and_the_old_names_do_not(tmp_path):
    code = ("import importlib.util as u, minority.protocol, minority.insitu, minority.sim, "
            "minority.gns, minority.render_server; "
            f"print([n for n in {OLD_NAMES!r} if u.find_spec(n)])")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_source_tree_resolves_without_an_install():
    """From the repository root with no site-packages (python -S: no editable import hook),
    as pyright and the IDEs resolve imports: every subpackage is found under minority/."""
    code = ("import importlib.util as u; "
            f"print([n for n in {OLD_NAMES!r} if u.find_spec('minority.' + n) is None])")
    out = subprocess.run([sys.executable, "-S", "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
    for name in OLD_NAMES:
        assert (ROOT / "minority" / name).resolve() == (ROOT / name).resolve(), name


def imported(path: Path) -> set[str]:
    """The minority subpackages a module imports (`minority.X...` -> X)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level
                 else [])
        for name in names:
            parts = name.split(".")
            if parts[0] in OLD_NAMES:
                found.add(f"old name {parts[0]}")
            elif parts[0] == "minority" and len(parts) > 1:
                found.add(parts[1])
            elif parts[0] == "minority" and isinstance(node, ast.ImportFrom):
                found.update(a.name for a in node.names)
    return found


@pytest.mark.parametrize("package", sorted(LAYERS))
def test_the_layers_hold(package):
    for path in sorted((ROOT / package).rglob("*.py")):
        bad = imported(path) - LAYERS[package] - {package}
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"
