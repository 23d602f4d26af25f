"""MkDocs hooks: the reference pages are generated from the code at every build.

- ``reference/scenario/<block>.md``: one page per block of a scenario file, from the pydantic
  schema (:class:`avflow.scenario.schema.Scenario`'s JSON Schema: types, defaults, bounds,
  allowed values, the attribute docstrings);
- ``reference/cli.md``: every command and option, from :func:`avflow.cli.build_parser`;
- the ``<!-- generated: cf-variables -->`` marker of ``outputs.md``: every variable of a run
  file, from :data:`avflow.output.cf.FIELDS` and :data:`avflow.output.cf.SUMMARIES`.

Nothing here is written to ``docs/``: the pages exist only in the built site (``mkdocs
build``), so they cannot go stale. ``tests/test_docs.py`` imports this file to check that
every schema field and every CLI option has its row.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

#: Blocks of a scenario file, in the order of the file; each gets its own page.
BLOCKS = ("name", "terrain", "grid", "release", "rheology", "entrainment", "forest",
          "sources", "structures", "secondary_release", "time", "output", "boundary",
          "physics", "numerics")
#: Top-level scalar fields documented on the "name" page.
TOP_SCALARS = ("name", "description")

CF_MARKER = "<!-- generated: cf-variables -->"
#: Tutorials that land on other branches: in the nav only once their page exists.
OPTIONAL_PAGES = {"Calibration": "calibration.md", "Regional maps": "regional.md"}

_UNIT_WORDS = ("m/s^2", "m/s", "m^3", "kg/m^3", "kPa", "Pa", "degrees", "s", "m", "-")


# ------------------------------------------------------------------------------------------
# Scenario reference
# ------------------------------------------------------------------------------------------


def _schema() -> dict:
    from avflow.scenario.schema import Scenario

    return Scenario.model_json_schema()


def _ref_name(ref: str) -> str:
    return ref.rsplit("/", 1)[-1]


def _units(prop: dict, name: str) -> str:
    """Units as the field's docstring states them: ``(m)``, ``(degrees, ...)``, ``m/s^2.``."""
    text = (prop.get("description") or "").strip()
    for match in re.finditer(r"\(([^()]*)\)", text):
        head = re.split(r"[,;:]", match.group(1))[0].strip()
        if head in _UNIT_WORDS:
            return "1 (dimensionless)" if head == "-" else head
        if head.startswith("m, ") or head == "m along the bed":
            return "m"
    lead = re.match(r"^(m/s\^2|kg/m\^3|m|s|kPa|Pa|degrees)[.,]", text)
    if lead:
        return lead.group(1)
    if name.endswith("_deg"):
        return "degrees"
    if text.lower().startswith("dimensionless"):
        return "1 (dimensionless)"
    return ""


def _bounds(s: dict) -> str:
    parts = []
    if "minimum" in s:
        parts.append(f">= {s['minimum']:g}")
    if "exclusiveMinimum" in s:
        parts.append(f"> {s['exclusiveMinimum']:g}")
    if "maximum" in s:
        parts.append(f"<= {s['maximum']:g}")
    if "exclusiveMaximum" in s:
        parts.append(f"< {s['exclusiveMaximum']:g}")
    if "minLength" in s:
        parts.append(f"at least {s['minLength']} characters")
    if "minItems" in s:
        parts.append(f"at least {s['minItems']} items")
    return ", ".join(parts)


