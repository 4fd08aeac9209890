"""The import structure: layers without back-edges, features without cross-imports, no cycles.

Layers, bottom to top (a module may import its own layer and those below):

  mi_plugins (0)  — reused by other Mitsuba projects: imports nothing else of photoreal
  foundation (1)  — what every stage uses: I/O, metrics, the training loop, the dr.wrap bridge
  inverse    (2)  — Dr.Jit optimisation, one feature per folder: morph, face, btf
  generative (3)  — torch models, one feature per folder: diffrender, btf, face, gan; and the shared
                    diffusion core (``generative.diffusion``)
  photoreal  (4)  — the application: CLI, demo, benchmarks

Features of one layer never import each other; they may import a shared core of their layer (``SHARED``), which
imports none of them. A module outside a feature uses only the names the
feature's package exports (``from inverse.morph import run_morph``), never a submodule or a private name.
Every import counts, also those inside functions. Run ``python tests/cli/test_layers.py [ROOT]`` for the report.
"""

from __future__ import annotations

import ast
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LAYERS = {"mi_plugins": 0, "foundation": 1, "inverse": 2, "generative": 3, "photoreal": 4}
FEATURE_LAYERS = ("inverse", "generative")
SHARED = {"generative.diffusion", "inverse.capture"}  #: cores a layer's features build on (public names only)


def unit(module: str) -> str:
    """The unit a module belongs to: a layer, or ``layer.feature`` for feature layers."""
    parts = module.split(".")
    if parts[0] in FEATURE_LAYERS and len(parts) > 1:
        return ".".join(parts[:2])
    return parts[0]


@dataclass
class Imports:
    root: Path
    modules: dict[str, Path] = field(default_factory=dict)
    edges: list[tuple[str, str, tuple[str, ...], int]] = field(default_factory=list)  #: (from, to, names, line)
    exports: dict[str, set[str]] = field(default_factory=dict)  #: package → __all__


def _module_name(path: Path, root: Path) -> str:
    rel = path.relative_to(root).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def scan(root: Path = ROOT) -> Imports:
    out = Imports(root)
    files = [p for top in LAYERS for p in sorted((root / top).rglob("*.py")) if (root / top).is_dir()]
    for path in files:
        out.modules[_module_name(path, root)] = path
    for path in files:
        name = _module_name(path, root)
        is_pkg = path.name == "__init__.py"
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and is_pkg and any(getattr(t, "id", "") == "__all__" for t in node.targets):
                out.exports[name] = {ast.literal_eval(e) for e in node.value.elts}
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in LAYERS:
                        out.edges.append((name, a.name, (), node.lineno))
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = base[: len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] not in LAYERS:
                    continue
                names = tuple(a.name for a in node.names)
                # `from pkg import submodule` imports the submodule
                subs = [n for n in names if f"{target}.{n}" in out.modules]
                if subs:
                    for n in subs:
                        out.edges.append((name, f"{target}.{n}", (), node.lineno))
                    names = tuple(n for n in names if n not in subs)
                if names:
                    out.edges.append((name, target, names, node.lineno))
    return out


