"""Reading YAML configuration files (ASL ``sensor.yaml``, Kalibr ``imu.yaml`` and camchains, a ROS 2
bag's ``metadata.yaml``) with PyYAML, keeping the line of every key and list item for error
messages.

OpenCV writes ``%YAML:1.0`` as its first line, which is not YAML (PyYAML rejects it): that line is
skipped (line numbers stay those of the file). OpenCV's ``!!opencv-matrix`` tag reads as a plain
mapping. Duplicate keys, which YAML forbids and PyYAML would silently resolve to the last, are an
error naming both lines. Every error is a :class:`datasets.errors.DataError` naming the file, the
line and the key path (``T_BS.data``).

Bounds: the file is read within the YAML size limit of :func:`datasets.errors.read_source`. Aliases
(``*name``, a repeat of an anchored ``&name`` node) are allowed, but the document they expand to
may hold at most :data:`MAX_NODES` nodes, counted with every alias expanded, and nest at most
:data:`MAX_DEPTH` levels: nested aliases make a few hundred bytes stand for billions of nodes ("a
billion laughs"), and such a document is refused before anything walks it. Parsing stops at the
same count, so that a large flat document costs no more than a few seconds either.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import yaml

from datasets.errors import DataError, read_lines

#: The most nodes (mappings, lists and scalars, keys included) a document may expand to, aliases
#: expanded: a camchain of ten cameras has some 500, a ROS 2 bag's metadata of a thousand
#: topics some 30 000.
MAX_NODES = 100_000
#: The deepest nesting of mappings and lists a document may have (a calibration file has 3-4).
MAX_DEPTH = 64


def _too_many(path, line: int | None, key: str | None) -> DataError:
    return DataError(path, line, key, f"a document of more than {MAX_NODES} nodes once its aliases are expanded",
                     "a calibration file of some hundreds (an alias, *name, stands for its anchor's whole value, "
                     "and nested ones multiply)", whole=True)


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader of the file ``path`` that also reads OpenCV's ``!!opencv-matrix`` as a
    mapping, and stops composing past :data:`MAX_NODES` nodes (aliases counted once: they are
    expanded later), with the :class:`DataError` of a document too large."""

    def __init__(self, text: str, path: Path):
        super().__init__(text)
        self.path, self.composed = path, 0

    def compose_node(self, parent, index):
        self.composed += 1
        if self.composed > MAX_NODES:
            raise _too_many(self.path, self.peek_event().start_mark.line + 1, None)
        return super().compose_node(parent, index)


_Loader.add_constructor("tag:yaml.org,2002:opencv-matrix",
                        lambda loader, node: loader.construct_mapping(node, deep=True))


def dotted(keys: tuple) -> str:
    """A key path as text: ``("T_BS", "data", 3)`` -> ``T_BS.data[3]``."""
    text = ""
    for key in keys:
        text += f"[{key}]" if isinstance(key, int) else (f".{key}" if text else str(key))
    return text


@dataclass(frozen=True)
class YamlDocument:
    """A YAML file read: ``data`` (dicts, lists, scalars), ``lines`` (key path -> 1-based line of
    the key or list item), ``n_lines`` and ``path``."""

    path: Path
    data: object
    lines: dict
    n_lines: int

    def line(self, keys: tuple) -> int | None:
        """The line of ``keys``, or of its nearest enclosing key that has one."""
        while keys and keys not in self.lines:
            keys = keys[:-1]
        return self.lines.get(keys)

    def error(self, keys: tuple, found, expected: str, line: int | None = None) -> DataError:
        """A :class:`DataError` about ``keys``, at its line unless ``line`` is given."""
        return DataError(self.path, line or self.line(keys), dotted(keys) or None, found, expected)

    def get(self, keys: tuple):
        """The value at ``keys`` (a :class:`DataError` naming the first key missing)."""
        value = self.data
        for depth, key in enumerate(keys):
            if isinstance(value, list) and isinstance(key, int) and 0 <= key < len(value):
                value = value[key]
                continue
            if not isinstance(value, dict) or key not in value:
                raise self.error(keys[: depth + 1], "no such key", f"a key '{key}'" +
                                 (f" in {dotted(keys[:depth])}" if depth else ""))
            value = value[key]
        return value

    def number(self, keys: tuple, minimum: float | None = None) -> float:
        """The finite number at ``keys`` (>= ``minimum`` if given)."""
        value = self.get(keys)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(keys, value, "a number")
        if not math.isfinite(value):
            raise self.error(keys, value, "a finite number")
        if minimum is not None and value < minimum:
            raise self.error(keys, value, f"a number >= {minimum:g}")
        return float(value)


class _Walk:
    """One walk over a composed document (aliases expanded): the line of every key and list item,
    duplicate keys refused, and the nodes counted against :data:`MAX_NODES` and the depth against
    :data:`MAX_DEPTH` as they are reached."""

    def __init__(self, path: Path):
        self.path, self.lines, self.nodes = path, {}, 0

    def node(self, node, keys: tuple) -> None:
        self.nodes += 1
        if self.nodes > MAX_NODES:  # named at the top-level key whose value expands past the bound
            raise _too_many(self.path, self.lines.get(keys[:1]), dotted(keys[:1]) or None)
        if len(keys) > MAX_DEPTH:
            raise DataError(self.path, self.lines.get(keys[:1]), dotted(keys[:1]) or None,
                            f"mappings or lists nested deeper than {MAX_DEPTH} levels",
                            f"at most {MAX_DEPTH} (a calibration file has a few)", whole=True)
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:
                self.nodes += 1
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else key_node.start_mark.line
                here = keys + (key,)
                line = key_node.start_mark.line + 1
                if here in self.lines:
                    raise DataError(self.path, line, dotted(here),
                                    f"a second '{key}:' (the first at line {self.lines[here]})", "each key once")
                self.lines[here] = line
                self.node(value_node, here)
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.lines[keys + (index,)] = item.start_mark.line + 1
                self.node(item, keys + (index,))


def read_yaml(path) -> YamlDocument:
    """Read a YAML file (see the module docstring)."""
    path = Path(path)
    text_lines = read_lines(path, "yaml")
    if text_lines and text_lines[0].startswith("%YAML:"):
        text_lines[0] = ""
    loader = _Loader("\n".join(text_lines) + "\n", path)
    walk = _Walk(path)
    try:
        node = loader.get_single_node()
        if node is not None:
            walk.node(node, ())
        data = None if node is None else loader.construct_document(node)
    except RecursionError:  # PyYAML composes and constructs recursively: nesting beyond Python's stack
        raise DataError(path, None, None, "mappings or lists nested deeper than the reader can follow",
                        f"at most {MAX_DEPTH} levels", whole=True) from None
    except yaml.MarkedYAMLError as error:
        mark = error.problem_mark or error.context_mark
        problem = " ".join(part for part in (error.context, error.problem) if part)
        raise DataError(path, None if mark is None else mark.line + 1, None, problem, "valid YAML") from None
    except yaml.YAMLError as error:
        raise DataError(path, None, None, str(error), "valid YAML") from None
    except DataError:  # the walk's own (a ValueError too)
        raise
    except ValueError as error:  # a value PyYAML cannot construct: an integer of more than 4300 digits
        raise DataError(path, None, None, str(error).split(";")[0], "valid YAML of values Python takes",
                        whole=True) from None
    finally:
        loader.dispose()
    return YamlDocument(path, data, walk.lines, len(text_lines))
