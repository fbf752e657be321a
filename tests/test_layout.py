"""The package layout of docs/architecture.md holds: each package of gf_core imports only the
packages before it in the data flow (module-level and function-level imports alike), so there is
no import circle and nothing in sim/ imports render/; formats/ needs nothing of the toolkit but
errors."""

import ast
from pathlib import Path

import gf_core

ROOT = Path(gf_core.__file__).parent
# docs/architecture.md: errors, camera, formats -> native -> render, sph -> sim -> data -> recon -> eval
# -> downstream -> bench (a package may import those of its own rank and before)
RANK = {"errors": 0, "limits": 0.5, "camera": 1, "formats": 1, "native": 2, "render": 3, "sph": 3, "sim": 4,
        "data": 5, "synthetic": 6, "recon": 6, "eval": 7, "downstream": 8, "bench": 9,
        "batch": 1.5}  # batch: errors and formats only
FORBIDDEN = {("sim", "render"), ("recon", "eval")}  # named in docs/architecture.md
ALLOWED_SAME_RANK = {("render", "sph"): False, ("sph", "render"): False, ("camera", "formats"): True,
                     ("formats", "camera"): False, ("synthetic", "recon"): False, ("recon", "synthetic"): False}


def imports(path: Path) -> set[str]:
    """The gf_core packages a module imports (its relative and absolute imports)."""
    pkg = path.relative_to(ROOT).parts
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(pkg[:len(pkg) - node.level])   # the package the dots climb to
                parts = base + (node.module.split(".") if node.module else [])
                names = [parts + [a.name] for a in node.names] if not node.module else [parts]
            elif node.module and node.module.startswith("gf_core."):
                names = [node.module.split(".")[1:]]
            else:
                continue
            out |= {n[0].removesuffix(".py") for n in names if n}
        elif isinstance(node, ast.Import):
            out |= {a.name.split(".")[1] for a in node.names if a.name.startswith("gf_core.")}
    return out


def test_packages_import_only_what_comes_before_them():
    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.name == "__init__.py" and len(rel.parts) == 1:
            continue
        me = rel.parts[0].removesuffix(".py")
        for other in imports(path):
            if other == me or other not in RANK:
                continue
            if RANK[other] > RANK[me] or (me, other) in FORBIDDEN or \
                    (RANK[other] == RANK[me] and not ALLOWED_SAME_RANK.get((me, other), False)):
                bad.append(f"{rel} imports {other}")
    assert not bad, "\n".join(bad)


def test_formats_needs_no_torch():
    for path in (ROOT / "formats").rglob("*.py"):
        tree = ast.parse(path.read_text())
        mods = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        mods |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module and not n.level}
        assert "torch" not in mods, path
