"""The code version of a step: a digest of every project module its module can reach through imports.

A step's cache key must change when any code it computes with changes, and only then.  A hand-kept list of
modules goes stale (a helper called through another module is easily forgotten), so the list is derived: the
import closure of the step's module inside the project (packages ``tasks`` and ``conf``), read statically from
the source with :mod:`ast`.  Every ``import`` / ``from ... import`` statement counts, also those inside functions
(a late import is still code the step runs).  ``from package import name`` reaches ``package/__init__.py`` and,
when ``name`` is a submodule, that module.  Parent packages that a dotted import executes implicitly are not
followed: their ``__init__.py`` files hold only a docstring (``tests/flows/test_layering.py`` keeps it so), except the
re-exporting ones a module imports from explicitly.

A module that reads data files shipped beside it (e.g. the material table ``materials.yaml``) names them in a
module-level ``DATA_FILES = ("materials.yaml", ...)`` tuple of string literals; their bytes join the version of
every step whose closure contains that module.

Reading the files (not ``sys.modules``) makes the version independent of import order and lets a test compute
the versions of a modified copy of the tree without importing it.
"""
from __future__ import annotations

import ast
import functools
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


_PARSED: dict[tuple[str, str, int, int], frozenset[str]] = {}  # (module, path, mtime_ns, size) -> its imports


def _imports_of(name: str, path: Path, root: Path) -> frozenset[str]:
    st = path.stat()
    key = (name, str(path), st.st_mtime_ns, st.st_size)
    if key not in _PARSED:
        _PARSED[key] = frozenset(imported_modules(name, path.read_text(), root))
    return _PARSED[key]


def import_closure(name: str, root: Path = REPO_ROOT, path: Path | None = None) -> list[str]:
    """Sorted names of every project module reachable from module ``name`` through imports (``name`` included).

    ``path`` is the source file of ``name`` when it is not a project module (e.g. a step defined in a test)."""
    seen: set[str] = set()
    todo = [name]
    files = {name: path} if path is not None else {}
    while todo:
        current = todo.pop()
        if current in seen:
            continue
        source = files.get(current) or module_file(current, root)
        if source is None:
            raise ModuleNotFoundError(f"project module {current!r} has no source file under {root}")
        files[current] = source
        seen.add(current)
        todo.extend(_imports_of(current, source, root) - seen)
    return sorted(seen)


def data_files(source_path: Path) -> list[Path]:
    """The files named by the module-level ``DATA_FILES`` tuple of the module at ``source_path`` (next to it);
    parsed once per version of the file (a step's version reads every module of its closure)."""
    st = source_path.stat()
    return list(_data_files(source_path, st.st_mtime_ns, st.st_size))


@functools.lru_cache(maxsize=None)
def _data_files(source_path: Path, mtime_ns: int, size: int) -> tuple[Path, ...]:
    return tuple(_parse_data_files(source_path))


def _parse_data_files(source_path: Path) -> list[Path]:
    for node in ast.parse(source_path.read_text()).body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        if (any(isinstance(t, ast.Name) and t.id == "DATA_FILES" for t in targets)
                and isinstance(node.value, (ast.Tuple, ast.List))):
            return [source_path.parent / elt.value for elt in node.value.elts
                    if isinstance(elt, ast.Constant) and isinstance(elt.value, str)]
    return []


def code_version(name: str, root: Path | None = None, path: Path | None = None) -> str:
    """sha256 over the names and sources of :func:`import_closure` of module ``name`` (source file ``path`` when
    ``name`` is not a project module)."""
    root = (root or REPO_ROOT).resolve()
    h = hashlib.sha256()
    for module in import_closure(name, root, path):
        source = path if (module == name and path is not None) else module_file(module, root)
        h.update(module.encode() + b"\0")
        h.update(source.read_bytes() + b"\0")
        for data in data_files(source):
            h.update(data.name.encode() + b"\0" + data.read_bytes() + b"\0")
    return h.hexdigest()
