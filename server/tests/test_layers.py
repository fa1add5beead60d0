"""The layer rule of the server package (docs/architecture.md, "Server source layout"), read
from the source with `ast`: every import statement, also those inside functions and under
TYPE_CHECKING, resolved to the module it names."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "renderfarm"

# A layer and the layers it may not import.
FORBIDDEN = {
    "domain": {"app", "api", "infra", "cli"},
    "infra": {"app", "api", "cli"},
    "app": {"api", "cli"},
    "client": {"app", "api", "infra", "cli"},  # the client stays importable without the server
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(path: Path) -> set[str]:
    """Every renderfarm module the file imports (for `from X import name`: X, and X.name in
    case name is a submodule)."""
    here = module_name(path)
    package = here if path.name == "__init__.py" else here.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.add(module)
            found |= {f"{module}.{a.name}" for a in node.names}
    return {m for m in found if m == "renderfarm" or m.startswith("renderfarm.")}


def layer_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in FORBIDDEN.keys() | {"api", "cli"} else None


SOURCES = sorted(p for p in PACKAGE.rglob("*.py") if "v1" not in p.relative_to(PACKAGE).parts)


def test_the_resolver_sees_relative_and_absolute_imports():
    """Not vacuous: known imports of the tree are found, resolved to full module names."""
    jobs = imported_modules(PACKAGE / "app" / "jobs.py")
    assert "renderfarm.infra.store" in jobs  # from ..infra.store import ...
    assert "renderfarm.app.checkpoints" in jobs  # from . import checkpoints
    assert "renderfarm.errors" in jobs
    assert "renderfarm.domain.scheduler" in imported_modules(PACKAGE / "app" / "job_control.py")
    assert layer_of("renderfarm.infra.store") == "infra" and layer_of("renderfarm.errors") is None


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_a_layer_imports_no_layer_above_it(layer):
    files = [p for p in SOURCES if module_name(p).split(".")[1:2] == [layer]]
    assert files, f"no modules found for {layer}"
    wrong = [
        f"{module_name(p)} imports {m}"
        for p in files
        for m in sorted(imported_modules(p))
        if layer_of(m) in FORBIDDEN[layer]
    ]
    assert not wrong, "\n".join(wrong)


def test_errors_imports_no_layer_at_run_time():
    """errors.py is imported by every layer: it may name a domain type only for annotations."""
    tree = ast.parse((PACKAGE / "errors.py").read_text())
    runtime = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert all(not (isinstance(n, ast.ImportFrom) and n.level) for n in runtime)


def test_every_module_is_in_a_layer_or_named_here():
    """A new top-level module has to be placed deliberately (a layer, or this list)."""
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert top == ["__init__.py", "__main__.py", "client.py", "errors.py"]
    packages = sorted(p.parent.name for p in PACKAGE.glob("*/__init__.py"))
    assert packages == ["api", "app", "cli", "domain", "infra", "v1"]


# Generated gRPC stubs are not written by hand; every other module over this many lines says
# in its docstring why it stays one module (#23: "no module over about 500 lines without a
# reason given in its header").
LONG_MODULE_LINES = 500
REASON_PHRASES = ("one module", "stays whole", "lines because")


def test_a_long_module_says_why_it_is_one_module():
    unexplained = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.parent.name == "v1" or len(path.read_text().splitlines()) <= LONG_MODULE_LINES:
            continue
        doc = (ast.get_docstring(ast.parse(path.read_text())) or "").lower()
        if not any(phrase in " ".join(doc.split()) for phrase in REASON_PHRASES):
            unexplained.append(str(path.relative_to(PACKAGE)))
    assert not unexplained, f"over {LONG_MODULE_LINES} lines without a reason: {unexplained}"
