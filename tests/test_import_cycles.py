"""No import circle between the project's modules, and the picture of the layers in
docs/architecture.md is the one the imports give (tools/layers.py reads them from the
sources: lazy imports count, annotation-only ones do not)."""

from tools.layers import DOC, cycles, document_block, module_graph, picture


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_imports_itself_back():
    graph = module_graph()
    assert len(graph) > 100  # every package was found
    assert graph["minority.cli"]  # imports were resolved
    assert cycles(graph) == []


def test_the_documented_layers_are_the_imports():
    assert document_block(DOC.read_text()) == picture(module_graph()), \
        "run `python tools/layers.py --write`"
