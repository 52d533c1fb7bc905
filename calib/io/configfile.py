"""YAML configuration with located values, for errors that name the file, line, key and value.

    root = load_yaml(path)
    cfg = root.mapping(required={"standoff_m"}, optional={"vessel"})
    standoff_m = cfg["standoff_m"].number(minimum=0.0)

Every accessor raises :class:`ConfigError` whose message reads
``site.yaml:12:3: targets[0].size_m: got [1.2], expected 2 numbers``.

This is the project's one YAML loader: every configuration file (site, vessel, scenario,
faults, ``--set`` values) is read here, and nowhere else calls ``yaml.load``/``yaml.compose``.
It is bounded so that a hostile or broken file fails at once with a clear message instead of
eating the machine: at most :data:`MAX_YAML_BYTES` of text, :data:`MAX_YAML_ALIASES` alias
references, :data:`MAX_YAML_DEPTH` levels of nesting and :data:`MAX_YAML_VALUES` values once
aliases are expanded (a "billion laughs" document is refused before anything is expanded);
recursive aliases and non-scalar mapping keys are refused. A path that is a directory, or
cannot be read, is one line naming it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib.core.errors import (
    ConfigError,  # the one ConfigError (re-exported): every accessor raises it
    read_file,
)

#: Largest configuration text read (bytes): configs are a few kB; a larger file is not one.
MAX_YAML_BYTES = 1 << 20
#: Most alias references (``*name``) in one document.
MAX_YAML_ALIASES = 100
#: Deepest nesting of mappings and sequences.
MAX_YAML_DEPTH = 64
#: Most values (mappings, sequences, scalars) once every alias is expanded.
MAX_YAML_VALUES = 100_000


@dataclass(frozen=True)
class Node:
    value: Any  # python scalar, list[Node] or dict[str, Node]
    path: str  # "targets[0].size_m"
    source: str  # file name
    line: int  # 1-based
    column: int  # 1-based

    # -- errors -----------------------------------------------------------------------------

    def where(self) -> str:
        return f"{self.source}:{self.line}:{self.column}: {self.path or '<top level>'}"

    def fail(self, expected: str) -> ConfigError:
        return ConfigError(f"{self.where()}: got {self.plain()!r}, expected {expected}")

    def plain(self) -> Any:
        """The value with nested Nodes unwrapped."""
        if isinstance(self.value, dict):
            return {k: v.plain() for k, v in self.value.items()}
        if isinstance(self.value, list):
            return [v.plain() for v in self.value]
        return self.value

    # -- typed accessors --------------------------------------------------------------------

    def mapping(self, required: Iterable[str] = (), optional: Iterable[str] = ()) -> dict[str, Node]:
        if not isinstance(self.value, dict):
            raise self.fail("a mapping")
        required, optional = set(required), set(optional)
        unknown = sorted(set(self.value) - required - optional)
        if unknown:
            node = self.value[unknown[0]]
            allowed = ", ".join(sorted(required | optional))
            raise ConfigError(
                f"{node.where()}: unknown key {unknown[0]!r}"
                + (f" (and {len(unknown) - 1} more)" if len(unknown) > 1 else "")
                + f"; allowed keys here: {allowed}"
            )
        missing = sorted(required - set(self.value))
        if missing:
            raise ConfigError(f"{self.where()}: missing required key {missing[0]!r}")
        return dict(self.value)

    def sequence(self, min_len: int = 0) -> list[Node]:
        if self.value is None and min_len == 0:
            return []
        if not isinstance(self.value, list) or len(self.value) < min_len:
            raise self.fail(f"a list of at least {min_len} item(s)" if min_len else "a list")
        return list(self.value)

    def number(
        self, minimum: float | None = None, maximum: float | None = None, exclusive_minimum: bool = False
    ) -> float:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail("a finite number")
        if minimum is not None and (v <= minimum if exclusive_minimum else v < minimum):
            raise self.fail(f"a number {'>' if exclusive_minimum else '≥'} {minimum:g}")
        if maximum is not None and v > maximum:
            raise self.fail(f"a number ≤ {maximum:g}")
        return float(v)

    def integer(self, minimum: int | None = None, maximum: int | None = None) -> int:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail("an integer")
        if minimum is not None and v < minimum:
            raise self.fail(f"an integer ≥ {minimum}")
        if maximum is not None and v > maximum:
            raise self.fail(f"an integer ≤ {maximum}")
        return int(v)

    def string(self, choices: Iterable[str] | None = None) -> str:
        v = self.value
        if not isinstance(v, str) or not v:
            raise self.fail("a non-empty string")
        if choices is not None and v not in set(choices):
            raise self.fail("one of " + ", ".join(sorted(choices)))
        return v

    def boolean(self) -> bool:
        if not isinstance(self.value, bool):
            raise self.fail("true or false")
        return self.value

    def vector(self, n: int, minimum: float | None = None) -> np.ndarray:
        items = self.value
        if not isinstance(items, list) or len(items) != n:
            raise self.fail(f"a list of {n} numbers")
        return np.array([it.number(minimum=minimum) for it in items])


def _where(source: str, mark) -> str:
    return f"{source}:{mark.line + 1}:{mark.column + 1}" if mark is not None else source


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe composer, counting alias references and nesting as it goes."""

    def __init__(self, stream: str, source: str):
        super().__init__(stream)
        self.source = source
        self.n_aliases = 0
        self.depth = 0

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            self.n_aliases += 1
            if self.n_aliases > MAX_YAML_ALIASES:
                mark = self.peek_event().start_mark
                raise ConfigError(
                    f"{_where(self.source, mark)}: more than {MAX_YAML_ALIASES} aliases (*name); "
                    f"a configuration file needs far fewer: write the values out"
                )
        self.depth += 1
        try:
            if self.depth > MAX_YAML_DEPTH:
                mark = self.peek_event().start_mark
                raise ConfigError(
                    f"{_where(self.source, mark)}: nested more than {MAX_YAML_DEPTH} levels deep"
                )
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def _expanded_size(root: yaml.Node, source: str) -> int:
    """How many values ``root`` holds once its aliases are expanded (a shared node counted once
    per reference), computed without expanding; refuses a node that contains itself and an
    expansion nested deeper than :data:`MAX_YAML_DEPTH`."""
    memo: dict[int, tuple[int, int]] = {}  # id(node) -> (values, depth) of its expansion
    active: set[int] = set()

    def walk(node: yaml.Node, level: int) -> tuple[int, int]:
        key = id(node)
        if key in active:
            raise ConfigError(
                f"{_where(source, node.start_mark)}: a recursive alias (a value contains itself)"
            )
        if key not in memo:
            if level > MAX_YAML_DEPTH:
                raise ConfigError(
                    f"{_where(source, node.start_mark)}: nested more than {MAX_YAML_DEPTH} levels "
                    f"deep once its aliases are expanded"
                )
            active.add(key)
            children: list[yaml.Node] = []
            if isinstance(node, yaml.MappingNode):
                children = [c for pair in node.value for c in pair]
            elif isinstance(node, yaml.SequenceNode):
                children = list(node.value)
            n, depth = 1, 0
            for c in children:
                cn, cd = walk(c, level + 1)
                n, depth = min(n + cn, MAX_YAML_VALUES + 1), max(depth, cd + 1)
            active.discard(key)
            memo[key] = (n, depth)
        n, depth = memo[key]
        if level + depth > MAX_YAML_DEPTH:
            raise ConfigError(
                f"{_where(source, node.start_mark)}: nested more than {MAX_YAML_DEPTH} levels deep "
                f"once its aliases are expanded"
            )
        return n, depth

    return walk(root, 0)[0]


