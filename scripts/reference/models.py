"""A pydantic model as a reference page: its fields walked into sections (a table of its own is a section,
every other field an entry of its section), each field's type, default, unit, description and a TOML
example that the model accepts. The rig file's and the rules file's pages (rig_rules.py) are made with it.
"""

from __future__ import annotations

import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .common import GENERATED_NOTE, _num


@dataclass
class FieldDoc:
    section: str            # the table the field lives in, as the TOML names it: "host", "cameras", ""
    name: str               # the key as written in the file (an alias when the model has one)
    anchor: str
    type: str
    default: str
    unit: str
    description: str
    required: bool
    example: str            # a TOML snippet


@dataclass
class SectionDoc:
    key: str                # "host", "cameras", "rules.when", "region.box", ...
    title: str              # "[host]", "[[cameras]]", ...
    model: type
    intro: str
    fields: list[FieldDoc] = field(default_factory=list)
    table_field: FieldDoc | None = None   # the field whose value this table is (none at the top)


_UNIT_SUFFIXES = [("_deg_s", "deg/s"), ("_m_s", "m/s"), ("_ms", "ms"), ("_us", "µs"), ("_px", "px"),
                  ("_deg", "degrees"), ("_m", "m"), ("_s", "s")]
_UNIT_WORDS = [(r"\bmetres\b|\bin metres\b", "m"), (r"\bm/s\b", "m/s"), (r"\bdeg/s\b", "deg/s"),
               (r"\bframes per second\b", "frames/s"), (r"\bmicroseconds\b", "µs"), (r"\bpixels\b|\bpx\b", "px"),
               (r"\bdegrees\b", "degrees"), (r"\bseconds\b", "s")]


def unit_of(name: str, description: str) -> str:
    """The unit a field's name or description gives, else ""."""
    for suffix, unit in _UNIT_SUFFIXES:
        if name.endswith(suffix):
            return unit
    if name == "fps":
        return "frames/s"
    found = {unit for pattern, unit in _UNIT_WORDS if re.search(pattern, description)}
    return found.pop() if len(found) == 1 else ""  # none, or several (a unit that depends on use)


def _models_in(ann: Any) -> list[type]:
    from pydantic import BaseModel

    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return [ann]
    return [m for a in typing.get_args(ann) for m in _models_in(a)]


def _is_list_of_model(ann: Any) -> bool:
    return typing.get_origin(ann) is list and bool(_models_in(ann))


def _constraints(metadata: list) -> str:
    out = []
    for m in metadata:
        for attr, sym in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")):
            v = getattr(m, attr, None)
            if v is not None and type(m).__name__ in ("Ge", "Gt", "Le", "Lt"):
                out.append(f"{sym} {_num(v)}")
        if type(m).__name__ == "MinLen":
            out.append(f"at least {m.min_length} long")
        if type(m).__name__ == "MaxLen":
            out.append(f"at most {m.max_length} long")
    return ", ".join(out)


def type_text(ann: Any, metadata: list | None = None, names: dict[type, str] | None = None) -> str:
    """A reader's name for a field's type."""
    names = names or {}
    base = _type_text(ann, names)
    extra = _constraints(metadata or [])
    return f"{base}, {extra}" if extra else base


def _type_text(ann: Any, names: dict[type, str]) -> str:
    from pydantic import BaseModel

    origin = typing.get_origin(ann)
    args = typing.get_args(ann)
    if origin is typing.Annotated:
        inner, *meta = args
        desc = next((getattr(m, "description", None) for m in meta if getattr(m, "description", None)), None)
        fi_meta = [x for m in meta for x in getattr(m, "metadata", [])]
        text = _type_text(inner, names)
        if desc and desc.startswith("HOST:PORT"):
            return "string HOST:PORT"
        extra = _constraints(fi_meta)
        return f"{text} ({extra})" if extra else text
    if origin is typing.Literal:
        return "one of " + ", ".join(f'`"{a}"`' if isinstance(a, str) else f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        parts = [a for a in args if a is not type(None)]
        return " or ".join(_type_text(a, names) for a in parts)
    if origin is list:
        return f"list of {_type_text(args[0], names)}" if args else "list"
    if origin is tuple:
        inner = {_type_text(a, names) for a in args}
        word = inner.pop() if len(inner) == 1 else "value"
        return f"[{', '.join(['x', 'y', 'z'][:len(args)])}] ({len(args)} {word}s)"
    if origin is dict:
        return "table"
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        key = names.get(ann)
        return f"table ([{key}](#{_anchor(key)}))" if key else "table"
    plain = {str: "string", int: "integer", float: "number", bool: "true or false"}
    return plain.get(ann, getattr(ann, "__name__", str(ann)))


def _anchor(key: str) -> str:
    return key.replace("[]", "").replace(".", "-") or "top"


# Integers shown in hexadecimal in the examples (TOML reads 0x123 as 291).
HEX_KEYS = {"can_id", "vendor_id", "product_id", "request_type"}


def _toml_value(v: Any, key: str = "") -> str:
    if isinstance(v, int) and not isinstance(v, bool) and key in HEX_KEYS:
        return f"0x{v:X}"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, float):
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + " }"
    return _toml_value(str(v))


