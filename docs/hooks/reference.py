"""MkDocs hook: the Reference pages, generated at build time from the code so that they cannot drift.

* ``<!-- reference:config -->`` (docs/reference/config.md) becomes one table per config group with every key of the
  dataclass schemas in ``conf/`` (``conf/schema.py`` and the ``conf/*_schema.py`` modules): its type, its value in the
  main job's composed config (``python -m flows.evaluate``), its unit and description (the field's comment or the
  ``name: text`` entry of its class docstring) and its valid range (the ``must ...`` messages of the range checks).
* ``<!-- reference:artifacts -->`` (docs/reference/artifacts.md) becomes one section per method step with what its
  ``@artifact_step`` declaration names: producing steps of its inputs, the config paths it reads (its cache key),
  the input files and the arrays it writes.  The declarations are read from the source with ``ast`` (nothing under
  ``tasks/`` is imported), so the page follows the code wherever a step module lives.
* ``<!-- reference:metric-ranges -->`` (docs/reference/preflight.md) becomes the table of every written metric's
  documented range (``tasks/evaluation/metric_ranges.py``, a module without heavy imports).

The functions are plain Python so that ``tests/flows/test_docs.py`` checks the same output the site shows.
"""
from __future__ import annotations

import ast
import dataclasses
import importlib
import re
import sys
import typing
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
STAGE_ORDER = ("control", "physics", "render", "generation", "evaluation", "reporting", "verification")
KEY_RE = re.compile(r"^[a-z_]+(\.[a-z_0-9]+)+(/[a-z_0-9]+)?$")
UNIT_RE = re.compile(
    r"^(m/s\^2|m/s|m|s|ms|Pa|MPa|Hz|N|rad|px|deg|degrees|1/s|kg/m\^3|kg|J|bytes|1|flexion units|frames|grid cells|"
    r"m per unit force coefficient|N per unit force coefficient)(?=$|[,;:)\s])")
IN_UNIT_RE = re.compile(r"\bin (m/s\^2|m/s|m|s|Pa|Hz|N|rad|px|degrees|kg/m\^3|metres|seconds|pascals)\b")


# ------------------------------------------------------------------------------------------------ config reference
def _conf_modules() -> list:
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    conf = ROOT / "conf"  # the studies' schemas live in conf/study/
    found = sorted(p.relative_to(ROOT).with_suffix("") for p in conf.rglob("*schema.py") if p != conf / "schema.py")
    names = ["conf.schema"] + [".".join(p.parts) for p in found]
    return [importlib.import_module(n) for n in names]


def _field_comments(cls: type) -> dict[str, str]:
    """Trailing ``# ...`` comments of the fields in a dataclass's source (with a comment block just above)."""
    import inspect

    try:
        lines, _ = inspect.getsourcelines(cls)
    except (OSError, TypeError):
        return {}
    out: dict[str, str] = {}
    above: list[str] = []
    for line in lines[1:]:
        stripped = line.strip()
        if stripped.startswith("#"):
            above.append(stripped.lstrip("#").strip())
            continue
        m = re.match(r"^\s+([a-z_][a-z_0-9]*)\s*:\s*[^=]+?(=.*?)?(#\s*(.*))?$", line.rstrip())
        if m and not stripped.startswith(("def ", "return")):
            text = (m.group(4) or "").strip()
            if above:
                text = (" ".join(above) + (" " + text if text else "")).strip()
            out[m.group(1)] = text
        above = []
    return out