def _type_and_allowed(s: dict) -> tuple[str, str]:
    """A readable type and the allowed values of one JSON Schema node."""
    if "$ref" in s:
        name = _ref_name(s["$ref"])
        return f"[{name}](#{name.lower()})", ""
    if "const" in s:
        return "string", f"`{s['const']}`"
    if "enum" in s:
        return s.get("type", "value"), ", ".join(f"`{v}`" for v in s["enum"])
    if "anyOf" in s or "oneOf" in s:
        kinds, allowed = [], []
        for option in s.get("anyOf") or s.get("oneOf"):
            t, a = _type_and_allowed(option)
            kinds.append(t)
            if a:
                allowed.append(a)
        return " or ".join(dict.fromkeys(kinds)), "; ".join(allowed)
    t = s.get("type", "")
    if t == "array":
        items = s.get("items") or s.get("prefixItems")
        if isinstance(items, list):
            inner = [(_type_and_allowed(i)) for i in items]
            return (f"list of {len(items)} {inner[0][0]}s", "; ".join(a for _, a in inner if a)
                    + ("; " if any(a for _, a in inner) and _bounds(s) else "") + _bounds(s))
        if isinstance(items, dict):
            it, ia = _type_and_allowed(items)
            return f"list of {it}s", "; ".join(x for x in (ia, _bounds(s)) if x)
        return "list", _bounds(s)
    if t == "null":
        return "null", ""
    return t, _bounds(s)


def _rst(text: str) -> str:
    """Docstrings are reStructuredText: their roles and literals as Markdown."""
    text = re.sub(r":(?:func|class|meth|mod|data|attr):`~?(?:[\w.]*\.)?([^`]+)`", r"`\1`",
                  str(text))
    text = text.replace("``", "`")
    # the docstrings' "(README)" pointed at prose that now lives in the user guide
    text = text.replace("(README)", "(user guide, what is solved)")
    return re.sub(r"::$", ":", text, flags=re.M)


def _cell(text: str) -> str:
    return " ".join(_rst(text).split()).replace("|", "\\|")


def _default(prop: dict, required: bool) -> str:
    if required:
        return "**required**"
    if "default" not in prop:
        return ""
    return f"`{json.dumps(prop['default'])}`"


def _describe(name: str, prop: dict) -> str:
    """The field's docstring; the few fields without one say what they are by their name."""
    if prop.get("description"):
        return prop["description"]
    if "const" in prop:
        return f"Chooses this {name}."
    if name in ("x_min", "x_max", "y_min", "y_max"):
        return f"Condition on the {name} side of the map."
    return ""


def _field_rows(model: dict) -> list[str]:
    rows = ["| field | type | default | units | allowed values | description |",
            "|---|---|---|---|---|---|"]
    required = set(model.get("required", ()))
    for name, prop in model.get("properties", {}).items():
        prop = {**prop, "description": _describe(name, prop)}
        typ, allowed = _type_and_allowed(prop)
        rows.append("| `{}` | {} | {} | {} | {} | {} |".format(
            name, _cell(typ), _default(prop, name in required), _units(prop, name),
            _cell(allowed), _cell(prop.get("description", ""))))
    return rows


def _models_under(node: dict, defs: dict) -> list[str]:
    """Every model a field's schema leads to, depth first (a block's sub-blocks)."""
    found: list[str] = []

    def walk(n):
        if isinstance(n, dict):
            if "$ref" in n:
                name = _ref_name(n["$ref"])
                if name not in found:
                    found.append(name)
                    walk(defs[name])
            for key, value in n.items():
                if key != "$ref":
                    walk(value)
        elif isinstance(n, list):
            for value in n:
                walk(value)

    walk(node)
    return found


