"""The code version of a step: a digest of every project module its module can reach through imports.

A step's cache key must change when any code it computes with changes, and only then.  A hand-kept list of
modules goes stale (a helper called through another module is easily forgotten), so the list is derived: the
import closure of the step's module inside the project (packages ``tasks`` and ``conf``), read statically from
the source with :mod:`ast`.  Every ``import`` / ``from ... import`` statement counts, also those inside functions
(a late import is still code the step runs).  ``from package import name`` reaches ``package/__init__.py`` and,
when ``name`` is a submodule, that module.  Parent packages that a dotted import executes implicitly are not
followed: their ``__init__.py`` files hold only a docstring (``tests/test_layering.py`` keeps it so), except the
re-exporting ones a module imports from explicitly.

Reading the files (not ``sys.modules``) makes the version independent of import order and lets a test compute
the versions of a modified copy of the tree without importing it.
"""
from __future__ import annotations

import ast
import hashlib
from pathlib import Path

PROJECT_PACKAGES = ("tasks", "conf")
REPO_ROOT = Path(__file__).resolve().parents[2]


def module_file(name: str, root: Path = REPO_ROOT) -> Path | None:
    """The source file of project module ``name`` under ``root`` (a module file or a package ``__init__``)."""
    base = root.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _is_project(name: str) -> bool:
    return name.split(".")[0] in PROJECT_PACKAGES


def imported_modules(name: str, source: str, root: Path = REPO_ROOT) -> set[str]:
    """Project modules named by the import statements of module ``name`` (whose text is ``source``)."""
    is_package = module_file(name, root) is not None and module_file(name, root).name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if _is_project(alias.name))
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from . import x / from .mod import y
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                target = f"{base}.{node.module}" if node.module else base
            else:
                target = node.module or ""
            if not _is_project(target):
                continue
            found.add(target)
            for alias in node.names:  # `from package import submodule`
                if module_file(f"{target}.{alias.name}", root) is not None:
                    found.add(f"{target}.{alias.name}")
    return {m for m in found if module_file(m, root) is not None}


def import_closure(name: str, root: Path = REPO_ROOT) -> list[str]:
    """Sorted names of every project module reachable from module ``name`` through imports (``name`` included)."""
    seen: set[str] = set()
    todo = [name]
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        path = module_file(current, root)
        if path is None:
            raise ModuleNotFoundError(f"project module {current!r} has no source file under {root}")
        seen.add(current)
        todo.extend(imported_modules(current, path.read_text(), root) - seen)
    return sorted(seen)


def code_version(name: str, root: Path | None = None) -> str:
    """sha256 over the names and sources of :func:`import_closure` of module ``name``."""
    root = (root or REPO_ROOT).resolve()
    h = hashlib.sha256()
    for module in import_closure(name, root):
        h.update(module.encode() + b"\0")
        h.update(module_file(module, root).read_bytes() + b"\0")
    return h.hexdigest()