def _doc_entries(cls: type) -> dict[str, str]:
    """``name: text`` entries of a class docstring for its field names, in any of the layouts conf/ uses: one entry
    per (indented) line, several on a line after ``.`` or ``;``, ``a, b:`` and ``a / b:`` naming several fields.
    Section headings (a capitalised line without a colon, less indented than the entries) are left out."""
    doc = cls.__doc__ or ""
    fields_ = [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls) else []
    if not fields_ or ":" not in doc:
        return {}
    lines = doc.splitlines()[1:]
    lines = [ln for ln in lines if not re.match(r"^\s{0,4}[A-Z][^:]*$", ln)]
    text = " ".join(ln.strip() for ln in lines).strip()
    name = "|".join(sorted(map(re.escape, fields_), key=len, reverse=True))
    head = re.compile(rf"(?:^|(?<=[.;)] )|(?<=[.;)]  ))((?:{name})(?:\s*(?:,|/)\s*(?:{name}))*):\s")
    found = list(head.finditer(text))
    out: dict[str, str] = {}
    for i, m in enumerate(found):
        body = text[m.end(): found[i + 1].start() if i + 1 < len(found) else len(text)].strip()
        for n in re.split(r"\s*(?:,|/)\s*", m.group(1)):
            out.setdefault(n, body)
    return out


def _doc_sentence(cls: type, name: str) -> str:
    """The first sentence of a class docstring that names ``name`` in double backquotes (prose docstrings)."""
    doc = " ".join((cls.__doc__ or "").split())
    for sentence in re.split(r"(?<=[.;])\s+", doc):
        if f"``{name}``" in sentence:
            return sentence.strip()
    return ""


def _type_name(tp: object) -> str:
    text = str(tp).replace("typing.", "").replace("NoneType", "None")
    if isinstance(tp, type):
        text = tp.__name__
    return re.sub(r"<class '([^']+)'>", r"\1", text).replace("conf.", "")


def _dataclass_of(tp: object) -> type | None:
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return tp
    for arg in typing.get_args(tp):
        if dataclasses.is_dataclass(arg) and isinstance(arg, type):
            return arg
    return None


def _ranges() -> dict[str, list[str]]:
    """Config key -> the ``must ...`` texts of the range checks in conf/ (module-level names are resolved)."""
    found: dict[str, list[str]] = {}

    def literal(node: ast.AST, namespace: dict) -> str | None:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return node.value
        if isinstance(node, ast.JoinedStr):
            parts = []
            for v in node.values:
                if isinstance(v, ast.Constant):
                    parts.append(str(v.value))
                else:
                    try:
                        parts.append(str(eval(compile(ast.Expression(v.value), "<range>", "eval"), dict(namespace))))
                    except Exception:
                        parts.append("…")
            return "".join(parts)
        return None

    def add(key: str, msg: str) -> None:
        msg = re.split(r",? \(?got\b", msg)[0].strip().rstrip(",;:")
        if not msg:
            return
        head, _, tail = key.partition("/")
        keys = [head] + ([head.rsplit(".", 1)[0] + "." + tail] if tail else [])
        for k in keys:
            if msg not in found.setdefault(k, []):
                found[k].append(msg)

    for module in _conf_modules():
        tree = ast.parse(Path(module.__file__).read_text())
        namespace = vars(module)
        for node in ast.walk(tree):
            items: list[ast.AST] = []
            prefix = ""
            if isinstance(node, ast.Call):
                items = list(node.args)
                if isinstance(node.func, ast.Name) and node.func.id == "bad":
                    prefix = "mpm."
            elif isinstance(node, ast.Tuple):
                items = list(node.elts)
            texts = [literal(i, namespace) for i in items]
            for i, text in enumerate(texts):
                if text is None:
                    continue
                key = prefix + text
                if KEY_RE.match(key) and i + 1 < len(texts) and texts[i + 1] is not None:
                    add(key, texts[i + 1])
                m = re.match(r"^([a-z_]+(?:\.[a-z_0-9]+)+): (must .*|needs? .*)$", text)
                if m:
                    add(m.group(1), m.group(2))
    return found


def _unit(key: str, text: str) -> str:
    m = UNIT_RE.match(text) or IN_UNIT_RE.search(text)
    if m:
        return {"metres": "m", "seconds": "s", "pascals": "Pa"}.get(m.group(1), m.group(1))
    if key.endswith("_deg"):
        return "deg"
    return ""


