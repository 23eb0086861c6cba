"""The layout of ``evtrack/flow``: no import cycle, small modules and classes, no copied
blocks, and one place that chooses the backend."""

from __future__ import annotations

import ast
import io
import keyword
import tokenize
from collections import defaultdict
from pathlib import Path

PACKAGE = "evtrack.flow"
ROOT = Path(__file__).resolve().parents[2] / "evtrack" / "flow"
MAX_MODULE_LINES = 800
MAX_CLASS_LINES = 500
BLOCK_LINES = 10


def _modules() -> dict[str, Path]:
    """Module name -> file, the package's ``__init__`` as ``evtrack.flow``."""
    out = {}
    for path in sorted(ROOT.glob("*.py")):
        out[PACKAGE if path.stem == "__init__" else f"{PACKAGE}.{path.stem}"] = path
    return out


def _import_graph() -> dict[str, set[str]]:
    """Every import of the package's modules, at any depth (inside functions too), as edges
    between the package's modules."""
    modules = _modules()
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                # ``from evtrack.flow import x``: the submodule x, or a name of the package
                targets = [f"{node.module}.{alias.name}"
                           if f"{node.module}.{alias.name}" in modules else node.module
                           for alias in node.names]
            graph[name].update(t for t in targets if t in modules and t != name)
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (a list of modules, the first repeated last), or None."""
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_the_import_graph_has_no_cycle():
    graph = _import_graph()
    assert graph["evtrack.flow.triplet"] >= {"evtrack.flow.backends"}  # the graph is read
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


def test_the_cycle_finder_finds_cycles():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_modules_and_classes_are_small():
    for path in _modules().values():
        text = path.read_text(encoding="utf-8")
        assert len(text.splitlines()) <= MAX_MODULE_LINES, path.name
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                size = node.end_lineno - node.lineno + 1
                assert size <= MAX_CLASS_LINES, f"{path.name}: class {node.name}, {size} lines"


def _line_shapes(path: Path) -> list[tuple[int, str]]:
    """``(line, shape)`` of each code line: its tokens with names, numbers and strings
    replaced by placeholders (comments, blank lines and lines of a string alone left out)."""
    tokens: dict[int, list[str]] = defaultdict(list)
    skip = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT,
            tokenize.ENDMARKER}
    source = path.read_text(encoding="utf-8")
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type in skip:
            continue
        if tok.type == tokenize.NAME and not keyword.iskeyword(tok.string):
            shape = "N"
        elif tok.type == tokenize.NUMBER:
            shape = "0"
        elif tok.type == tokenize.STRING:
            shape = "S"
        else:
            shape = tok.string
        tokens[tok.start[0]].append(shape)
    return [(line, " ".join(shape)) for line, shape in sorted(tokens.items())
            if shape != ["S"]]


def _copied_blocks(paths: list[Path], size: int) -> list[str]:
    """Blocks of ``size`` code lines that occur twice (the same lines, or the same shape
    with other names), not overlapping; blocks of fewer than ``size // 2`` distinct shapes
    (runs of similar assignments or fields) do not count."""
    seen: dict[tuple[str, ...], list[tuple[str, int, int]]] = defaultdict(list)
    for path in paths:
        lines = _line_shapes(path)
        for i in range(len(lines) - size + 1):
            block = lines[i:i + size]
            key = tuple(shape for _, shape in block)
            if len(set(key)) >= size // 2:
                seen[key].append((path.name, block[0][0], block[-1][0]))
    found = []
    for places in seen.values():
        for k, (name_a, first_a, last_a) in enumerate(places):
            for name_b, first_b, last_b in places[k + 1:]:
                if name_a != name_b or last_a < first_b or last_b < first_a:
                    found.append(f"{name_a}:{first_a}-{last_a} ~ {name_b}:{first_b}-{last_b}")
    return found


def test_no_copied_blocks():
    assert _copied_blocks(list(_modules().values()), BLOCK_LINES) == []


def test_the_copy_finder_finds_renamed_copies(tmp_path):
    body = """    total = 0
    for item in values:
        if item > limit:
            total += item * 2
        elif item < 0:
            continue
        else:
            total -= helper(item, limit)
    result = [total, limit]
    result.append(len(values))
    return result
"""
    (tmp_path / "a.py").write_text(f"def f(values, limit):\n{body}", encoding="utf-8")
    renamed = body.replace("total", "acc").replace("item", "v").replace("helper", "g")
    (tmp_path / "b.py").write_text(f"def h(values, limit):\n{renamed}", encoding="utf-8")
    assert _copied_blocks([tmp_path / "a.py", tmp_path / "b.py"], BLOCK_LINES)
    (tmp_path / "b.py").write_text("def h():\n    return 1\n", encoding="utf-8")
    assert not _copied_blocks([tmp_path / "a.py", tmp_path / "b.py"], BLOCK_LINES)


def test_the_flow_asks_resolve_for_its_backend():
    """``TripletFlow`` picks its backend through :func:`evtrack.flow.backends.resolve`, not by
    the type of its search."""
    tree = ast.parse((ROOT / "triplet.py").read_text(encoding="utf-8"))
    checks = [node for node in ast.walk(tree) if isinstance(node, ast.Call)
              and isinstance(node.func, ast.Name) and node.func.id == "isinstance"]
    searches = {"CompiledSearch", "CandidateSearch"}
    names = [{n.id for n in ast.walk(c) if isinstance(n, ast.Name)} for c in checks]
    assert not [n for n in names if n & searches]
    assert "resolve" in {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
