"""YAML configuration with located values, for errors that name the file, line, key and value.

    root = load_yaml(path)
    cfg = root.mapping(required={"standoff_m"}, optional={"vessel"})
    standoff_m = cfg["standoff_m"].number(minimum=0.0)

Every accessor raises :class:`ConfigError` whose message reads
``site.yaml:12:3: targets[0].size_m: got [1.2], expected 2 numbers``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib.core.errors import ConfigError  # the one ConfigError (re-exported): every accessor raises it


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

    def integer(self, minimum: int | None = None) -> int:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail("an integer")
        if minimum is not None and v < minimum:
            raise self.fail(f"an integer ≥ {minimum}")
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


def _to_node(node: yaml.Node, path: str, source: str) -> Node:
    line, col = node.start_mark.line + 1, node.start_mark.column + 1
    if isinstance(node, yaml.MappingNode):
        out: dict[str, Node] = {}
        for k, v in node.value:
            key = yaml.safe_load(yaml.serialize(k)) if not isinstance(k, yaml.ScalarNode) else k.value
            key = str(key)
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
    value = yaml.safe_load(yaml.serialize(node))
    return Node(value, path, source, line, col)


def load_yaml(path_or_text: str | Path, source: str | None = None) -> Node:
    """Load YAML from a file path (or from text when ``source`` names it) into located Nodes."""
    if source is None:
        path = Path(path_or_text)
        source = str(path)
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise ConfigError(f"{source}: file not found") from None
        except UnicodeDecodeError as e:
            raise ConfigError(f"{source}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    else:
        text = str(path_or_text)
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{source}:{mark.line + 1}:{mark.column + 1}" if mark else source
        raise ConfigError(f"{where}: not valid YAML: {getattr(e, 'problem', e)}") from None
    if root is None:
        return Node({}, "", source, 1, 1)
    return _to_node(root, "", source)