def _rows(cls: type, prefix: str, values: object, seen: set,
          documented: frozenset = frozenset()) -> list[tuple[str, str, str, str, str]]:
    """Rows of ``cls``'s fields (nested dataclasses expanded); a field whose dataclass is in ``documented`` (a group
    of the main config) gets one row pointing to that group instead of its schema defaults."""
    comments, docs = _field_comments(cls), _doc_entries(cls)
    rows = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}.{f.name}" if prefix else f.name
        tp = hints.get(f.name, f.type)
        sub = _dataclass_of(tp)
        value = values.get(f.name) if isinstance(values, dict) else None
        if sub is not None and sub in documented:
            rows.append((key, _type_name(tp), "–", "", f"the `{sub.__name__}` group of the main config, above"))
            continue
        if sub is not None and typing.get_origin(tp) is not dict:
            seen.add(sub)
            rows += _rows(sub, key, value if isinstance(value, dict) else _default(f), seen, documented)
            continue
        text = docs.get(f.name) or comments.get(f.name, "") or _doc_sentence(cls, f.name)
        if typing.get_origin(tp) is dict and _dataclass_of(typing.get_args(tp)[-1]):
            inner = _dataclass_of(typing.get_args(tp)[-1])
            text = (text + " " if text else "") + f"Named entries, each with the keys of `{inner.__name__}`."
            value = sorted(value) if isinstance(value, dict) else value
        shown = value if isinstance(values, dict) and f.name in values else _default(f)
        rows.append((key, _type_name(tp), _fmt(shown), _unit(f.name, text), text))
    return rows


def _default(f: dataclasses.Field) -> object:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        value = f.default_factory()  # type: ignore[misc]
        return dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
    return "???"


