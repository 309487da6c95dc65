"""picdrive's import contract: which layer may import which, read from the source.

Every module of ``host/picdrive`` and ``hil/picdrive_hil`` is parsed (never
imported) and every ``import`` / ``from ... import`` is collected, those
inside functions and methods too (they are where back-edges hide), plus
``importlib.import_module("literal")`` calls.  Each module belongs to exactly
one layer (``LAYERS``, first matching prefix); a layer may import only itself
and the layers it lists; and the module graph has no cycle, inside a layer
either.  ``docs/architecture.md`` ("The house") states the same rules.

    python3 tests/support/import_contract.py      # prints the layers and checks the tree

The checker is plain functions over a folder tree, so the tests run it on
synthetic trees as well (a deliberately added back-edge must fail).
"""
from __future__ import annotations

import ast
import sys
from dataclasses import dataclass, field
from pathlib import Path

# layer -> (module prefixes, layers it may import besides itself), bottom to top.  A prefix
# "picdrive.models" matches the module and everything under it; the first matching layer wins.
LAYERS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "core": (("picdrive.errors", "picdrive.fileio", "picdrive.paths", "picdrive.outputs", "picdrive.argtypes",
              "picdrive.profile", "picdrive.tolerances", "picdrive.board", "picdrive.commutation", "picdrive.control_law",
              "picdrive.result", "picdrive.__init__"), ()),
    "models": (("picdrive.models",), ("core",)),
    "analysis": (("picdrive.analysis",), ("models", "core")),
    "design": (("picdrive.design",), ("analysis", "models", "core")),
    "link": (("picdrive.link",), ("core",)),
    "firmware": (("picdrive.firmware",), ("link", "core")),
    "twin": (("picdrive_hil",), ("firmware", "link", "core")),
    "gate": (("picdrive.gate",), ("design", "analysis", "models", "twin", "firmware", "link", "core")),
    # the tolerance study: the verification's scenario (gate) on drives drawn from the tolerances
    "robustness": (("picdrive.robustness",), ("gate", "design", "analysis", "twin", "firmware", "link", "core")),
    "papers": (("picdrive.papers",), ("gate", "design", "analysis", "models", "core")),
    # the console talks to the firmware through the link; it takes the law -> parameter mapping from
    # the firmware, its owner (fixedpoint.law_parameters), instead of rebuilding it
    "console": (("picdrive.console",), ("firmware", "link", "analysis", "core")),
    "app": (("picdrive.cli", "picdrive.__main__", "picdrive.demo"),
            ("robustness", "console", "papers", "gate", "design", "analysis", "models", "twin", "firmware", "link", "core")),
}
ROOTS = ("picdrive", "picdrive_hil")      # the packages whose imports are checked


@dataclass
class Tree:
    """The modules of a source tree and their imports (module -> {imported module: first line})."""
    modules: dict[str, Path] = field(default_factory=dict)
    imports: dict[str, dict[str, int]] = field(default_factory=dict)


def _module_name(base: Path, path: Path) -> str:
    parts = list(path.relative_to(base).with_suffix("").parts)
    return ".".join(parts)


def _resolve(tree: Tree, name: str) -> str | None:
    """The module ``name`` refers to (itself, or the longest existing module prefix), or None outside ROOTS."""
    if name.split(".")[0] not in ROOTS:
        return None
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in tree.modules:
            return cand
        if cand + ".__init__" in tree.modules:
            return cand + ".__init__"
        parts.pop()
    return name          # not in the tree: reported as unknown


def scan(package_dirs) -> Tree:
    """Parse every ``.py`` under each package folder (its parent is the import root)."""
    t = Tree()
    files = []
    for d in package_dirs:
        d = Path(d)
        for p in sorted(d.rglob("*.py")):
            t.modules[_module_name(d.parent, p)] = p
            files.append((d.parent, p))
    for base, p in files:
        me = _module_name(base, p)
        pkg = me.split(".")[:-1]           # the package a relative import starts from
        found: dict[str, int] = {}
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"), str(p))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base_parts = pkg[:len(pkg) - node.level + 1]
                    mod = ".".join(base_parts + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                # "from pkg import sub" imports the submodule when there is one
                names = [f"{mod}.{a.name}" if _resolve(t, f"{mod}.{a.name}") not in (None, _resolve(t, mod))
                         else mod for a in node.names]
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                  and node.func.attr == "import_module" and node.args
                  and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
                names = [node.args[0].value]
            for n in names:
                r = _resolve(t, n)
                if r is not None and r != me and r not in (f"{x}.__init__" for x in ROOTS):
                    found.setdefault(r, node.lineno)
        t.imports[me] = found
    return t


def layer_of(module: str, layers=LAYERS) -> str | None:
    best = None
    for name, (prefixes, _) in layers.items():
        for pre in prefixes:
            if (module == pre or module.startswith(pre + ".")) and (best is None or len(pre) > best[1]):
                best = (name, len(pre))
    return best[0] if best else None


def cycles(tree: Tree) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in tree.imports.get(v, {}):
            if w not in tree.modules:
                continue
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
    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    for v in sorted(tree.modules):
        if v not in index:
            visit(v)
    return out


def violations(tree: Tree, layers=LAYERS) -> list[str]:
    """Every breach of the contract, one line each (empty: the tree keeps it)."""
    bad = []
    for m in sorted(tree.modules):
        lm = layer_of(m, layers)
        if lm is None:
            bad.append(f"{m}: in no layer (add it to LAYERS in tests/support/import_contract.py)")
            continue
        allowed = {lm, *layers[lm][1]}
        for dep, line in sorted(tree.imports[m].items()):
            if dep not in tree.modules:
                bad.append(f"{m}:{line}: imports {dep}, which is not in the tree")
                continue
            ld = layer_of(dep, layers)
            if ld not in allowed:
                bad.append(f"{m}:{line} ({lm}) imports {dep} ({ld}): {lm} may import only "
                           f"{', '.join(sorted(allowed))}")
    for comp in cycles(tree):
        bad.append("import cycle: " + " <-> ".join(comp))
    return bad


def report(tree: Tree, layers=LAYERS) -> str:
    """The layers bottom to top, what each may import, its modules and its imports in use."""
    lines = ["picdrive import contract (bottom to top; a layer imports only itself and the layers listed):"]
    for name, (_, allowed) in layers.items():
        mods = sorted(m for m in tree.modules if layer_of(m, layers) == name)
        used = sorted({layer_of(d, layers) for m in mods for d in tree.imports[m]} - {name, None})
        lines.append(f"  {name:<9} may import: {', '.join(allowed) or '-'}; imports: {', '.join(used) or '-'}")
        short = [m.removesuffix(".__init__") for m in mods]
        lines.append(f"  {'':<9} {len(mods)} modules: {', '.join(short)}")
    return "\n".join(lines)


def repo_packages(root: Path) -> list[Path]:
    return [root / "host" / "picdrive", root / "hil" / "picdrive_hil"]


if __name__ == "__main__":
    root = Path(__file__).resolve().parents[2]
    t = scan(repo_packages(root))
    print(report(t))
    bad = violations(t)
    print("\n".join(bad) if bad else "contract kept: no forbidden import, no cycle")
    raise SystemExit(1 if bad else 0)