def _to_node(node: yaml.Node, path: str, source: str) -> Node:
    line, col = node.start_mark.line + 1, node.start_mark.column + 1
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Node] = {}
        for k, v in node.value:
            if not isinstance(k, yaml.ScalarNode):
                raise ConfigError(
                    f"{_where(source, k.start_mark)}: {path or '<top level>'}: a mapping key must be "
                    f"a plain value (a name), not a {'list' if isinstance(k, yaml.SequenceNode) else 'mapping'}"
                )
            key = str(k.value)
            child_path = f"{path}.{key}" if path else key
            if key in out:
                raise ConfigError(
                    f"{source}:{k.start_mark.line + 1}:{k.start_mark.column + 1}: {child_path}: duplicate key"
                )
            out[key] = _to_node(v, child_path, source)
        return Node(out, path, source, line, col)
    if isinstance(node, yaml.SequenceNode):
        return Node(
            [_to_node(v, f"{path}[{i}]", source) for i, v in enumerate(node.value)], path, source, line, col
        )
    # the tag was resolved when the node was composed (int, float, bool, null, str, …); an empty
    # value (``key:`` with nothing after it) is null, as in yaml.safe_load
    value = yaml.constructor.SafeConstructor().construct_object(node, deep=True)
    return Node(value, path, source, line, col)


def _read_text(path: Path) -> str:
    source = str(path)
    raw = read_file(path, ConfigError, expected="a YAML file", max_bytes=MAX_YAML_BYTES)
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(
            f"{source}: larger than {MAX_YAML_BYTES >> 20} MiB, expected a configuration file (a few kB)"
        )
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"{source}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def load_yaml(path_or_text: str | Path, source: str | None = None) -> Node:
    """Load YAML from a file path (or from text when ``source`` names it) into located Nodes,
    within the bounds of the module docstring."""
    if source is None:
        path = Path(path_or_text)
        source = str(path)
        text = _read_text(path)
    else:
        text = str(path_or_text)
        if len(text) > MAX_YAML_BYTES:
            raise ConfigError(f"{source}: longer than {MAX_YAML_BYTES >> 20} MiB, expected a configuration")
    loader = _BoundedLoader(text, source)
    try:
        root = loader.get_single_node()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        raise ConfigError(f"{_where(source, mark)}: not valid YAML: {getattr(e, 'problem', e)}") from None
    finally:
        loader.dispose()
    if root is None:
        return Node({}, "", source, 1, 1)
    n = _expanded_size(root, source)
    if n > MAX_YAML_VALUES:
        raise ConfigError(
            f"{source}: more than {MAX_YAML_VALUES:,} values once its aliases are expanded "
            f"(aliases nested in aliases, a 'billion laughs'?): refused"
        )
    return _to_node(root, "", source)
