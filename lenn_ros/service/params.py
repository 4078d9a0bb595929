"""Which ``ros__parameters`` a ROS 2 params file gives a node: rcl's matching rules, written once.

The identifier node warns about a ``--params-file`` that addresses no section to it
(:func:`unmatched_params_files`: rclpy would apply it to no node and say nothing), and
``evaluate``, ``fit``, ``replay`` and ``load_model`` read a params file for a node by the same
rules (:func:`read_params_files`, through :mod:`lenn_ros.service.building`), so a file means
the same parameters offline as live.
What the values mean is :mod:`lenn_ros.config`'s business; here only which of them apply.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lenn_ros.config import ConfigError


def read_params_file(path: str | Path, node: str = "/identifier") -> dict[str, Any]:
    """The ``ros__parameters`` a ROS 2 params file gives the node ``node``, by rcl's rules.

    ``node`` is the fully qualified name (``/robot1/identifier``; a bare name is in the
    root namespace). See :func:`read_params_files`: one file is the case of one.
    """
    return read_params_files([path], node)


def read_params_files(paths: list[str | Path] | tuple[str | Path, ...], node: str = "/identifier") -> dict[str, Any]:
    """The parameters rcl gives ``node`` from these files (``--params-file`` after ``--params-file``).

    rcl's rules, as rclpy applies them (checked against rclpy in test_params_keys.py):
    every section whose key matches the node (:func:`node_key_matches`: ``/**``,
    ``/**/identifier``, ``/robot1/*``, ``identifier`` = the root namespace's) applies, in
    the order the keys first appear over the files, a later one overriding an earlier one
    name by name; a key repeated (in the file or a later file) is merged into its first
    place. No "most specific wins": ``/**/identifier`` above ``/**`` is overridden by it.
    ``/robot1/identifier`` and ``/robot2/identifier`` are two nodes, never merged.
    """
    name = "/" + str(node).strip().lstrip("/")
    sections: dict[str, dict[str, Any]] = {}  # key as written -> its parameters, in first-appearance order
    for path in paths:
        for key, parameters in _params_sections(Path(path)).items():
            sections.setdefault(key, {}).update(parameters)
    matched = [key for key in sections if node_key_matches(key, name)]
    if not matched:
        shown = ", ".join(sections) or "none"
        files = ", ".join(str(path) for path in paths)
        raise ConfigError(
            f"params file {files} has no section for the node {name} (its keys: {shown}): name a section '/**:' "
            f"(any node), '/**/{name.rsplit('/', 1)[-1]}:' or '{name}:', each with 'ros__parameters:'"
        )
    merged: dict[str, Any] = {}
    for key in matched:
        merged.update(sections[key])
    return merged


def _params_sections(path: Path) -> dict[str, dict[str, Any]]:
    """A params file's sections: key -> its flattened ``ros__parameters`` (a file ROS would refuse is an error)."""
    try:
        document = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"params file {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"params file {path} is a directory; pass the .yaml file in it") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"params file {path} is not valid YAML: {str(error).splitlines()[0]}") from None
    if not isinstance(document, dict):
        raise ConfigError(f"params file {path} must map node names to {{ros__parameters: ...}}")
    sections = {}
    for key, section in document.items():
        if isinstance(section, dict) and isinstance(section.get("ros__parameters"), dict):
            sections[str(key).strip()] = _flatten(section["ros__parameters"])
    return sections


def node_key_matches(key: str, fully_qualified_name: str) -> bool:
    """Whether a params-file key addresses a node, by rcl's rules: the one matcher of the package.

    ``*`` stands for one name token, ``**`` for any number of them (none included); a
    key without a leading ``/`` is taken from the root namespace.
    """
    pattern = [token for token in str(key).strip().split("/") if token]
    name = [token for token in fully_qualified_name.split("/") if token]

    def match(p: int, n: int) -> bool:
        if p == len(pattern):
            return n == len(name)
        if pattern[p] == "**":
            return any(match(p + 1, rest) for rest in range(n, len(name) + 1))
        return n < len(name) and pattern[p] in ("*", name[n]) and match(p + 1, n + 1)

    return match(0, 0)


def params_files(argv: list[str]) -> list[str]:
    """The ``--params-file`` paths in a command line, in order."""
    return [argv[i + 1] for i, argument in enumerate(argv[:-1]) if argument == "--params-file"]


def unmatched_params_files(argv: list[str], fully_qualified_name: str) -> list[tuple[str, list[str]]]:
    """The ``--params-file`` files in ``argv`` with no section for this node, and their keys.

    rclpy applies such a file to no node and says nothing: the node would run on its
    defaults while the user believes their file is in force.
    """
    unmatched = []
    for path in params_files(argv):
        try:
            keys = list(_params_sections(Path(path)))
        except ConfigError:
            continue  # rclpy itself refuses a file it cannot read, with its own message
        if not any(node_key_matches(key, fully_qualified_name) for key in keys):
            unmatched.append((path, keys))
    return unmatched


def _flatten(parameters: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested YAML maps are dotted names in ROS 2 (``qos_overrides: {/u: ...}``)."""
    flat: dict[str, Any] = {}
    for name, value in parameters.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{name}."))
        else:
            flat[f"{prefix}{name}"] = value
    return flat