def _default_text(fi: Any) -> tuple[str, Any]:
    """(what the page shows, the value) for a field's default; ("", None) when it has none."""
    from pydantic_core import PydanticUndefined

    if fi.is_required():
        return "", None
    if fi.default_factory is not None:
        value = fi.default_factory()
        if hasattr(value, "model_dump"):
            return "the table's defaults", None
        return (_toml_value(value) if value not in ([], {}) else ("none" if value == [] else "empty")), value
    if fi.default is PydanticUndefined:
        return "", None
    if fi.default is None:
        return "none", None
    return _toml_value(fi.default), fi.default


def _lookup(data: Any, path: list[str]) -> list[Any]:
    """Every value at `path` in a parsed TOML document ("[]" steps into each item of a list)."""
    nodes = [data]
    for step in path:
        nxt = []
        for n in nodes:
            if step == "[]":
                nxt += n if isinstance(n, list) else []
            elif isinstance(n, dict) and step in n:
                nxt.append(n[step])
        nodes = nxt
    return nodes


class ModelDocs:
    """Walks a pydantic model into sections of fields.

    A field whose value is a table of its own (`[host]`, `[[cameras]]`, `[rules.when]`) is documented
    as that table's section; every other field is an entry of its section. A model that several
    fields share (a region, a range) is a section named in `shared`, and those fields link to it.
    """

    def __init__(self, root: type, example_files: list[Path], shared: dict[str, str],
                 examples: dict[str, Any], intros: dict[str, str]):
        self.root = root
        self.shared = shared                  # class name -> section key
        self.examples = examples              # section.field -> value (for fields the files lack)
        self.intros = intros
        self.data = [tomllib.loads(p.read_text()) for p in example_files]
        self.sections: list[SectionDoc] = []
        self.keys: dict[type, str] = {}
        self.parents: dict[type, list[tuple[type, str]]] = {}   # model -> the (model, field)s reaching it
        self._plan(root, "")
        order = list(shared.values())
        ordered = sorted(self.keys.items(), key=lambda kv: order.index(kv[1]) + 1 if kv[1] in order else 0)
        for model, key in ordered:
            self._section(model, key)

    def is_shared(self, key: str) -> bool:
        return key in self.shared.values()

    def _plan(self, model: type, key: str) -> None:
        if model in self.keys:
            return
        self.keys[model] = self.shared.get(model.__name__, key)
        key = self.keys[model]
        for name, fi in model.model_fields.items():
            if fi.exclude:
                continue
            for sub in _models_in(fi.annotation):
                self.parents.setdefault(sub, []).append((model, fi.alias or name))
                self._plan(sub, f"{key}.{fi.alias or name}" if key else fi.alias or name)

    def _own_table(self, fi: Any) -> bool:
        """True when the field's value is a table documented as its own (non-shared) section."""
        models = _models_in(fi.annotation)
        return bool(models) and not any(self.is_shared(self.keys[m]) for m in models)

    def _title(self, key: str) -> str:
        if not key:
            return "Top level"
        if self.is_shared(key):
            return key
        return f"[[{key}]]" if self._is_list(key) else f"[{key}]"

    def _field_info(self, key: str) -> Any:
        """The FieldInfo of the field that a (non-shared) section key names."""
        parent, fi = self.root, None
        for part in key.split("."):
            fi = next((f for n, f in parent.model_fields.items() if (f.alias or n) == part), None)
            if fi is None:
                return None
            models = _models_in(fi.annotation)
            parent = models[0] if models else None
        return fi

    def _is_list(self, key: str) -> bool:
        fi = self._field_info(key)
        return fi is not None and _is_list_of_model(fi.annotation)

    def _path(self, key: str) -> list[str]:
        """The section key as a path into the TOML document, with "[]" steps into lists."""
        out: list[str] = []
        parts = key.split(".") if key else []
        for i, part in enumerate(parts):
            out.append(part)
            if self._is_list(".".join(parts[: i + 1])):
                out.append("[]")
        return out

    def _section(self, model: type, key: str) -> None:
        doc = (model.__doc__ or "").strip()
        intro = self.intros.get(key, doc if doc and not doc.startswith(("Usage docs", "!!!")) else "")
        sec = SectionDoc(key=key, title=self._title(key), model=model, intro=intro)
        if key and not self.is_shared(key):
            fi = self._field_info(key)
            kind = "list of tables" if _is_list_of_model(fi.annotation) else "table"
            sec.table_field = FieldDoc(
                section=key, name=key.rsplit(".", 1)[-1], anchor=_anchor(key),
                type=", ".join(filter(None, [kind, _constraints(fi.metadata)])), default=_default_text(fi)[0], unit="",
                description=(fi.description or "").strip(), required=fi.is_required(), example="")
        for name, fi in model.model_fields.items():
            if fi.exclude or self._own_table(fi):
                continue
            written = fi.alias or name
            desc = (fi.description or "").strip()
            default, value = _default_text(fi)
            full = f"{key}.{written}" if key else written
            sec.fields.append(FieldDoc(
                section=key, name=written, anchor=_anchor(full),
                type=type_text(fi.annotation, fi.metadata, self.keys),
                default=default, unit=unit_of(written, desc), description=desc,
                required=fi.is_required(), example=self._example(model, key, written, value)))
        self.sections.append(sec)

    def value_for(self, model: type, key: str, written: str, default: Any = None) -> Any:
        """An example value: the hand-picked one, else the example files', else the default."""
        full = f"{key}.{written}" if key else written
        if full in self.examples:
            return self.examples[full]
        if not self.is_shared(key):
            found = [v for d in self.data for v in _lookup(d, [*self._path(key), written])]
            if found:
                return found[0]
        if default is not None and not (isinstance(default, float) and math.isinf(default)):
            return default
        return None

    def instance(self, model: type, key: str, written: str, value: Any) -> dict:
        """A smallest valid table of `model` holding `written = value`: its required fields, then
        optional ones added in order until the model accepts it."""
        from pydantic import ValidationError

        fields = [(fi.alias or n, fi) for n, fi in model.model_fields.items() if not fi.exclude]
        out = {written: value}
        for name, fi in fields:
            if name != written and fi.is_required():
                out[name] = self._example_value(model, key, name, fi)
        for name, fi in [(n, f) for n, f in fields if n not in out]:
            try:
                model.model_validate(out)
                break
            except ValidationError:
                v = self._example_value(model, key, name, fi)
                if v is not None:
                    out[name] = v
        order = [n for n, _ in fields]
        return dict(sorted(out.items(), key=lambda kv: order.index(kv[0])))

    def parent(self, model: type) -> tuple[type, str]:
        """Where an example of a shared table is shown: a field of a file's own table if one
        reaches it, else the first shared table that does."""
        options = self.parents[model]
        return next(((m, f) for m, f in options if not self.is_shared(self.keys[m])), options[0])

    def _example_value(self, model: type, key: str, name: str, fi: Any) -> Any:
        subs = _models_in(fi.annotation)
        if subs:
            sub = subs[0]
            sub_key = self.keys[sub]
            for sname, sfi in sub.model_fields.items():
                v = self._example_value(sub, sub_key, sfi.alias or sname, sfi)
                if v is not None:
                    return self.instance(sub, sub_key, sfi.alias or sname, v)
            return None
        return self.value_for(model, key, name, _default_text(fi)[1])

    def _example(self, model: type, key: str, written: str, default: Any) -> str:
        value = self.value_for(model, key, written, default)
        if value is None:
            return ""
        if not self.is_shared(key):
            head = "" if not key else (f"[[{key}]]\n" if self._is_list(key) else f"[{key}]\n")
            return f"{head}{written} = {_toml_value(value, written)}"
        # A field of a shared table: show the smallest valid table holding it, where a file uses it.
        table, name, m = self.instance(model, key, written, value), written, model
        while self.is_shared(self.keys[m]):
            parent, pname = self.parent(m)
            name = pname
            if self.is_shared(self.keys[parent]):
                table = self.instance(parent, self.keys[parent], pname, table)
            m = parent
        pkey = self.keys[m]
        head = f"[[{pkey}]]" if self._is_list(pkey) else f"[{pkey}]"
        return f"{head}\n{name} = {_toml_value(table)}"


