"""The package's house rules, checked on its source with `ast` (nothing imported):

- rooms import one way only: a module may import from its own room and from the rooms listed for it in
  ``ALLOWED`` (``model`` and ``data`` import no other room; ``policy`` may use ``model``, ``data`` and
  ``execution``; ``sims`` know nothing of models or policies); every import counts, those inside functions too;
- no import loop among the package's modules;
- sizes a newcomer can read: no file over 450 lines, ``CNMPConfig`` <= 30 fields of its own, the single-decoder
  ``CNMP`` <= 200 lines with no mixture branch, ``CNMPPolicy`` <= 150 lines.
"""

from __future__ import annotations

import ast
from dataclasses import fields
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "lerobot_cnmp"

ALLOWED = {  # room -> the other rooms it may import from
    "model": set(),
    "data": set(),
    "execution": {"model", "data"},
    "policy": {"model", "data", "execution"},
    "promp": {"model", "data", "execution", "policy"},
    "sims": {"data", "execution"},
}
TOP = None  # modules directly under lerobot_cnmp/ (api, hub, record, serve, plot): the top, may import any room


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def room(mod: str) -> str | None:
    parts = mod.split(".")
    if len(parts) >= 3 or (len(parts) == 2 and (PKG / parts[1]).is_dir()):
        return parts[1]
    return TOP


def imports_of(mod: str) -> set[str]:
    """The package modules ``mod`` imports anywhere in its body (the module itself, or the package it names)."""
    tree = ast.parse(MODULES[mod].read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against this module's package
                base = mod.split(".")
                if not MODULES[mod].name == "__init__.py":
                    base = base[:-1]
                base = base[: len(base) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if not name.startswith("lerobot_cnmp"):
                continue
            for alias in node.names:
                sub = f"{name}.{alias.name}"
                out.add(sub if sub in MODULES else name)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("lerobot_cnmp")}
    out.discard(mod)
    return {m for m in out if m in MODULES}


GRAPH = {m: imports_of(m) for m in MODULES}


def test_imports_run_one_way_between_rooms():
    bad = []
    for mod, deps in GRAPH.items():
        src = room(mod)
        if src is TOP:
            continue
        for dep in deps:
            dst = room(dep)
            if dst == src:
                continue
            if dst is TOP or dst not in ALLOWED.get(src, set()):
                bad.append(f"{mod} -> {dep}")
    assert not bad, "imports against the room order:\n" + "\n".join(sorted(bad))


def test_no_import_loop():
    index, low, stack, on_stack, loops = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in GRAPH[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                loops.append(sorted(comp))

    for v in GRAPH:
        if v not in index:
            visit(v)
    assert not loops, f"import loops: {loops}"


def test_no_file_over_450_lines():
    long = {str(p.relative_to(PKG)): n for p in PKG.rglob("*.py") if (n := len(p.read_text().splitlines())) > 450}
    assert not long, f"files over 450 lines: {long}"


def _class_lines(path: Path, name: str) -> tuple[int, ast.ClassDef]:
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return node.end_lineno - node.lineno + 1, node
    raise AssertionError(f"no class {name} in {path}")


def test_cnmp_model_is_small_and_knows_no_mixture():
    n, node = _class_lines(PKG / "model" / "cnmp.py", "CNMP")
    assert n <= 200, f"CNMP is {n} lines"
    src = ast.unparse(node)
    for word in ("expert", "gate", "mixture", "n_experts"):
        assert word not in src, f"CNMP names {word!r}"


def test_cnmp_policy_is_thin():
    n, _ = _class_lines(PKG / "policy" / "modeling_cnmp.py", "CNMPPolicy")
    assert n <= 150, f"CNMPPolicy is {n} lines"


def test_config_has_at_most_30_fields_of_its_own():
    from lerobot.configs.policies import PreTrainedConfig

    from lerobot_cnmp.policy.configuration_cnmp import CNMPConfig

    own = {f.name for f in fields(CNMPConfig)} - {f.name for f in fields(PreTrainedConfig)}
    assert len(own) <= 30, f"CNMPConfig has {len(own)} fields of its own: {sorted(own)}"
