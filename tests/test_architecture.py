"""The package reads as the data flow: no module of ``src/n2f2`` imports from a stage later in
it, and no two modules import each other, directly or through others (no import cycle). Every
import is parsed with ``ast`` (also those inside functions, and relative ones), and the checkers
themselves are tried on small fake package trees whose violations are known by hand."""

from __future__ import annotations

import ast
from pathlib import Path

import n2f2

# Importable by every stage.
BOTTOM = ("cameras", "errors", "io", "config", "sparse", "validate", "distributed", "heap", "_lazy")
# The stages, in data-flow order: each may import from itself, the bottom, and earlier stages.
STAGES = ("data", "render", "gaussians", "segments", "field", "train", "hierarchy", "query", "eval", "pipeline",
          "experiments", "viewer", "cli")
PACKAGE_ROOT = Path(n2f2.__file__).parent


def _rank(top: str) -> int | None:
    """-1 for the bottom layer (and the package's own ``__init__``), the stage's position, or
    None for a name that is neither (reported as unknown)."""
    if top in BOTTOM or top == "":
        return -1
    return STAGES.index(top) if top in STAGES else None


def _module_parts(root: Path, path: Path) -> list[str]:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    return parts[:-1] if parts[-1] == "__init__" else parts


def imported_names(root: Path, path: Path, package: str) -> list[tuple[int, str]]:
    """``(line, dotted module)`` of every import of ``package`` in ``path`` (inside functions
    too), relative imports resolved against the module's own package; a name imported from a
    package (``from . import x``, ``from pkg.sub import x``) counts as the submodule ``x`` when
    there is one, else as the package."""
    tree = ast.parse(path.read_text(), filename=str(path))
    parts = _module_parts(root, path)
    own_package = parts if path.name == "__init__.py" else parts[:-1]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names if a.name.split(".")[0] == package]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = own_package[: len(own_package) - (node.level - 1)] if node.level > 1 else own_package
                if node.level - 1 > len(own_package):
                    raise ValueError(f"{path}:{node.lineno}: relative import beyond the package")
                target = [package, *base] + (node.module.split(".") if node.module else [])
            elif node.module and node.module.split(".")[0] == package:
                target = node.module.split(".")
            else:
                continue
            names = []  # from .m import a, b: the submodules m.a and m.b, or m itself for other names
            for a in node.names:
                sub = root.joinpath(*target[1:], a.name)
                is_module = sub.with_suffix(".py").is_file() or (sub / "__init__.py").is_file()
                names.append(".".join(target + [a.name]) if is_module else ".".join(target))
            found += [(node.lineno, name) for name in dict.fromkeys(names)]
    return found