def violations(imp: Imports) -> dict[str, list[str]]:
    """{"back_edges": [...], "cross_feature": [...], "internals": [...], "cycles": [...]} as readable lines."""
    v: dict[str, list[str]] = {"back_edges": [], "cross_feature": [], "internals": [], "cycles": []}
    for src, dst, names, line in imp.edges:
        where = f"{imp.modules[src].relative_to(imp.root)}:{line}"
        ls, ld = LAYERS[src.split(".")[0]], LAYERS[dst.split(".")[0]]
        us, ud = unit(src), unit(dst)
        if ld > ls or (src.startswith("mi_plugins") and not dst.startswith("mi_plugins")):
            v["back_edges"].append(f"{where}: {src} imports {dst} (layer {ld} above {ls})")
        elif ls == ld and us != ud and src.split(".")[0] in FEATURE_LAYERS and (ud not in SHARED or us in SHARED):
            v["cross_feature"].append(f"{where}: {src} imports {dst} (feature {ud} from feature {us})")
        elif us != ud and dst.split(".")[0] in FEATURE_LAYERS:
            public = imp.exports.get(ud, set())
            bad = [n for n in names if n.startswith("_") or n not in public]
            if dst != ud or not names or bad:
                what = f"names {bad}" if dst == ud and names else f"module {dst}"
                v["internals"].append(f"{where}: {src} uses {what} of {ud} (use `from {ud} import …` with its __all__)")
    # cycles between units (every import counts)
    graph: dict[str, set[str]] = {}
    for src, dst, _, _ in imp.edges:
        if unit(src) != unit(dst):
            graph.setdefault(unit(src), set()).add(unit(dst))
    v["cycles"] += [f"units: {' → '.join(c)}" for c in _cycles(graph)]
    # cycles between modules (a module importing its own package closes a circle through the package's __init__)
    mgraph: dict[str, set[str]] = {}
    for src, dst, _, _ in imp.edges:
        if src != dst:
            mgraph.setdefault(src, set()).add(dst)
    v["cycles"] += [f"modules: {' → '.join(c)}" for c in _cycles(mgraph)]
    return v


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One representative cycle per strongly connected component with more than one node (Tarjan)."""
    index, low, stack, on, comps = {}, {}, [], set(), []
    counter = [0]

    def visit(n):
        index[n] = low[n] = counter[0]
        counter[0] += 1
        stack.append(n)
        on.add(n)
        for m in graph.get(n, ()):
            if m not in index:
                visit(m)
                low[n] = min(low[n], low[m])
            elif m in on:
                low[n] = min(low[n], index[m])
        if low[n] == index[n]:
            comp = []
            while True:
                m = stack.pop()
                on.discard(m)
                comp.append(m)
                if m == n:
                    break
            if len(comp) > 1:
                comps.append(sorted(comp) + [sorted(comp)[0]])

    for n in list(graph):
        if n not in index:
            visit(n)
    return comps


def report(root: Path = ROOT) -> str:
    imp = scan(root)
    v = violations(imp)
    lines = [f"{len(imp.modules)} modules, {len(imp.edges)} project imports"]
    for k, items in v.items():
        lines.append(f"{k}: {len(items)}")
        lines += [f"  {x}" for x in items]
    return "\n".join(lines)


def test_the_scan_sees_every_kind_of_import():
    imp = scan()
    edges = {(s, d) for s, d, _, _ in imp.edges}
    assert ("inverse.morph.stage", "foundation.loop") in edges  # absolute, module level
    assert ("inverse.morph.stage", "inverse.morph.scene") in edges  # relative
    assert ("photoreal.cli.morph", "inverse.morph") in edges  # inside a function
    assert "run_morph" in imp.exports["inverse.morph"]


def test_the_checks_catch_what_they_forbid(tmp_path):
    """Oracle: a hand-made tree with one violation of each kind is reported exactly so."""
    files = {
        "mi_plugins/__init__.py": "import foundation.files\n",
        "foundation/__init__.py": "", "foundation/files.py": "from inverse.morph import go\n",
        "inverse/__init__.py": "", "inverse/morph/__init__.py": "from .run import go\n__all__ = ['go']\n",
        "inverse/morph/run.py": "from inverse.face.fit import fit\ndef go(): pass\n",
        "inverse/face/__init__.py": "from .fit import fitting\n__all__ = ['fitting']\n",
        "inverse/face/fit.py": "from inverse.face import fitting as f\ndef fitting(): pass\n",
        "generative/__init__.py": "", "generative/gan/__init__.py": "__all__ = []\n",
        "generative/gan/train.py": "from inverse.morph.run import go\nfrom inverse.face import _private\n",
        "photoreal/__init__.py": "", "photoreal/cli.py": "from inverse.morph import go\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    v = violations(scan(tmp_path))
    assert len(v["back_edges"]) == 2  # mi_plugins → foundation, foundation → inverse
    assert len(v["cross_feature"]) == 1 and "inverse.face.fit" in v["cross_feature"][0]
    assert len(v["internals"]) == 2  # a submodule of morph, a private name of face
    assert any("inverse.face.fit" in c for c in v["cycles"])  # face/fit imports its own package


def test_a_shared_core_is_imported_by_features_and_imports_none(tmp_path):
    """Oracle: a hand-made generative layer whose feature uses the core's public name (allowed), a private
    submodule of it (flagged) and whose core imports the feature (flagged)."""
    files = {
        "generative/__init__.py": "",
        "generative/diffusion/__init__.py": "from .core import unet\n__all__ = ['unet']\n",
        "generative/diffusion/core.py": "def unet(): pass\n",
        "generative/diffusion/extra.py": "from generative.face import fit\n",
        "generative/face/__init__.py": "from .models import fit\n__all__ = ['fit']\n",
        "generative/face/models.py": "from generative.diffusion import unet\nfrom generative.diffusion.core import unet\n"
                                     "def fit(): pass\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    v = violations(scan(tmp_path))
    assert len(v["cross_feature"]) == 1 and "generative.diffusion.extra" in v["cross_feature"][0]
    assert len(v["internals"]) == 1 and "generative.diffusion.core" in v["internals"][0]


def test_layers_have_no_back_edges_cross_feature_imports_or_cycles():
    v = violations(scan())
    assert v == {"back_edges": [], "cross_feature": [], "internals": [], "cycles": []}, report()


def rebound_exports(root: Path = ROOT) -> list[str]:
    """Package ``__init__`` files that bind one name twice (the second import silently replaces the first: two
    submodules with a ``DecompSettings`` each) or list a name twice in ``__all__``."""
    out = []
    for init in sorted(root.glob("*/**/__init__.py")):
        if ".venv" in init.parts or init.parts[len(root.parts)] not in LAYERS:
            continue
        bound: dict[str, str] = {}
        for node in ast.parse(init.read_text()).body:
            if isinstance(node, ast.ImportFrom):
                src = "." * node.level + (node.module or "")
                for a in node.names:
                    name = a.asname or a.name
                    if name in bound and bound[name] != f"{src}.{a.name}":
                        out.append(f"{init.relative_to(root)}: {name} from {bound[name]} and from {src}.{a.name}")
                    bound[name] = f"{src}.{a.name}"
            elif isinstance(node, ast.Assign) and any(getattr(x, "id", "") == "__all__" for x in node.targets):
                names = [e.value for e in getattr(node.value, "elts", []) if isinstance(e, ast.Constant)]
                out += [f"{init.relative_to(root)}: {n} twice in __all__" for n in sorted(set(names))
                        if names.count(n) > 1]
    return out


def test_no_package_exports_one_name_twice(tmp_path):
    """A name bound twice in a package is the later submodule's: ``bench diffrender`` once received the face
    decomposition's settings. Oracle for the check itself: a hand-made package with both faults."""
    (tmp_path / "generative" / "x").mkdir(parents=True)
    (tmp_path / "generative" / "x" / "__init__.py").write_text(
        "from .a import S, f\nfrom .b import S\nfrom .b import f as g\n__all__ = ['S', 'f', 'S', 'g']\n")
    found = rebound_exports(tmp_path)
    assert len(found) == 2 and "S from .a.S and from .b.S" in found[0] and "twice in __all__" in found[1]
    assert rebound_exports() == []


if __name__ == "__main__":
    print(report(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT))