def _fmt(value: object) -> str:
    if isinstance(value, str) and value == "???":
        return "(required)"
    text = repr(value) if isinstance(value, str) else str(value)
    if value is None:
        text = "null"
    elif isinstance(value, bool):
        text = str(value).lower()
    text = text if len(text) <= 60 else text[:57] + "…"
    return "`" + text.replace("|", "\\|") + "`"


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def main_job_config() -> dict:
    """The composed config of ``python -m flows.evaluate`` (no overrides), as plain containers."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    schema = importlib.import_module("conf.schema")
    schema.register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("evaluate")
    return OmegaConf.to_container(cfg, resolve=False)  # type: ignore[return-value]


def config_rows() -> dict[str, list[tuple[str, str, str, str, str]]]:
    """Group -> rows (key, type, main-job value, unit, description) of the main config, then the other schemas."""
    schema = importlib.import_module("conf.schema")
    values = main_job_config()
    seen: set = {schema.Config}
    groups: dict[str, list] = {}
    hints = typing.get_type_hints(schema.Config)
    for f in dataclasses.fields(schema.Config):
        sub = _dataclass_of(hints[f.name])
        if f.name == "object":
            catalog = values.get("catalog") or {}
            example = catalog.get("tomato") or next(iter(catalog.values()), None)
            groups["object"] = _rows(sub, "object", example, seen)
            seen.add(sub)
        elif f.name == "variant":
            variants = values.get("variants") or {}
            groups["variant"] = _rows(sub, "variant", variants.get("full"), seen)
            seen.add(sub)
        elif sub is not None and typing.get_origin(hints[f.name]) is not dict:
            seen.add(sub)
            groups[f.name] = _rows(sub, f.name, values.get(f.name), seen)
        else:
            groups.setdefault("(top level)", []).extend(_rows_for_field(schema.Config, f, values))
    for module in _conf_modules():
        for obj in vars(module).values():
            if (dataclasses.is_dataclass(obj) and isinstance(obj, type) and obj.__module__ == module.__name__
                    and obj not in seen and not issubclass(obj, schema.Config)):
                groups[f"{obj.__name__} ({module.__name__.replace('.', '/')}.py)"] = _rows(obj, "", None, set(),
                                                                                         frozenset(seen))
    return groups


def _rows_for_field(cls: type, f: dataclasses.Field, values: dict) -> list:
    rows = _rows(cls, "", values, set())
    return [r for r in rows if r[0] == f.name]


def config_reference_markdown() -> str:
    ranges = _ranges()
    out = []
    for group, rows in config_rows().items():
        out.append(f"## `{group}`\n" if group[0].islower() else f"## {group}\n")
        out.append("| key | type | main job | unit | valid range | what it is |")
        out.append("|---|---|---|---|---|---|")
        for key, tp, value, unit, text in rows:
            rng = "; ".join(ranges.get(key, []))
            out.append(f"| `{key}` | {_cell(tp)} | {value} | {_cell(unit)} | {_cell(rng)} | {_cell(text)} |")
        out.append("")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------ artifact reference
def artifact_steps() -> list[dict]:
    """Every ``@artifact_step(...)`` declaration under tasks/, in pipeline order (stage, then flows/pipeline.py)."""
    pipeline = (ROOT / "flows" / "pipeline.py")
    order_text = pipeline.read_text() if pipeline.exists() else ""
    order_text = order_text[max(order_text.find("PER_OBJECT"), 0):]  # the step tuples, in pipeline order
    steps = []
    for path in sorted((ROOT / "tasks").rglob("*.py")):
        tree = ast.parse(path.read_text())
        names = {**_imported_names(tree), **_module_names(tree)}
        for node in ast.walk(tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for dec in node.decorator_list:
                if not (isinstance(dec, ast.Call) and getattr(dec.func, "id", getattr(dec.func, "attr", "")) ==
                        "artifact_step" and dec.args and isinstance(dec.args[0], ast.Constant)):
                    continue
                spec = {"name": dec.args[0].value, "module": ".".join(path.relative_to(ROOT).with_suffix("").parts),
                        "function": node.name, "doc": (ast.get_docstring(node) or "").strip().split("\n\n")[0]}
                for kw in dec.keywords:
                    spec[kw.arg] = _static_names(kw.value, names)
                steps.append(spec)

    def order(spec: dict) -> tuple:
        stage = spec["module"].split(".")[1]
        pos = order_text.find(spec["function"])
        return (STAGE_ORDER.index(stage) if stage in STAGE_ORDER else 99, pos if pos >= 0 else 10**9)

    return sorted(steps, key=order)


def _module_names(tree: ast.Module) -> dict[str, ast.AST]:
    """A module's top-level ``NAME = value`` bindings, unevaluated."""
    return {t.id: n.value for n in tree.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}


def _imported_names(tree: ast.Module, depth: int = 3) -> dict[str, ast.AST]:
    """Module-level names a module imports from another of ours (``from tasks.x import NAME``), bound to the value
    they are assigned in that module, with the names that value uses from there (a declaration shared by two steps,
    e.g. the rollout's outputs)."""
    out: dict[str, ast.AST] = {}
    for node in tree.body:
        if depth and isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "tasks" \
                and not node.level:
            path = ROOT.joinpath(*node.module.split(".")).with_suffix(".py")
            if not path.exists():
                continue
            source_tree = ast.parse(path.read_text())
            assigned = _module_names(source_tree)
            if any(a.name in assigned for a in node.names):
                out.update({**_imported_names(source_tree, depth - 1), **assigned})
                out.update({a.asname: assigned[a.name] for a in node.names if a.asname and a.name in assigned})
    return out