def scenario_pages() -> dict[str, str]:
    """``reference/scenario/<block>.md`` -> Markdown, one page per block."""
    schema = _schema()
    defs, props = schema["$defs"], schema["properties"]
    required = set(schema.get("required", ()))
    pages = {}
    note = ("*Generated from `avflow/scenario/schema.py` at every docs build; edit the "
            "docstrings there, not this page.*\n")
    top = ["# Top-level fields", "", note, "A scenario file is one YAML mapping with these "
           "keys; the blocks have their own pages.", "",
           "| field | type | default | description |", "|---|---|---|---|"]
    for name, prop in props.items():
        if name in TOP_SCALARS:
            typ, _ = _type_and_allowed(prop)
            top.append(f"| `{name}` | {typ} | {_default(prop, name in required)} | "
                       f"{_cell(prop.get('description', ''))} |")
        else:
            text = prop.get("description") or defs[_ref_name(prop["$ref"])].get("description")
            top.append(f"| `{name}` | block | {'**required**' if name in required else 'optional'}"
                       f" | [{name}]({name}.md): {_cell(text)} |")
    pages["reference/scenario/index.md"] = "\n".join(top) + "\n"
    for block in BLOCKS:
        if block in TOP_SCALARS:
            continue
        prop = props[block]
        lines = [f"# `{block}`", "", note]
        if prop.get("description"):
            lines += [_cell(prop["description"]), ""]
        lines += ["Required." if block in required else
                  "Optional: leave it out (null) for none." if prop.get("default", 0) is None
                  else "Optional: every field has a default.", ""]
        disc = prop.get("discriminator") or next(  # an optional block: in its anyOf
            (o["discriminator"] for o in prop.get("anyOf", ()) if "discriminator" in o), None)
        if disc:
            key = disc["propertyName"]
            kinds = ", ".join(f"[`{k}`](#{_ref_name(v).lower()})"
                              for k, v in disc["mapping"].items())
            lines += [f"Chosen by `{key}`: {kinds}.", ""]
        for model_name in _models_under(prop, defs):
            model = defs[model_name]
            lines += [f"## {model_name}", ""]
            if model.get("description"):
                lines += [_rst(model["description"].strip()), ""]
            if "properties" in model:
                lines += _field_rows(model)
            for option in model.get("anyOf", []):  # boundary: a mapping, or one word
                if "properties" in option:
                    lines += _field_rows(option) + [""]
                elif "enum" in option:
                    lines += ["Or one word for every side: "
                              + ", ".join(f"`{v}`" for v in option["enum"]) + ".", ""]
            lines.append("")
        pages[f"reference/scenario/{block}.md"] = "\n".join(lines)
    return pages


def schema_field_paths() -> set[str]:
    """Every ``Model.field`` of the schema (what the pages must name; tests check it)."""
    defs = _schema()["$defs"]
    return {f"{m}.{f}" for m, d in defs.items()
            for part in [d, *d.get("anyOf", [])] for f in part.get("properties", {})}


# ------------------------------------------------------------------------------------------
# CLI reference
# ------------------------------------------------------------------------------------------


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    rows = ["| argument | value | default | description |", "|---|---|---|---|"]
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        names = ", ".join(f"`{o}`" for o in action.option_strings) or f"`{action.dest}`"
        if action.choices:
            value = " \\| ".join(f"`{c}`" for c in action.choices)
        elif action.nargs == 0:
            value = "flag"
        else:
            value = f"`{action.metavar or action.dest.upper()}`" if action.option_strings \
                else "positional"
        default = action.default
        shown = "" if default in (None, False, [], argparse.SUPPRESS) else f"`{default}`"
        rows.append(f"| {names} | {value} | {shown} | {_cell(action.help or '')} |")
    return rows


def cli_page() -> str:
    from avflow.cli import build_parser

    parser = build_parser()
    lines = ["# Command line", "", "*Generated from `avflow/cli.py` (`build_parser`) at every "
             "docs build.*", "", _cell(parser.description or ""), "",
             "Exit codes: 0 success, 1 a run or member failed, 2 bad input (one line naming "
             "the file and the field), 130 interrupted.", "", "```text",
             parser.format_usage().strip(), "```", ""]
    lines += _option_rows(parser) + [""]
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {c.dest: c.help for c in sub._choices_actions}
    for name, command in sub.choices.items():
        command.prog = f"avflow {name}"
        lines += [f"## avflow {name}", "", _cell(helps.get(name, "")), "", "```text",
                  command.format_usage().strip(), "```", ""]
        lines += _option_rows(command) + [""]
    return "\n".join(lines)


