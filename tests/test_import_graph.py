"""The library's modules import each other without circles.

Every module of ``torch_ao`` is parsed with :mod:`ast` (nothing is imported);
each ``import``/``from ... import`` inside the package is an edge, whether it
sits at module level or inside a function, and relative imports are resolved. Imports under
``if TYPE_CHECKING:`` (for annotations; they never run) are not edges.
A cycle in that graph is a layering defect: the assertion names its modules.
"""
import ast
from pathlib import Path

PACKAGE = "torch_ao"
ROOT = Path(__file__).resolve().parent.parent / PACKAGE


def module_names(root=ROOT, package=PACKAGE):
    """Map each dotted module name under ``package`` to its source file."""
    modules = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


def _resolve(name, modules):
    """The longest known module that ``name`` is or lies inside, or None."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def _is_type_checking(test) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _runtime_nodes(tree):
    """Every node of ``tree`` but those under ``if TYPE_CHECKING:`` (annotations only, never run)."""
    pending = [tree]
    while pending:
        node = pending.pop()
        yield node
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            pending.extend(node.orelse)
            continue
        pending.extend(ast.iter_child_nodes(node))


def imports_of(module, path, modules):
    """The package modules that ``module`` (at ``path``) imports anywhere.

    Importing ``a.b.c`` runs ``a/b/__init__.py`` first: the packages above a target are edges too,
    except those above ``module`` itself (they are running already when it runs) unless a name is
    taken from them explicitly (``from .. import f``: ``f`` must be defined there by then)."""
    is_package = path.name == "__init__.py"
    base = module.split(".") if is_package else module.split(".")[:-1]
    found, implicit = set(), set()  # named targets; the packages above them
    for node in _runtime_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = base[: len(base) - (node.level - 1)]
                source = ".".join(anchor + ([node.module] if node.module else []))
            else:
                source = node.module
            # ``from pkg import sub`` depends on the submodule pkg.sub when
            # there is one, otherwise on the name defined in pkg itself.
            targets = [
                f"{source}.{alias.name}" if f"{source}.{alias.name}" in modules else source
                for alias in node.names
            ]
        else:
            continue
        for target in targets:
            resolved = _resolve(target, modules)
            if resolved is None:
                continue
            found.add(resolved)
            parts = resolved.split(".")
            implicit.update(".".join(parts[:depth]) for depth in range(1, len(parts)))
    own = module.split(".")
    above = {".".join(own[:depth]) for depth in range(1, len(own) + (0 if is_package else 1))}
    return (found | (implicit - above)) - {module}


def import_graph(root=ROOT, package=PACKAGE):
    modules = module_names(root, package)
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def find_cycles(graph):
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []
    counter = [0]

    def visit(node):
        index[node] = low[node] = counter[0]
        counter[0] += 1
        stack.append(node)
        on_stack.add(node)
        for succ in sorted(graph.get(node, ())):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return cycles


def test_checker_finds_a_planted_cycle(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from .sub import b\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("from ..c import x\n")
    (pkg / "c.py").write_text("import pkg.a\nx = 1\n")
    (pkg / "d.py").write_text("from pkg import c\n")
    graph = import_graph(pkg, "pkg")
    assert graph["pkg.a"] == {"pkg.sub", "pkg.sub.b"}
    assert graph["pkg.sub.b"] == {"pkg.c"}
    assert graph["pkg.d"] == {"pkg.c"}
    assert find_cycles(graph) == [["pkg.a", "pkg.c", "pkg.sub.b"]]
    (pkg / "sub" / "__init__.py").write_text("from . import b\n")  # the package runs b: a -> sub -> b -> c -> a
    (pkg / "c.py").write_text("x = 1\n")
    (pkg / "f.py").write_text("import typing\nif typing.TYPE_CHECKING:\n    from .g import G\nelse:\n    import pkg.c\n")
    (pkg / "g.py").write_text("from . import f\nG = 1\n")  # f -> g for annotations only: no circle
    (pkg / "e.py").write_text("from .sub import b\n")
    (pkg / "sub" / "b.py").write_text("from ..e import y\n")  # b -> e -> sub (its package) -> b
    graph = import_graph(pkg, "pkg")
    assert graph["pkg.f"] == {"pkg.c"}
    assert find_cycles(graph) == [["pkg.e", "pkg.sub", "pkg.sub.b"]]


def test_no_import_cycles():
    cycles = find_cycles(import_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)
