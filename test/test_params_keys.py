"""Which params-file sections address a node: rcl's wildcard rules, and files that address none."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from lenn_ros.config import ConfigError
from lenn_ros.service.params import node_key_matches, read_params_file, read_params_files, unmatched_params_files


@pytest.mark.parametrize(
    ("key", "name", "expected"),
    [
        ("/**", "/identifier", True),
        ("/**", "/robot1/arm/ident3", True),
        ("/**/identifier", "/identifier", True),  # ** stands for no token too
        ("/**/identifier", "/robot1/identifier", True),
        ("/**/identifier", "/robot1/ident3", False),
        ("identifier", "/identifier", True),  # no leading slash: the root namespace
        ("identifier", "/id3/identifier", False),
        ("/id3/identifier", "/id3/identifier", True),
        ("/*/identifier", "/id3/identifier", True),
        ("/*/identifier", "/a/b/identifier", False),
        ("/**/arm/*", "/robot/arm/ident3", True),
    ],
)
def test_node_key_matches_like_rcl(key: str, name: str, expected: bool) -> None:
    assert node_key_matches(key, name) is expected


def test_a_file_with_no_section_for_the_node_is_found(tmp_path: Path) -> None:
    shipped = tmp_path / "example3.yaml"
    shipped.write_text(yaml.safe_dump({"/**/identifier": {"ros__parameters": {"example": 3}}}))
    anything = tmp_path / "any.yaml"
    anything.write_text(yaml.safe_dump({"/**": {"ros__parameters": {"example": 3}}}))
    argv = ["identifier", "--ros-args", "--params-file", str(shipped), "--params-file", str(anything)]
    assert unmatched_params_files(argv, "/identifier") == []
    assert unmatched_params_files(argv, "/id3/ident3") == [(str(shipped), ["/**/identifier"])]


# -- one matcher for every reader of params files: read_params_file(s) by rcl's rules -------------
FLEET = {
    "/**": {"ros__parameters": {"alpha": 0.1, "order": 3}},
    "/robot1/identifier": {"ros__parameters": {"alpha": 0.2}},
    "/robot2/identifier": {"ros__parameters": {"alpha": 0.3, "order": 5}},
    "/*/ident3": {"ros__parameters": {"order": 7}},
    "/**/identifier": {"ros__parameters": {"u_lags": 2}},
}


def write(tmp_path: Path, document: dict, name: str = "params.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


@pytest.mark.parametrize(
    ("node", "expected"),
    [
        ("/robot1/identifier", {"alpha": 0.2, "order": 3, "u_lags": 2}),  # never robot2's section
        ("/robot2/identifier", {"alpha": 0.3, "order": 5, "u_lags": 2}),
        ("/identifier", {"alpha": 0.1, "order": 3, "u_lags": 2}),  # /**/identifier: ** is no token too
        ("/robot3/ident3", {"alpha": 0.1, "order": 7}),  # * is one token
        ("/a/b/ident3", {"alpha": 0.1, "order": 3}),  # ... and only one
        ("/anything/else", {"alpha": 0.1, "order": 3}),  # /** alone
    ],
)
def test_sections_are_picked_by_the_whole_name_not_the_last_token(tmp_path: Path, node: str, expected: dict) -> None:
    """On main, ``evaluate --params`` matched by the last token: both robots' sections merged into each."""
    assert read_params_file(write(tmp_path, FLEET), node) == expected


def test_a_later_section_overrides_an_earlier_one_and_a_repeated_key_keeps_its_place(tmp_path: Path) -> None:
    """rcl's order, not "most specific wins": ``/**`` after ``/**/identifier`` overrides it."""
    first = write(tmp_path, {"/**/identifier": {"ros__parameters": {"alpha": 2.0}}, "/**": {"ros__parameters": {
        "alpha": 1.0, "beta": 0.1}}}, "first.yaml")  # fmt: skip
    assert read_params_file(first) == {"alpha": 1.0, "beta": 0.1}
    second = write(tmp_path, {"/**/identifier": {"ros__parameters": {"beta": 0.9}}}, "second.yaml")
    # the second file's /**/identifier merges into the first place of that key: /** still comes after it
    assert read_params_files([first, second]) == {"alpha": 1.0, "beta": 0.1}


def test_a_file_without_a_section_for_the_node_is_one_line_naming_its_keys(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"no section for the node /robot3/identifier \(its keys: /robot1/id"):
        read_params_file(write(tmp_path, {"/robot1/identifier": {"ros__parameters": {"alpha": 0.2}}}),
                         "/robot3/identifier")  # fmt: skip


DOCUMENTS = [
    FLEET,
    {"/**/identifier": {"ros__parameters": {"alpha": 2.0}}, "/**": {"ros__parameters": {"alpha": 1.0, "beta": 0.1}}},
    {"identifier": {"ros__parameters": {"alpha": 1.0}}, "/**": {"ros__parameters": {"alpha": 2.0}},
     "/identifier": {"ros__parameters": {"alpha": 3.0}}},
    {"/robot1/**": {"ros__parameters": {"alpha": 1.0}}, "/**/robot1/*": {"ros__parameters": {"beta": 0.2}}},
    {"/*/identifier": {"ros__parameters": {"alpha": 5.0}},
     "/robot1/*": {"ros__parameters": {"alpha": 6.0, "beta": 0.1}},
     "/robot1/identifier": {"ros__parameters": {"qos_overrides": {"/u": {"subscription": {"depth": 5}}}}}},
]  # fmt: skip
NAMES = [("/", "identifier"), ("/robot1", "identifier"), ("/robot2", "identifier"), ("/robot1/arm", "identifier"),
         ("/robot3", "ident3"), ("/", "ident3")]  # fmt: skip


@pytest.mark.ros
def test_the_matcher_gives_what_rclpy_gives_every_node(tmp_path: Path, domain: int) -> None:
    """The reference is rclpy itself: the overrides a real node gets from the same files, for every name."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    files = [write(tmp_path, document, f"doc{number}.yaml") for number, document in enumerate(DOCUMENTS)]
    checked = 0
    for chosen in ([0], [1], [2], [3], [4], [1, 0], [0, 4, 2]):
        paths = [files[i] for i in chosen]
        arguments = ["--ros-args"] + [item for path in paths for item in ("--params-file", str(path))]
        context = Context()
        rclpy.init(args=arguments, context=context, domain_id=domain)
        try:
            for namespace, name in NAMES:
                node = Node(name, namespace=namespace, context=context)
                expected = {key: parameter.value for key, parameter in node._parameter_overrides.items()}
                fully_qualified = node.get_fully_qualified_name()
                node.destroy_node()
                try:
                    ours = read_params_files(paths, fully_qualified)
                except ConfigError:
                    ours = {}
                assert ours == expected, (chosen, fully_qualified)
                checked += 1
        finally:
            context.try_shutdown()
    assert checked == 7 * len(NAMES)