def cli_options() -> set[str]:
    """Every ``command --option`` the parser knows (tests check the page names each)."""
    from avflow.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {f"{name} {opt}" for name, command in sub.choices.items()
            for action in command._actions for opt in action.option_strings
            if opt.startswith("--") and opt != "--help"}


# ------------------------------------------------------------------------------------------
# Output variables
# ------------------------------------------------------------------------------------------

_KINDS = {"field": "snapshot map `(time, [y,] x)`", "flag": "snapshot map `(time, [y,] x)`",
          "reduced": "map over the run `([y,] x)`", "static": "map of the bed `([y,] x)`",
          "series": "time series `(time)`", "summary": "0-d summary"}


def cf_table() -> str:
    from avflow.output.cf import FIELDS, SUMMARIES

    rows = ["| variable | what | units | long_name / standard_name | cell_methods | comment |",
            "|---|---|---|---|---|---|"]
    for name, a in FIELDS.items():
        what = _KINDS.get(a["kind"], a["kind"])
        if a.get("grid_only"):
            what += ", grids only"
        label = a.get("long_name") or f"standard_name `{a.get('standard_name')}`"
        comment = a.get("comment", "")
        if "flag_meanings" in a:
            comment = "; ".join(f"{v} {m}" for v, m in
                                zip(a["flag_values"].tolist(), a["flag_meanings"].split()))
        units = f"`{a['units']}`" if a.get("units") else "flag values"
        rows.append(f"| `{name}` | {what} | {units} | {_cell(label)} | "
                    f"{a.get('cell_methods', '')} | {_cell(comment)} |")
    for name, (units, meaning) in SUMMARIES.items():
        rows.append(f"| `{name}` | {_KINDS['summary']} | `{units}` | {_cell(meaning)} | | |")
    return ("*Generated from `avflow/output/cf.py` (`FIELDS`, `SUMMARIES`) at every docs "
            "build. On profiles volumes are per metre of width (`m2`, energies `J m-1`).*\n\n"
            + "\n".join(rows) + "\n")


# ------------------------------------------------------------------------------------------
# MkDocs events
# ------------------------------------------------------------------------------------------


def generated_pages() -> dict[str, str]:
    pages = scenario_pages()
    pages["reference/cli.md"] = cli_page()
    return pages


def on_config(config):
    """Pages written on other branches join the tutorials' nav once they exist."""
    docs = Path(config["docs_dir"])
    for section in config["nav"] or []:
        if isinstance(section, dict) and "Tutorials" in section:
            for title, page in OPTIONAL_PAGES.items():
                entry = {title: page}
                if (docs / page).is_file() and entry not in section["Tutorials"]:
                    section["Tutorials"].append(entry)
    return config


def on_files(files, config):
    from mkdocs.structure.files import File

    for uri, text in generated_pages().items():
        files.append(File.generated(config, uri, content=text))
    # The workflows' committed figures, shown where they are made (validation, performance)
    root = Path(config["config_file_path"]).parent
    for png in sorted((root / "workflows").rglob("*.png")):
        uri = png.relative_to(root).as_posix()
        files.append(File.generated(config, uri, abs_src_path=str(png)))
    return files


def on_page_markdown(markdown, page, config, files):
    if CF_MARKER in markdown:
        markdown = markdown.replace(CF_MARKER, cf_table())
    return markdown


#: A Sphinx role as mkdocstrings leaves it in the page: ``:class:<code>~a.b.C</code>``.
_ROLE_HTML = re.compile(r":(?:func|class|meth|mod|data|attr|obj|exc):<code>~?(?:[\w.]*\.)?"
                        r"([^<]+)</code>")


def on_page_content(html, page, config, files):
    """The docstrings' Sphinx roles (``:class:`X```) as plain code, not raw text."""
    return _ROLE_HTML.sub(r"<code>\1</code>", html)
