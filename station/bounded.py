"""Reading input with bounded work: files with a size limit, YAML with its alias expansion bounded,
and the input quoted back in error messages cut to a few hundred characters.

YAML's aliases let a few hundred bytes stand for a structure of billions of nodes (each level of
``&a [*b, *b, ...]`` multiplies): PyYAML shares the aliased objects, so loading stays small, but
anything that walks the result (validation, an error message quoting it) does the full expansion.
``load_yaml`` counts the nodes of the document as it would be expanded (each node once, linear in
the text) and refuses a document above ``MAX_YAML_NODES`` before anything is constructed.

Documents are parsed by libyaml (C, several times faster than PyYAML's pure-Python reader).  libyaml's
parser keeps its nesting on a heap stack, but the composer that turns its events into nodes recurses
in C, so a document nested 50 000 deep would crash the process: the events are walked first and a
document nested deeper than ``MAX_YAML_DEPTH`` is refused before it is composed.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

from station.errors import BadInputError

QUOTE_CHARS = 200  # the most of an input an error message quotes
MAX_YAML_NODES = 100_000  # a station configuration has ~300 nodes, a RUN.yaml of 100 steps ~1 000
MAX_YAML_BYTES = 1 << 20  # 1 MiB
MAX_YAML_DEPTH = 100  # a station configuration nests 5 deep, an interchange file 4


def cut(text: str, limit: int = QUOTE_CHARS) -> str:
    """``text`` cut to ``limit`` characters, the full length said."""
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def quote(value: Any, limit: int = QUOTE_CHARS) -> str:
    """``repr(value)`` cut to ``limit`` characters (``cut``); a large structure is not even formatted
    whole."""
    if isinstance(value, list | tuple | dict | set) and len(value) > limit:
        return f"<{type(value).__name__} of {len(value)} items>"
    return cut(repr(value), limit)


def read_text_limited(path: Path, max_bytes: int, what: str, error: type[BadInputError] = BadInputError,
                      *, say_what: bool = False) -> str:
    """The UTF-8 text of ``path``, refused (``error``) when it is larger than ``max_bytes``: its size
    is checked before a byte is read, and at most ``max_bytes + 1`` bytes are ever read (a file that
    grows meanwhile, a device).  ``what`` names the file in the messages (also when it cannot be
    read with ``say_what``)."""
    try:
        with path.open("rb") as f:
            size = _size(f)
            if size is not None and size > max_bytes:
                raise error(f"{path}: {what} of {size} bytes exceeds the limit of {max_bytes} bytes")
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read{' ' + what if say_what else ''}: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise error(f"{path}: {what} exceeds the limit of {max_bytes} bytes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: {what} is not UTF-8 text (byte 0x{data[exc.start]:02x} at position {exc.start})") \
            from None


def _size(f: Any) -> int | None:
    st = os.fstat(f.fileno())
    return st.st_size if stat.S_ISREG(st.st_mode) else None


def _expanded_nodes(root: yaml.Node, limit: int) -> int:
    """Nodes of the document with every alias expanded, counted up to just above ``limit``; each
    distinct node is visited once (its expanded size memoised), so the work is linear in the text."""
    sizes: dict[int, int] = {}
    open_: set[int] = set()  # visited, children not yet summed: met again below itself = a recursive alias
    order: list[tuple[yaml.Node, bool]] = [(root, False)]
    while order:  # post-order without recursion (a deeply nested document must not overflow the stack)
        node, done = order.pop()
        if id(node) in sizes or (not done and id(node) in open_):
            continue
        if isinstance(node, yaml.ScalarNode):
            sizes[id(node)] = 1
            continue
        children = [c for pair in node.value for c in pair] if isinstance(node, yaml.MappingNode) else \
            list(node.value)
        if not done:
            open_.add(id(node))
            order.append((node, True))
            order.extend((c, False) for c in children if id(c) not in sizes and id(c) not in open_)
            continue
        open_.discard(id(node))
        total = 1
        for c in children:
            total += sizes.get(id(c), 1)  # a child still open is a cycle (a recursive alias): 1
            if total > limit:
                break
        sizes[id(node)] = min(total, limit + 1)
    return sizes[id(root)]


def duplicate_keys(root: yaml.Node) -> list[str]:
    """Every key written twice in one mapping of the document (``key 'capacity_N' on lines 12 and
    14``): YAML says a mapping's keys are unique, PyYAML keeps the last silently."""
    out: list[str] = []
    seen_nodes: set[int] = set()
    todo = [root]
    while todo:
        node = todo.pop()
        if id(node) in seen_nodes or isinstance(node, yaml.ScalarNode):
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            keys: dict[tuple[str, str], int] = {}
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.tag != "tag:yaml.org,2002:merge":
                    line = k.start_mark.line + 1
                    first = keys.setdefault((k.tag, k.value), line)
                    if first != line:
                        out.append(f"key {quote(k.value)} on line {first} and again on line {line}")
                todo.extend((k, v))
        else:
            todo.extend(node.value)
    return out


_OPEN = (yaml.MappingStartEvent, yaml.SequenceStartEvent)
_CLOSE = (yaml.MappingEndEvent, yaml.SequenceEndEvent)


def _too_deep(text: str, limit: int = MAX_YAML_DEPTH) -> bool:
    """Whether some collection of ``text`` is nested more than ``limit`` deep, from libyaml's events
    (iterative: no recursion however deep the text; a syntax error is left to the loader to report)."""
    parser = yaml.cyaml.CParser(text)
    depth = 0
    try:
        while (event := parser.get_event()) is not None:
            if isinstance(event, _OPEN):
                depth += 1
                if depth > limit:
                    return True
            elif isinstance(event, _CLOSE):
                depth -= 1
    except yaml.YAMLError:
        return False
    finally:
        parser.dispose()
    return False


def load_yaml(text: str, source: str, error: type[BadInputError] = BadInputError,
              max_nodes: int = MAX_YAML_NODES) -> Any:
    """``yaml.safe_load(text)`` with the document's expanded size bounded (module docstring) and no key
    written twice in one mapping; a malformed document raises ``error`` naming ``source``, its message
    within a few hundred characters."""
    if _too_deep(text):
        raise error(f"{source}: the YAML document is nested more than {MAX_YAML_DEPTH} deep; refused")
    loader = yaml.CSafeLoader(text)  # composes recursively in C: only after the depth was checked
    try:
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            n = _expanded_nodes(node, max_nodes)
            if n > max_nodes:
                raise error(f"{source}: the YAML document expands to more than {max_nodes} nodes (through "
                            "its aliases '*name'); refused")
            dups = duplicate_keys(node)
            if dups:
                raise error(f"{source}: a key written twice (which one counts is not for the station to guess): "
                            f"{cut('; '.join(sorted(dups)), 4 * QUOTE_CHARS)}")
            return loader.construct_document(node)
        except yaml.YAMLError as exc:
            raise error(f"{source}: not valid YAML: {cut(str(exc), 4 * QUOTE_CHARS)}") from None
        except RecursionError:
            raise error(f"{source}: the YAML document is nested too deeply") from None
    finally:
        loader.dispose()