def _static_names(node: ast.AST, names: dict[str, ast.AST]) -> list[str]:
    """The strings a declaration's argument stands for, read without running the module: a tuple or list of string
    literals, a module-level name bound to one, ``tuple(NAME)`` of a dict (its keys) and ``a + b``."""
    if isinstance(node, (ast.Tuple, ast.List)):
        out: list[str] = []
        for e in node.elts:
            if isinstance(e, ast.Constant) and isinstance(e.value, str):
                out.append(e.value)
            elif isinstance(e, ast.Starred):
                out += _static_names(e.value, names)
            else:
                raise ValueError(f"@artifact_step element {ast.unparse(e)!r} cannot be read statically")
        return out
    if (isinstance(node, ast.GeneratorExp) and len(node.generators) == 1 and not node.generators[0].ifs
            and isinstance(node.generators[0].target, ast.Name)):  # (f"{k}?" for k in NAMES)
        var = node.generators[0].target.id

        def render(elt: ast.AST, value: str) -> str:
            if isinstance(elt, ast.Name) and elt.id == var:
                return value
            if isinstance(elt, ast.JoinedStr):
                return "".join(str(v.value) if isinstance(v, ast.Constant) else render(v.value, value)
                               for v in elt.values)
            raise ValueError(f"@artifact_step element {ast.unparse(elt)!r} cannot be read statically")

        return [render(node.elt, v) for v in _static_names(node.generators[0].iter, names)]
    if isinstance(node, ast.Dict):
        return [k.value for k in node.keys if isinstance(k, ast.Constant) and isinstance(k.value, str)]
    if isinstance(node, ast.Name) and node.id in names:
        return _static_names(names[node.id], names)
    if isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("tuple", "list") and len(node.args) == 1:
        return _static_names(node.args[0], names)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return _static_names(node.left, names) + _static_names(node.right, names)
    raise ValueError(f"@artifact_step argument {ast.unparse(node)!r} cannot be read statically: use a tuple of "
                     f"strings or a module-level name bound to one")


def artifact_reference_markdown() -> str:
    out = []
    for s in artifact_steps():
        out.append(f"## `{s['name']}`\n")
        out.append(f"`{s['module']}.{s['function']}`" + (f": {' '.join(s['doc'].split())}" if s["doc"] else ""))
        out.append("")
        out.append(f"- **inputs** (producing steps): {', '.join(f'`{i}`' for i in s.get('inputs', [])) or 'none'}")
        out.append(f"- **reads** (config paths, the cache key): "
                   f"{', '.join(f'`{r}`' for r in s.get('reads', [])) or 'none'}")
        if s.get("files"):
            out.append(f"- **files** (content digest joins the key): {', '.join(f'`{r}`' for r in s['files'])}")
        outputs = ", ".join(f"`{o.rstrip('?')}`" + (" (some scenes)" if o.endswith("?") else "")
                            for o in s.get("outputs", []))
        out.append(f"- **arrays written**: {outputs or 'none'}")
        out.append("")
    return "\n".join(out)


# ------------------------------------------------------------------------------------------------ mkdocs hook
# ------------------------------------------------------------------------------------------------ metric ranges
def metric_ranges_markdown() -> str:
    """The table of :data:`tasks.evaluation.metric_ranges.METRIC_RANGES`: each metric and the range it is checked
    against when written."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from tasks.evaluation.metric_ranges import METRIC_RANGES

    rows = [f"| `{name}` | {rng.text()} |" for name, rng in METRIC_RANGES.items()]
    return "\n".join(["| metric | documented range |", "|---|---|", *rows])


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ARG001 (mkdocs hook signature)
    if "<!-- reference:config -->" in markdown:
        markdown = markdown.replace("<!-- reference:config -->", config_reference_markdown())
    if "<!-- reference:artifacts -->" in markdown:
        markdown = markdown.replace("<!-- reference:artifacts -->", artifact_reference_markdown())
    if "<!-- reference:metric-ranges -->" in markdown:
        markdown = markdown.replace("<!-- reference:metric-ranges -->", metric_ranges_markdown())
    return markdown
