"""calib.io.configfile: the project's one YAML loader is bounded (aliases, nesting, expanded
size, bytes); tests/cli/test_inputs_cannot_lie.py checks that every YAML file goes through it."""

from __future__ import annotations

import re
import time

import pytest

from calib.io.configfile import MAX_YAML_BYTES, ConfigError, load_yaml
from calib.io.site import load_site


def billion_laughs(levels: int = 9, fan: int = 9) -> str:
    """Each level an anchored list of ``fan`` aliases of the one before: fan**levels values."""
    text = 'a: &a ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n'
    for i in range(1, levels + 1):
        name, prev = chr(ord("a") + i), chr(ord("a") + i - 1)
        text += f"{name}: &{name} [{', '.join([f'*{prev}'] * fan)}]\n"
    return text


def test_a_billion_laughs_site_yaml_fails_within_a_second_while_a_few_aliases_work(tmp_path):
    root = load_yaml("a: &a [1, 2]\nb: [*a, *a]\n", source="cfg.yaml")
    assert root.plain() == {"a": [1, 2], "b": [[1, 2], [1, 2]]}
    path = tmp_path / "site.yaml"
    path.write_text(billion_laughs())
    t0 = time.thread_time()  # CPU time of this thread: the loader's work, not the machine's load
    with pytest.raises(
        ConfigError, match=r"site\.yaml: more than 100,000 values once its aliases are expanded"
    ):
        load_site(path)
    assert time.thread_time() - t0 < 1.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (billion_laughs(levels=3, fan=40), r"cfg\.yaml:4:88: more than 100 aliases \(\*name\)"),
        ("[" * 100 + "]" * 100, r"cfg\.yaml:1:65: nested more than 64 levels deep"),
        ("a: &a [*a]\n", r"cfg\.yaml:1:4: a recursive alias \(a value contains itself\)"),
        (
            "? [1, 2]\n: 3\n",
            r"cfg\.yaml:1:3: <top level>: a mapping key must be a plain value \(a name\), not a list",
        ),
        (
            "a: &a [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]\n"
            "b: [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[*a]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]\n",
            r"nested more than 64 levels deep once its aliases are expanded",
        ),
    ],
)
def test_aliases_nesting_and_keys_are_bounded(text, message):
    t0 = time.thread_time()  # CPU time of this thread: the loader's work, not the machine's load
    with pytest.raises(ConfigError, match=message):
        load_yaml(text, source="cfg.yaml")
    assert time.thread_time() - t0 < 1.0


def test_size_directory_and_unreadable_files_are_one_line(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_text("x: " + "y" * MAX_YAML_BYTES + "\n")
    with pytest.raises(ConfigError, match=r"big\.yaml: larger than 1 MiB, expected a configuration file"):
        load_yaml(big)
    with pytest.raises(ConfigError, match=r"cfg: longer than 1 MiB"):
        load_yaml("x" * (MAX_YAML_BYTES + 1), source="cfg")
    with pytest.raises(
        ConfigError, match=rf"{re.escape(str(tmp_path))}: is a directory, expected a YAML file"
    ):
        load_site(tmp_path)
