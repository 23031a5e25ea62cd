"""Guards of the package layout: no import cycle inside gmmgp_app, and the stages are
reached only through the pipeline (imports read with ast, function-level ones included)."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "gmmgp_app"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, name: str = None) -> set:
    """Modules of gmmgp_app imported anywhere in ``path`` (absolute names)."""
    name = _module_name(path) if name is None else name
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("gmmgp_app")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("gmmgp_app"):
                continue
            out.add(mod)
            for a in node.names:  # "from . import x" / "from .stages import gp" name modules
                if (PKG.parent / (mod + "." + a.name).replace(".", "/")).with_suffix(
                        ".py").is_file() or (PKG.parent / (mod + "." + a.name).replace(
                        ".", "/") / "__init__.py").is_file():
                    out.add(f"{mod}.{a.name}")
    return out


def _graph() -> dict:
    modules = {_module_name(p): p for p in PKG.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        deps = set()
        for imp in _imports(path):
            # an import of a.b.c also runs a/__init__ and a/b/__init__: keep the module itself
            while imp not in modules and "." in imp:
                imp = imp.rsplit(".", 1)[0]
            if imp in modules and imp != name:
                deps.add(imp)
        graph[name] = deps
    return graph


def _cycles(graph: dict) -> list:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def _package_edges(graph: dict) -> dict:
    """The graph without edges from a package's __init__ to its own modules (re-exports)."""
    return {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}


def test_no_import_cycle_inside_the_package():
    cycles = _cycles(_package_edges(_graph()))
    assert cycles == [], f"import cycles (function-level imports included): {cycles}"


def test_only_the_pipeline_imports_the_stages():
    allowed = {"gmmgp_app.pipeline"}
    bad = {m: sorted(d for d in deps if d == "gmmgp_app.stages" or
                     d.startswith("gmmgp_app.stages."))
           for m, deps in _graph().items()
           if m not in allowed and not m.startswith("gmmgp_app.stages")}
    bad = {m: d for m, d in bad.items() if d}
    assert bad == {}, f"modules importing gmmgp_app.stages besides the pipeline: {bad}"


def test_the_guards_see_a_cycle_and_a_stage_import(tmp_path):
    """The checks above can fail: a planted cycle and a planted stage import are found."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
    probe = PKG / "viz" / "gui.py"
    assert "gmmgp_app.viz.gui_model" in _imports(probe)
    fake = tmp_path / "m.py"
    fake.write_text("def f():\n    from ..stages.gp import fit_local_gps\n"
                    "    from .. import stages\n")
    found = _imports(fake, "gmmgp_app.viz.m")
    assert {"gmmgp_app.stages.gp", "gmmgp_app.stages"} <= found
