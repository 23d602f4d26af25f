"""YAML reading with positions, shared by scenario and ensemble files.

PyYAML's safe loader restricted to YAML 1.2's core scalars, and every key and list item
recorded with its (line, column), so that a validation error can name ``file:line:col`` and
the dotted field. Knows nothing of the scenario schema.
"""

from __future__ import annotations

import difflib
import json
import os
import re
import stat
from typing import Any, Mapping

import yaml

from avflow.errors import ScenarioError

# =========================================================================================

_BOOL, _INT, _FLOAT, _TIMESTAMP = (f"tag:yaml.org,2002:{name}"
                                   for name in ("bool", "int", "float", "timestamp"))


class YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader with the scalars of YAML 1.2's core schema.

    PyYAML follows YAML 1.1, where ``1e-3`` is a string (a float needs a dot), ``yes``,
    ``no``, ``on`` and ``off`` are booleans, ``010`` is octal, ``1:30`` is 90 and
    ``2024-01-01`` a date. Here only true/false are booleans, integers are decimal, decimal
    and exponent notations are floats, and everything else stays a string.
    """


YamlLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers
            if tag not in (_BOOL, _INT, _FLOAT, _TIMESTAMP)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
YamlLoader.add_implicit_resolver(
    _BOOL, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
YamlLoader.add_implicit_resolver(  # before floats: a plain integer stays an int
    _INT, re.compile(r"^[-+]?[0-9]+$"), list("-+0123456789"))
YamlLoader.add_implicit_resolver(
    _FLOAT, re.compile(r"""^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?
                          |[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))
YamlLoader.add_constructor(_INT, lambda loader, node: int(loader.construct_scalar(node), 10))

_MERGE = "tag:yaml.org,2002:merge"

#: Values that aliases (``*name``) may add in all, beyond those written in the text. Anchors
#: and aliases are fine for reuse (an ensemble naming one rheology block twice adds a few
#: values); a "billion laughs" file of 300 bytes would expand to 1e9 values and 9 GB. Values
#: written out in full are not counted: their number is bounded by the file's size.
MAX_ALIAS_VALUES = 10_000


#: Largest scenario or ensemble file read (bytes). The longest shipped is under 3 KB; a
#: megabyte is some 20,000 lines of YAML. ``avflow run /dev/zero`` read until memory ran out.
MAX_FILE_BYTES = 1 << 20