def _field_block(f: FieldDoc) -> list[str]:
    lines = [f"### `{f.name}` {{#{f.anchor}}}", ""]
    if f.description:
        lines += [f.description, ""]
    lines += [_facts(f), ""]
    if f.example:
        lines += ["```toml", f.example, "```", ""]
    return lines


def _facts(f: FieldDoc) -> str:
    facts = [f"**Type:** {f.type}"]
    if f.required:
        facts.append("**Default:** required")
    elif f.default in ("none", "empty", "the table's defaults"):
        facts.append(f"**Default:** {f.default}")
    else:
        facts.append(f"**Default:** `{f.default}`")
    if f.unit:
        facts.append(f"**Unit:** {f.unit}")
    return " · ".join(facts)


def model_page(docs: ModelDocs, title: str, intro: str, example_note: str) -> str:
    lines = [GENERATED_NOTE, f"# {title}", "", intro, "", example_note, ""]
    for sec in docs.sections:
        lines += [f"## {sec.title} {{#{_anchor(sec.key)}}}", ""]
        if sec.table_field is not None:
            if sec.table_field.description:
                lines += [sec.table_field.description, ""]
            lines += [_facts(sec.table_field), ""]
        if sec.intro:
            lines += [" ".join(sec.intro.split()), ""]
        for f in sec.fields:
            lines += _field_block(f)
    return "\n".join(lines)