def layer_violations(root: Path, package: str) -> list[str]:
    """Every import in the package at ``root`` of a stage later in the data flow than the
    importing module's stage, or of a top-level name the layering does not know."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        parts = _module_parts(root, path)
        here = parts[0] if parts else ""
        here_rank = _rank(here)
        if here_rank is None:
            problems.append(f"{path.relative_to(root)}: module {here!r} is in no layer")
            continue
        for line, name in imported_names(root, path, package):
            top = name.split(".")[1] if "." in name else ""
            rank = _rank(top)
            if rank is None:
                problems.append(f"{path.relative_to(root)}:{line}: imports {name}, which is in no layer")
            elif rank > here_rank:
                problems.append(f"{path.relative_to(root)}:{line}: {here or package} imports {name} "
                                f"(later in the data flow)")
    return problems


def test_no_module_imports_a_later_stage():
    assert layer_violations(PACKAGE_ROOT, "n2f2") == []


def test_the_layers_name_every_top_level_module():
    tops = {p.stem if p.is_file() else p.name for p in PACKAGE_ROOT.iterdir()
            if (p.suffix == ".py" and p.name != "__init__.py") or (p / "__init__.py").is_file()}
    assert tops == set(BOTTOM) | set(STAGES)


def _tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / "pkg" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "pkg"


def test_checker_finds_each_kind_of_violation(tmp_path):
    """A fake tree with one violation of each kind (worked out by hand) and legal imports beside
    them: exactly the violations are reported."""
    pkg = _tree(tmp_path, {
        "__init__.py": "",
        "errors.py": "",
        "data/__init__.py": "from .scene import x\n",  # legal: within the stage
        "data/scene.py": "from ..errors import InputError\n",  # legal: the bottom layer
        # violation 1: a plain absolute import of a later stage, inside a function
        "data/load.py": "def f():\n    import pkg.render.core\n",
        "render/__init__.py": "from pkg.data import scene\n",  # legal: an earlier stage
        # violation 2: a relative import two levels up into a later stage
        "gaussians/fit.py": "from ..query.engine import QueryEngine\n",
        # violation 3: `from .. import viewer` (the name is the later stage's package)
        "eval/runner.py": "from .. import viewer\nfrom .. import errors\n",
        "query/engine.py": "from ..field import model\n",  # legal
        "viewer/__init__.py": "",
        "cli.py": "from .viewer import commands\nfrom .pipeline import commands as c\n",  # legal: cli is last
    })
    problems = layer_violations(pkg, "pkg")
    assert [p.split(":")[0:2] for p in problems] == [["data/load.py", "2"], ["eval/runner.py", "1"],
                                                     ["gaussians/fit.py", "1"]]
    assert "imports pkg.render.core" in problems[0]
    assert "imports pkg.viewer" in problems[1]
    assert "imports pkg.query.engine" in problems[2]


def test_checker_reports_a_module_in_no_layer(tmp_path):
    pkg = _tree(tmp_path, {"__init__.py": "", "extras.py": "", "data/__init__.py": "from ..extras import y\n"})
    assert layer_violations(pkg, "pkg") == ["data/__init__.py:1: imports pkg.extras, which is in no layer",
                                            "extras.py: module 'extras' is in no layer"]


def test_checker_on_a_clean_tree_reports_nothing(tmp_path):
    pkg = _tree(tmp_path, {"__init__.py": "", "io.py": "", "train/__init__.py": "from ..field import f\n",
                           "field/__init__.py": "import numpy\nfrom pkg.io import write\n"})
    assert layer_violations(pkg, "pkg") == []


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """Module -> the modules of the package at ``root`` it imports, by dotted name; a package is its
    ``__init__`` (``pkg.sub``). Every import counts, at any depth: inside functions and under
    ``if TYPE_CHECKING:`` too (a lazy import only hides a cycle until someone moves it). A name
    that is no module counts as the longest module it starts with; a module importing itself is
    no edge.

    Python loads a module's parent packages before the module. That implied import is no edge:
    a package's ``__init__`` may import its own submodules (the usual re-exports) as long as they
    do not import it back. An explicit import of the parent (``from . import name``, ``from pkg.sub
    import name`` with ``name`` defined in ``pkg/sub/__init__.py``) is an edge like any other, so a
    child that reads its parent's names while the parent imports that child is a cycle: the child
    can meet the parent half initialised."""
    modules = {".".join([package, *_module_parts(root, p)]): p for p in sorted(root.rglob("*.py"))}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        edges = set()
        for _, imported in imported_names(root, path, package):
            while imported not in modules and "." in imported:
                imported = imported.rsplit(".", 1)[0]
            if imported in modules and imported != name:
                edges.add(imported)
        graph[name] = edges
    return graph


def import_cycles(root: Path, package: str) -> list[list[str]]:
    """Every import cycle of the package at ``root``: the strongly connected components of
    :func:`import_graph` with more than one module (Tarjan's algorithm, iterative), each sorted,
    in sorted order. Modules in one component import each other, directly or through others."""
    graph = import_graph(root, package)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    work: list = []  # the depth-first path: (module, iterator over the modules it imports)
    cycles = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        work.append((v, iter(sorted(graph[v]))))

    for start in sorted(graph):
        if start in index:
            continue
        visit(start)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    visit(w)  # descend; v's other children wait
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:  # every child of v done
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[v])
                if low[v] == index[v]:  # v is the root of a component: pop it
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    if len(component) > 1:
                        cycles.append(sorted(component))
    return sorted(cycles)


def test_cycle_checker_finds_exactly_the_cycles_of_a_fake_tree(tmp_path):
    """A fake tree (worked out by hand) with two cycles and legal chains beside them: a -> b ->
    sub.c -> a (one import inside a function, one under TYPE_CHECKING), and a child importing
    its parent's names while the parent imports it (p <-> p.q); d -> a and d -> e -> sub.c lead
    into the first cycle without coming back, and sub's __init__ imports sub.c, which never
    imports sub: exactly the two cycles are reported."""
    pkg = _tree(tmp_path, {
        "__init__.py": "",
        "a.py": "from . import b\n",  # the submodule pkg.b
        "b.py": "def f():\n    from .sub.c import g\n",
        "sub/__init__.py": "from .c import g\n",  # legal: c does not import sub back
        "sub/c.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import pkg.a\ndef g(): ...\n",
        "d.py": "from pkg.a import x\nfrom .e import y\n",  # legal: into the cycle, not back
        "e.py": "import numpy\nfrom .sub import c\nfrom . import e\n",  # legal; the self-import is no edge
        "p/__init__.py": "from .q import Q\nhelper = 1\n",
        "p/q.py": "from . import helper\nclass Q: ...\n",  # pkg.p's __init__, which imports q
    })
    graph = import_graph(pkg, "pkg")
    assert graph["pkg.a"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.sub.c"} and graph["pkg.sub.c"] == {"pkg.a"}
    assert graph["pkg.e"] == {"pkg.sub.c"} and graph["pkg.p.q"] == {"pkg.p"}
    assert import_cycles(pkg, "pkg") == [["pkg.a", "pkg.b", "pkg.sub.c"], ["pkg.p", "pkg.p.q"]]


def test_cycle_checker_on_a_clean_tree_reports_nothing(tmp_path):
    pkg = _tree(tmp_path, {"__init__.py": "from .a import f\n",  # a package importing its own submodule
                           "a.py": "from .b import g\ndef f():\n    from pkg.c import h\n",
                           "b.py": "def g(): ...\n", "c.py": "from . import b\nh = 1\n"})
    assert import_graph(pkg, "pkg") == {"pkg": {"pkg.a"}, "pkg.a": {"pkg.b", "pkg.c"}, "pkg.b": set(),
                                        "pkg.c": {"pkg.b"}}
    assert import_cycles(pkg, "pkg") == []


def test_the_package_has_no_import_cycles():
    cycles = import_cycles(PACKAGE_ROOT, "n2f2")
    assert cycles == [], "modules that import each other (directly or through others): " + "; ".join(
        ", ".join(c) for c in cycles)


def test_the_cli_loads_torch_only_after_choosing_the_openmp_wait_policy():
    # OpenMP reads GOMP_SPINCOUNT / OMP_WAIT_POLICY once, when torch loads: importing the CLI
    # must not load torch before main() has set them.
    import subprocess
    import sys

    code = "import sys, n2f2.cli; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