def read_text_file(path, what: str, error=ScenarioError) -> str:
    """The UTF-8 text of a scenario or ensemble file, or one ``error`` line saying why not:
    missing, not a regular file (a device, a pipe, a folder), over :data:`MAX_FILE_BYTES`,
    not UTF-8."""
    try:
        mode = os.stat(path).st_mode  # before opening: a named pipe would block the open
        if not stat.S_ISREG(mode) and not (stat.S_ISFIFO(mode) and is_stdin_pipe(path)):
            raise error(f"not a {what} file: "
                        f"{'a folder' if stat.S_ISDIR(mode) else 'not a regular file'}", path)
        with open(path, "rb") as f:  # a pipe too is read to MAX_FILE_BYTES at most
            data = f.read(MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise error(f"{what} file not found", path) from None
    except OSError as err:
        raise error(f"cannot read the {what} file: {err.strerror or err}", path) from None
    if len(data) > MAX_FILE_BYTES:
        raise error(f"the {what} file is over {MAX_FILE_BYTES >> 20} MiB: not a {what} "
                    "file?", path)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise error(f"not a UTF-8 text file ({err.reason})", path) from None


def is_stdin_pipe(path) -> bool:
    """``/dev/stdin`` (or ``/dev/fd/N``) fed by a pipe (``cat s.yaml | avflow run
    /dev/stdin``): a stream that ends, unlike a device or a named pipe nobody writes to."""
    return re.fullmatch(r"pipe:\[\d+\]", os.path.basename(os.path.realpath(path))) is not None


def read_yaml(text: str, path: str | None) -> tuple[Any, dict[tuple, tuple[int, int]]]:
    """Plain Python data from YAML text, and the (line, column) of every key and item.

    Positions are keyed by the path of keys and list indices, e.g. ``("terrain", "slope")``
    or ``("terrain", "extent", "x", 1)``; ``()`` is the top-level node.
    """
    positions: dict[tuple, tuple[int, int]] = {}

    def where(node: yaml.Node) -> tuple[int, int]:
        return node.start_mark.line + 1, node.start_mark.column + 1

    def fail(message: str, node: yaml.Node, keys: tuple = ()) -> ScenarioError:
        return ScenarioError(message, path, dotted(keys), *where(node))

    def scalar(node: yaml.Node, keys: tuple) -> Any:
        try:
            return loader.construct_object(node)
        except (ValueError, yaml.YAMLError) as err:
            raise fail(f"cannot read {node.value!r} as {node.tag}: {err}", node, keys) from None

    built: set[int] = set()  # nodes built once: building one again expands an alias
    inside: set[int] = set()  # collections being built (an alias to one of them is a loop)
    expanded = 0

    def build(node: yaml.Node, keys: tuple) -> Any:
        """Data of ``node``, written at ``keys``; records where its keys and items are."""
        nonlocal expanded
        if id(node) in inside:
            raise fail("an alias refers to a collection that contains it (a recursive "
                       "structure has no finite value)", node, keys)
        if id(node) in built:
            expanded += 1
            if expanded > MAX_ALIAS_VALUES:
                raise fail(f"aliases (*name) expand to more than {MAX_ALIAS_VALUES} values "
                           "(a YAML alias bomb?); write the values out or use fewer aliases",
                           node, keys)
        built.add(id(node))
        if isinstance(node, (yaml.MappingNode, yaml.SequenceNode)):
            inside.add(id(node))
            try:
                return build_collection(node, keys)
            finally:
                inside.discard(id(node))
        return scalar(node, keys)

    def build_collection(node: yaml.Node, keys: tuple) -> Any:
        if isinstance(node, yaml.MappingNode):
            mapping: dict[str, Any] = {}
            for key_node, value_node in node.value:
                if key_node.tag == _MERGE:
                    raise fail("merge keys (<<) are not supported", key_node, keys)
                key = scalar(key_node, keys) if isinstance(key_node, yaml.ScalarNode) else None
                if not isinstance(key, str):
                    raise fail(f"keys must be names, got {show(key)}", key_node, keys)
                if key in mapping:
                    first_line = positions[keys + (key,)][0]
                    raise fail(f"duplicate key (first written at line {first_line})",
                               key_node, keys + (key,))
                positions[keys + (key,)] = where(key_node)  # the key, not its value
                mapping[key] = build(value_node, keys + (key,))
            return mapping
        if isinstance(node, yaml.SequenceNode):
            items = []
            for i, item in enumerate(node.value):
                positions[keys + (i,)] = where(item)
                items.append(build(item, keys + (i,)))
            return items

    loader = None
    try:
        _check_depth(text, path)  # before composing: PyYAML's composer recurses
        loader = YamlLoader(text)  # a control character is refused here already
        root = loader.get_single_node()
        if root is not None:
            positions[()] = where(root)
        data = None if root is None else build(root, ())
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        detail = f" ({err.context})" if err.context else ""
        raise ScenarioError(f"YAML syntax error: {err.problem}{detail}", path, None,
                            *((mark.line + 1, mark.column + 1) if mark else ())) from None
    except yaml.YAMLError as err:
        raise ScenarioError(f"YAML error: {' '.join(str(err).split())}", path) from None
    finally:
        if loader is not None:
            loader.dispose()
    if data is None:
        raise ScenarioError("empty scenario: expected a mapping of fields (name: ..., "
                            "terrain: ..., ...)", path, None, 1, 1)
    if not isinstance(data, dict):
        raise ScenarioError(f"expected a mapping of fields (name: ..., terrain: ..., ...), "
                            f"got {show(data)}", path, None, *positions[()])
    return data, positions


#: Deepest nesting of mappings and lists read (a scenario needs 4; PyYAML and the checks
#: after it recurse, and a file nested a few thousand levels was a RecursionError).
MAX_DEPTH = 64


def _check_depth(text: str, path: str | None) -> None:
    """Refuse YAML nested deeper than :data:`MAX_DEPTH`, from PyYAML's events (its parser
    does not recurse; its composer does)."""
    depth = 0
    for event in yaml.parse(text, Loader=YamlLoader):
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > MAX_DEPTH:
                mark = event.start_mark
                raise ScenarioError(f"nested more than {MAX_DEPTH} levels deep (mappings and "
                                    "lists): not a file avflow reads", path, None,
                                    mark.line + 1, mark.column + 1)
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1


def dotted(keys: tuple) -> str | None:
    return ".".join(str(k) for k in keys) or None


def dotted_parts(field: str | None) -> tuple:
    """``"terrain.extent.x.1"`` -> ``("terrain", "extent", "x", 1)`` (list items by index)."""
    if not field:
        return ()
    return tuple(int(p) if p.isdigit() else p for p in field.split("."))


def position(positions: Mapping[tuple, tuple[int, int]], keys: tuple) -> tuple[int, int] | None:
    """Position of ``keys``, or of its closest parent that was written (a missing field)."""
    for n in range(len(keys), -1, -1):
        if keys[:n] in positions:
            return positions[keys[:n]]
    return None



def show(value: Any) -> str:
    """A value as the user wrote it in YAML (strings quoted), for 'got ...' in messages."""
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, (bool, type(None), list, dict, tuple)):
        text = json.dumps(value, default=str)
        return text if len(text) <= 60 else text[:57] + "..."
    return repr(value)


def did_you_mean(word: str, choices: Any) -> str:
    close = difflib.get_close_matches(str(word), list(choices), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""
